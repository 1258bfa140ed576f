"""Training of the master and slave networks with Eq. 2 (Guan et al. 2022,
'Neural network training'), evaluation, and compensation with the trained master.

    Loss = E_y[CE(Slave(Master(y)), y)] + l1 * E_xy[L1(Master(y), x)]
         + l2 * E_xy[CE(Slave(x), y)] + l3 * Sparsity_y(Master(y))          # Eq. 2

- x: the mask rescaled to [-1, 1]; y: the print as a two-channel class map (void,
  solid). The master reads y as one channel in [-1, 1] (void -1, solid +1).
- l1 = l2 = 1, l3 = 0.05; l1 is multiplied by 0.98 after every iteration, so the master
  leans on the data first and on the slave later (paper).
- Gaussian noise is added to x for the slave (paper; its size is not given: ``slave_noise``).
- Sparsity: the master's mask in dose units, (Master(y) + 1) / 2 in [0, 1], summed
  outside the target and divided by the number of pixels (a per-pixel mean, so that
  l3 = 0.05 weighs the same at any resolution and batch size).
- Cross-entropy with class probabilities: at full resolution y is one-hot; when training
  on area-downsampled data, a coarse pixel's class probabilities are the void and solid
  fractions of the pixels it covers.
- Who learns from what: the master's parameters follow terms 1, 2 and 4, the slave's
  parameters term 3 only. In term 1 the slave is the (frozen, eval-mode) differentiable
  printer that passes gradients to the master; were it trained by term 1 too, it could
  learn to agree with the master instead of with the printer. Eq. 2's value is logged
  in full.
- Adam, lr 1e-5, betas (0.9, 0.999), batch 10, weights ~ N(0, 0.02) (paper).

Presets (``PRESETS``): "paper" is the paper's run (for a GPU: on a 2-core CPU one epoch
would take about 2.6 h); "default" trains on two CPU cores in 8 to 11 minutes; "ci" takes
seconds. See ``PRESETS`` for the choices and ``benchmarks/bench_training.py`` for the
measurements behind them.

Outputs in ``out_dir``: master.pt, slave.pt, checkpoint.pt (after every epoch; a rerun
resumes from it), log.tsv (every term of Eq. 2, train and test, per epoch), curves.png,
eval.tsv (slave vs simulator, master's masks printed by the simulator, identity masks).
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from . import __version__, metrics
from .io import InputError, claim_output_dir, write_tsv
from .settings import TRAINING

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- settings

DEFAULTS = dict(
    width=64,  # base channels (Fig. 4: 64)
    depth=7,  # stride-2 blocks each way (Fig. 4: 7)
    scale=1,  # train at the field area-downsampled by this factor (1: full resolution)
    crop=None,  # side of random training crops at the training resolution (None: whole field)
    coords=False,  # X, Y of each pixel in the full field as two extra input channels
    epochs=200,  # paper
    batch=10,  # paper
    lr=1e-5,  # paper
    betas=(0.9, 0.999),  # paper: gradient decay 0.9, squared gradient decay 0.999
    lambda1=1.0,  # paper, Eq. 2
    lambda2=1.0,  # paper, Eq. 2
    lambda3=0.05,  # paper, Eq. 2
    lambda1_decay=0.98,  # paper: l1 *= 0.98 every iteration
    slave_noise=0.1,  # std of the Gaussian noise on x for the slave (not given in the paper)
    max_train=None,  # use at most this many training pairs (None: the whole train split)
    max_test=None,  # test pairs for the per-epoch test losses (None: the whole test split)
    eval_pairs=None,  # test pairs for eval.tsv (None: the whole test split)
    seed=TRAINING.default.seed,
)

PRESETS = {
    # Guan et al. 2022: 4,000 pairs at 512 x 512 (3,600 / 400), width 64, 200 epochs,
    # Adam lr 1e-5, batch 10. About 26 h on a GTX 1070 Ti in the paper: for a GPU.
    "paper": dict(),
    # Two CPU cores, 8 to 11 minutes of the 30-minute default run (485 s on idle cores, 670 s
    # in a full run). Deliberate departures from the paper, with the measurements behind
    # them (benchmarks/bench_training.py on a 2-core AMD EPYC, torch 2.13 CPU; "IoU" is the
    # simulator's print of the master's mask vs the target on held-out pairs, next to the
    # identity mask's):
    # - 1,200 pairs (PRESET_PAIRS), 8 epochs (864 iterations of 10): 485 s wall on two idle
    #   cores (780 CPU s), including the per-epoch test losses and eval.tsv.
    # - Train at 256 x 256 (area-downsampled: the 512 field's sigma of ~4 px becomes ~2 px,
    #   still resolved; the master's mask is upsampled back to 512). One Eq. 2 iteration of
    #   10 pairs costs 0.72 CPU s at 256 px and 3.3 at 512 px (width 16). At equal time the
    #   whole field at 256 px beat random 128 px crops of the 512 field (IoU 0.928 after
    #   3 epochs vs 0.916 to 0.919 after 9 epochs of crops, which took 1.6 times longer;
    #   identity 0.905), needs no coordinate channels, and infers four times cheaper.
    # - Width 16: after 6 epochs IoU 0.959 (width 16) vs 0.928 (width 8); width 32 costs
    #   three times more per iteration.
    # - lr 1e-3 instead of 1e-5: after 2 epochs the test loss is 0.063 with 1e-3 and 1.36
    #   with 1e-5 (IoU 0.69, below the identity mask's 0.94): 1e-5 needs the paper's
    #   72,000 iterations.
    "default": dict(width=16, scale=2, crop=None, coords=False, epochs=8, batch=10, lr=1e-3, max_test=60),
    # A smoke test: seconds on a CPU.
    "ci": dict(width=4, scale=4, crop=None, coords=False, epochs=2, batch=4, lr=2e-3, max_train=24, max_test=8, eval_pairs=8),
}

# PRESET_PAIRS (unscatter.settings): the augmentation pairs each preset is sized for.

# Settings that may change between a run and its resumption.
_RESUMABLE = ("epochs", "eval_pairs")


def settings_for(preset: str = TRAINING.default.preset, **overrides) -> dict:
    """The full settings of a preset with ``overrides`` (None values are ignored; the
    user-facing ones are checked against unscatter.settings.TRAINING's bounds)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; known: {sorted(PRESETS)}")
    s = dict(DEFAULTS)
    s.update(PRESETS[preset])
    for k, v in overrides.items():
        if k not in DEFAULTS:
            raise ValueError(f"unknown training setting {k!r}; known: {sorted(DEFAULTS)}")
        if v is not None:
            s[k] = TRAINING.check(k, v) if k in TRAINING.settings else v
    s["betas"] = tuple(float(b) for b in s["betas"])
    _check(s)
    return s


def _check(s: dict) -> None:
    for k in ("width", "depth", "scale", "epochs", "batch"):
        if int(s[k]) != s[k] or s[k] < 1:
            raise ValueError(f"setting {k!r} must be a positive integer, got {s[k]!r}")
    if s["batch"] < 2:
        raise ValueError("batch must be at least 2 (batch norm at a 1 x 1 bottleneck needs two samples)")
    if s["crop"] is not None and (s["crop"] < 2 ** s["depth"] or s["crop"] % 2 ** s["depth"]):
        raise ValueError(f"crop must be a multiple of 2^depth = {2 ** s['depth']}, got {s['crop']}")
    if not s["lr"] > 0:
        raise ValueError("lr must be > 0")


# ------------------------------------------------------------------------------ Eq. 2


def class_map(p: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) solid probability -> (B, 2, H, W) class map (void, solid)."""
    return torch.cat([1 - p, p], dim=1)


def sparsity(master_y: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Eq. 2's sparsity: the mask's dose (master_y + 1) / 2 outside the target,
    summed and divided by the number of pixels (a per-pixel mean)."""
    return (((master_y + 1) / 2) * (1 - p)).mean()


def loss_terms(master_y: torch.Tensor, slave_master_y: torch.Tensor, slave_x: torch.Tensor, x: torch.Tensor, p: torch.Tensor) -> dict:
    """The four terms of Eq. 2 from the networks' outputs.

    master_y: (B, 1, H, W) Master(y) in [-1, 1]; slave_master_y, slave_x: (B, 2, H, W)
    logits of Slave(Master(y)) and Slave(x + noise); x: (B, 1, H, W) mask in [-1, 1];
    p: (B, 1, H, W) probability that the print is solid (y's solid channel).
    """
    y = class_map(p)
    return dict(
        ce_master=F.cross_entropy(slave_master_y, y),  # slave-supported master loss
        l1_master=(master_y - x).abs().mean(),  # data-supported master loss
        ce_slave=F.cross_entropy(slave_x, y),  # data-supported slave loss
        sparsity=sparsity(master_y, p),
    )


def eq2_total(terms: dict, lambda1: float, lambda2: float = 1.0, lambda3: float = 0.05):
    """Eq. 2: CE_master + l1 * L1 + l2 * CE_slave + l3 * sparsity."""
    return terms["ce_master"] + lambda1 * terms["l1_master"] + lambda2 * terms["ce_slave"] + lambda3 * terms["sparsity"]


TERMS = ("ce_master", "l1_master", "ce_slave", "sparsity")


# ------------------------------------------------------------------------------ data


def grid_coords(n: int, scale: int, region_px: int) -> torch.Tensor:
    """Normalised coordinate of the centres of ``n`` grid pixels of ``scale`` design
    pixels each, over a design region of ``region_px`` pixels: -1 at the first design
    pixel centre, +1 at the last (unscatter.model's convention; a grid longer than the
    region, as when padding, runs on past +1)."""
    centre = torch.arange(n, dtype=torch.float64) * scale + (scale - 1) / 2
    half = (region_px - 1) / 2
    return ((centre - half) / half if half > 0 else torch.zeros(n, dtype=torch.float64)).float()


def coord_maps(h: int, w: int, scale: int, region_hw: tuple[int, int]) -> torch.Tensor:
    """(2, h, w): X (along columns) and Y (along rows) of a grid over the region."""
    X = grid_coords(w, scale, region_hw[1])[None, :].expand(h, w)
    Y = grid_coords(h, scale, region_hw[0])[:, None].expand(h, w)
    return torch.stack([X, Y])


def prepare(masks: np.ndarray, prints: np.ndarray, scale: int) -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 masks and bool prints (B, H, W) -> x in [-1, 1] and solid probability p in
    [0, 1], both (B, 1, H / scale, W / scale) (area averages when scale > 1)."""
    x = torch.from_numpy(np.asarray(masks, np.float32) / 255.0)[:, None]
    p = torch.from_numpy(np.asarray(prints, np.float32))[:, None]
    if scale > 1:
        x, p = F.avg_pool2d(x, scale), F.avg_pool2d(p, scale)
    return 2 * x - 1, p


def _inputs(a: torch.Tensor, coords: torch.Tensor | None) -> torch.Tensor:
    """A network input: the image channel, then the coordinate channels (if any)."""
    if coords is None:
        return a
    return torch.cat([a, coords.to(a)], dim=1)


# ----------------------------------------------------------------------- networks


def _build(settings: dict):
    from .nets import master_net, slave_net

    cin = 3 if settings["coords"] else 1
    return master_net(settings["width"], cin, settings["depth"]), slave_net(settings["width"], cin, settings["depth"])


def _net_meta(settings: dict, size: int, kind: str) -> dict:
    return dict(
        kind=kind,
        width=int(settings["width"]),
        depth=int(settings["depth"]),
        in_channels=3 if settings["coords"] else 1,
        coords=bool(settings["coords"]),
        scale=int(settings["scale"]),
        size=int(size),
        unscatter_version=__version__,
    )


def load_net(path, device=None):
    """A trained master or slave (.pt written by ``train``) in eval mode, and its meta."""
    from .nets import master_net, slave_net

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "trained network file does not exist (run `unscatter train` first)")
    try:
        d = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise InputError(path, f"cannot read the network ({exc})") from exc
    meta = d.get("meta") if isinstance(d, dict) else None
    if not meta or meta.get("kind") not in ("master", "slave"):
        raise InputError(path, "not a master or slave network written by `unscatter train`")
    build = master_net if meta["kind"] == "master" else slave_net
    net = build(meta["width"], meta["in_channels"], meta["depth"])
    net.load_state_dict(d["state_dict"])
    net.to(device or _device(None)).eval()
    return net, meta


def _device(device) -> torch.device:
    if device:
        return torch.device(device)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


# ----------------------------------------------------------------- master inference


def _pad_to(a: torch.Tensor, multiple: int, value: float) -> torch.Tensor:
    h, w = a.shape[-2:]
    ph, pw = -h % multiple, -w % multiple
    return F.pad(a, (0, pw, 0, ph), value=value) if (ph or pw) else a


@torch.no_grad()
def master_masks(master, meta: dict, targets: np.ndarray, batch: int = 8) -> np.ndarray:
    """Masks (uint8, B x H x W) for binary targets (B x H x W) from a master in eval mode.

    The target is area-downsampled by the training scale, padded with void to a multiple
    of the network's 2^depth, given its coordinate channels, and the master's mask is
    upsampled back (bilinear) to the design's pixels.
    """
    t = np.asarray(targets)
    if t.ndim == 2:
        t = t[None]
    B, H, W = t.shape
    s, mult = meta["scale"], 2 ** meta["depth"]
    dev = next(master.parameters()).device
    out = np.empty((B, H, W), np.uint8)
    for i in range(0, B, batch):
        y = torch.from_numpy((t[i : i + batch] != 0).astype(np.float32))[:, None]
        y = _pad_to(y, s, 0.0)  # void beyond the design region
        if s > 1:
            y = F.avg_pool2d(y, s)
        h, w = y.shape[-2:]
        y = _pad_to(2 * y - 1, mult, -1.0)
        coords = coord_maps(y.shape[-2], y.shape[-1], s, (H, W))[None].expand(len(y), -1, -1, -1) if meta["coords"] else None
        m = master(_inputs(y.to(dev), coords)).float().cpu()[..., :h, :w]
        dose = (m + 1) / 2
        if s > 1:
            dose = F.interpolate(dose, scale_factor=s, mode="bilinear", align_corners=False)
        dose = dose[:, 0, :H, :W].clamp(0, 1)
        out[i : i + batch] = torch.round(dose * 255).to(torch.uint8).numpy()
    return out


@torch.no_grad()
def slave_prints(slave, meta: dict, masks: np.ndarray, batch: int = 8) -> np.ndarray:
    """Prints (bool, B x H x W) the slave predicts for uint8 masks, at the design's pixels."""
    m = np.asarray(masks)
    if m.ndim == 2:
        m = m[None]
    B, H, W = m.shape
    s, mult = meta["scale"], 2 ** meta["depth"]
    dev = next(slave.parameters()).device
    out = np.empty((B, H, W), bool)
    for i in range(0, B, batch):
        x = _pad_to(torch.from_numpy(m[i : i + batch].astype(np.float32) / 255)[:, None], s, 0.0)
        if s > 1:
            x = F.avg_pool2d(x, s)
        h, w = x.shape[-2:]
        x = _pad_to(2 * x - 1, mult, -1.0)
        coords = coord_maps(x.shape[-2], x.shape[-1], s, (H, W))[None].expand(len(x), -1, -1, -1) if meta["coords"] else None
        logit = slave(_inputs(x.to(dev), coords)).float().cpu()[..., :h, :w]
        if s > 1:
            logit = F.interpolate(logit, scale_factor=s, mode="bilinear", align_corners=False)
        out[i : i + batch] = (logit[:, 1] > logit[:, 0])[:, :H, :W].numpy()
    return out


_CACHE: dict = {}


def compensate_nn(design, train_dir, device=None) -> np.ndarray:
    """The master's mask (uint8, 255 = 100 % dose) for a design (nonzero = solid)."""
    path = Path(train_dir) / "master.pt"
    key = (str(path.resolve()), path.stat().st_mtime_ns if path.is_file() else None, str(device))
    if key not in _CACHE:
        _CACHE.clear()
        _CACHE[key] = load_net(path, device)
    master, meta = _CACHE[key]
    d = np.asarray(design)
    if d.ndim != 2:
        raise ValueError(f"a design is one 2-D image, got shape {d.shape}")
    if d.shape != (meta["size"], meta["size"]):
        log.warning("design %s differs from the training field %d x %d: the printer's field is position dependent", d.shape, meta["size"], meta["size"])
    return master_masks(master, meta, d[None] != 0)[0]


# ----------------------------------------------------------------------------- train


def _dataset_id(ds) -> dict:
    a = ds.attrs
    return dict(seed=a.get("seed"), count=a.get("count"), size=a.get("size"), families=a.get("families"), params=a.get("params", {}).get("parameters"))


@contextlib.contextmanager
def _deterministic():
    prev = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    prev_cudnn = torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic = False, True
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(prev[0], warn_only=prev[1])
        torch.backends.cudnn.benchmark, torch.backends.cudnn.deterministic = prev_cudnn


@contextlib.contextmanager
def _threads(n: int | None):
    """torch's intra-op threads for the duration (None: leave as is)."""
    prev = torch.get_num_threads()
    if n:
        torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(prev)


# What a training folder holds (``train``): a folder with these files only and no marker
# file is a training run from before the marker, and may be resumed or replaced.
TRAIN_FILES = ("master.pt", "slave.pt", "checkpoint.pt", "checkpoint.pt.tmp", "master.pt.tmp", "slave.pt.tmp", "log.tsv",
               "curves.png", "eval.tsv")


def _training_folder(folder: Path) -> bool:
    return all(p.name in TRAIN_FILES for p in folder.iterdir())


def _load_checkpoint(path: Path) -> dict:
    """checkpoint.pt, or an InputError naming it (a truncated file, or not ours)."""
    try:
        c = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several kinds for a damaged file
        raise InputError(path, "cannot read the checkpoint: truncated, or not written by `unscatter train`; "
                               "remove it, or train with --no-resume") from exc
    keys = {"epoch", "iteration", "settings", "dataset", "master", "slave", "opt_master", "opt_slave", "log", "seconds"}
    if not isinstance(c, dict) or not keys <= set(c):
        raise InputError(path, "not a checkpoint of `unscatter train`; remove it, or train with --no-resume")
    return c


def _save_atomic(obj, path: Path) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


def train(
    dataset_zarr,
    out_dir,
    preset: str = TRAINING.default.preset,
    settings: dict | None = None,
    resume: bool | str = True,
    device=None,
    threads: int | None = None,
    progress: bool = True,
) -> dict:
    """Train master and slave on an augmentation store with Eq. 2; write ``out_dir``.

    ``settings`` override the preset's (keys of ``DEFAULTS``). With ``resume`` (the
    default) a checkpoint.pt in ``out_dir`` from the same settings and data is continued
    (a larger ``epochs`` extends a finished run), and one from other settings or data is
    an error (it may be someone's run); ``resume="matching"`` starts over instead (the
    workflow: it reruns training exactly when the dataset or the settings changed);
    ``resume=False`` always starts over. ``out_dir`` is a new folder or an earlier
    training folder (never the dataset, nor another command's output).
    Returns a summary: settings, epochs run, seconds per epoch, final losses, eval rows.
    """
    from tqdm import tqdm

    from .augment import open_dataset

    s = settings_for(preset, **(settings or {}))
    ds = open_dataset(dataset_zarr)
    dev = _device(device)
    size = ds.size
    if size % s["scale"] or (size // s["scale"]) % 2 ** s["depth"]:
        raise ValueError(f"the field ({size} px) / scale {s['scale']} must be a multiple of 2^depth = {2 ** s['depth']}")
    n = size // s["scale"]  # training grid side
    if s["crop"] is not None and s["crop"] > n:
        raise ValueError(f"crop {s['crop']} exceeds the training field {n}")
    train_idx = ds.train[: s["max_train"]]
    test_idx = ds.test[: s["max_test"]]
    if len(train_idx) < 2:
        raise InputError(ds.path, f"the train split has {len(train_idx)} pairs; need at least 2")
    ident = _dataset_id(ds)
    out = claim_output_dir(out_dir, command="train", inputs=[dataset_zarr], recognise=_training_folder)

    with _deterministic(), _threads(threads):
        torch.manual_seed(s["seed"])
        master, slave = _build(s)
        master.to(dev)
        slave.to(dev)
        opt_m = torch.optim.Adam(master.parameters(), lr=s["lr"], betas=s["betas"])
        opt_s = torch.optim.Adam(slave.parameters(), lr=s["lr"], betas=s["betas"])
        state = dict(epoch=0, iteration=0, log=[], seconds=[])
        ck = out / "checkpoint.pt"
        c = _load_checkpoint(ck) if resume and ck.is_file() else None
        if c is not None:
            fixed = {k: v for k, v in s.items() if k not in _RESUMABLE}
            prev = {k: v for k, v in c["settings"].items() if k not in _RESUMABLE}
            if _plain(prev) != _plain(fixed) or _plain(c["dataset"]) != _plain(ident):
                diff = sorted(k for k in set(prev) | set(fixed) if _plain(prev.get(k)) != _plain(fixed.get(k)))
                why = f"the checkpoint is from other settings ({', '.join(diff) or 'dataset'})"
                if resume != "matching":
                    raise ValueError(f"{ck}: {why}; remove it or train with --no-resume")
                log.info("%s: %s; training starts over", ck, why)
                c = None
        if c is not None:
            master.load_state_dict(c["master"])
            slave.load_state_dict(c["slave"])
            opt_m.load_state_dict(c["opt_master"])
            opt_s.load_state_dict(c["opt_slave"])
            state = dict(epoch=int(c["epoch"]), iteration=int(c["iteration"]), log=list(c["log"]), seconds=list(c["seconds"]))
            log.info("resuming from %s after epoch %d", ck, state["epoch"])

        full_coords = coord_maps(n, n, s["scale"], (size, size)) if s["coords"] else None
        for epoch in range(state["epoch"], s["epochs"]):
            t0 = time.perf_counter()
            rows, state["iteration"] = _train_epoch(
                ds, train_idx, master, slave, opt_m, opt_s, s, epoch, state["iteration"], n, size, dev, progress, tqdm
            )
            lam1 = s["lambda1"] * s["lambda1_decay"] ** state["iteration"]
            test = _test_epoch(ds, test_idx, master, slave, s, lam1, full_coords, dev)
            sec = time.perf_counter() - t0
            state["seconds"].append(sec)
            state["log"].append(dict(epoch=epoch + 1, split="train", lambda1=rows["lambda1"], **{k: rows[k] for k in TERMS + ("total",)}, seconds=sec))
            if test:
                state["log"].append(dict(epoch=epoch + 1, split="test", lambda1=lam1, **test, seconds=""))
            state["epoch"] = epoch + 1
            _save_atomic(
                dict(
                    epoch=state["epoch"],
                    iteration=state["iteration"],
                    settings=_plain(s),
                    dataset=_plain(ident),
                    master=master.state_dict(),
                    slave=slave.state_dict(),
                    opt_master=opt_m.state_dict(),
                    opt_slave=opt_s.state_dict(),
                    log=state["log"],
                    seconds=state["seconds"],
                ),
                ck,
            )
            _write_log(out / "log.tsv", state["log"])
            log.info(
                "epoch %d/%d: train total %.4f (CE master %.4f, L1 %.4f, CE slave %.4f, sparsity %.4f), %.1f s",
                epoch + 1, s["epochs"], rows["total"], rows["ce_master"], rows["l1_master"], rows["ce_slave"], rows["sparsity"], sec,
            )

        master.eval()
        slave.eval()
        for kind, net in (("master", master), ("slave", slave)):
            _save_atomic(dict(meta=_net_meta(s, size, kind), settings=_plain(s), state_dict=net.state_dict()), out / f"{kind}.pt")
        _write_log(out / "log.tsv", state["log"])
        _plot_curves(out / "curves.png", state["log"])
        eval_rows = evaluate(ds, ds.test[: s["eval_pairs"]], master, slave, _net_meta(s, size, "master"))
        write_tsv(out / "eval.tsv", eval_rows, EVAL_COLUMNS)
    last = [r for r in state["log"] if r["split"] == "train"]
    return dict(
        settings=s,
        epochs=state["epoch"],
        iterations=state["iteration"],
        seconds_per_epoch=state["seconds"],
        final=last[-1] if last else None,
        eval=eval_rows,
        device=str(dev),
    )


def _plain(v):
    """Settings as plain comparable values (tuples as lists)."""
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def _prefetched(ds, index_lists: list):
    """``ds.pairs`` of each index list in turn, read one batch ahead in a thread, so
    that reading and decompressing overlap the training step."""
    from concurrent.futures import ThreadPoolExecutor

    if not index_lists:
        return
    with ThreadPoolExecutor(1) as ex:
        nxt = ex.submit(ds.pairs, index_lists[0])
        for k in range(len(index_lists)):
            cur = nxt.result()
            if k + 1 < len(index_lists):
                nxt = ex.submit(ds.pairs, index_lists[k + 1])
            yield cur


def _crop(a: torch.Tensor, offsets: np.ndarray, crop: int) -> torch.Tensor:
    return torch.stack([a[i, :, r : r + crop, c : c + crop] for i, (r, c) in enumerate(offsets)])


def _train_epoch(ds, train_idx, master, slave, opt_m, opt_s, s, epoch, iteration, n, size, dev, progress, tqdm):
    """One pass over the training split; returns the mean terms and the new iteration."""
    rng = np.random.default_rng([s["seed"], epoch])  # the epoch's order, crops and noise depend on (seed, epoch) only
    gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
    order = rng.permutation(train_idx)
    crop = s["crop"] or n
    offsets = rng.integers(0, n - crop + 1, size=(len(order), 2))
    bs = s["batch"]
    batches = [slice(i, min(i + bs, len(order))) for i in range(0, len(order), bs)]
    if len(batches) > 1 and batches[-1].stop - batches[-1].start < 2:
        batches = batches[:-1]  # batch norm needs two samples
    sums = {k: 0.0 for k in TERMS + ("total", "lambda1")}
    count = 0
    master.train()
    slave.train()
    bar = tqdm(batches, desc=f"epoch {epoch + 1}/{s['epochs']}", unit="batch", disable=not progress, leave=False)
    for sl, (masks, prints) in zip(bar, _prefetched(ds, [order[b] for b in batches])):
        x, p = prepare(masks, prints, s["scale"])
        coords = None
        if s["coords"]:
            full = coord_maps(n, n, s["scale"], (size, size))[None].expand(len(x), -1, -1, -1)
            coords = _crop(full, offsets[sl], crop) if crop < n else full
        if crop < n:
            x, p = _crop(x, offsets[sl], crop), _crop(p, offsets[sl], crop)
        noise = torch.randn(x.shape, generator=gen) * s["slave_noise"]
        x, p, noise = x.to(dev), p.to(dev), noise.to(dev)
        y_in = 2 * p - 1
        lam1 = s["lambda1"] * s["lambda1_decay"] ** iteration

        opt_m.zero_grad(set_to_none=True)
        opt_s.zero_grad(set_to_none=True)
        # term 3 trains the slave on (x + noise, y)
        slave_x = slave(_inputs(x + noise, coords))
        master_y = master(_inputs(y_in, coords))
        # term 1: the slave as a frozen differentiable printer for the master
        slave.eval()
        slave.requires_grad_(False)
        slave_master_y = slave(_inputs(master_y, coords))
        slave.requires_grad_(True)
        slave.train()
        # slave_x depends on the slave only, slave_master_y (frozen slave) on the master only
        terms = loss_terms(master_y, slave_master_y, slave_x, x, p)
        total = eq2_total(terms, lam1, s["lambda2"], s["lambda3"])
        total.backward()
        opt_m.step()
        opt_s.step()
        iteration += 1

        k = len(x)
        for name in TERMS:
            sums[name] += terms[name].item() * k
        sums["total"] += total.item() * k
        sums["lambda1"] += lam1 * k
        count += k
        bar.set_postfix(total=f"{total.item():.3f}", ce_slave=f"{terms['ce_slave'].item():.3f}")
    bar.close()
    return {k: v / max(count, 1) for k, v in sums.items()}, iteration


@torch.no_grad()
def _test_epoch(ds, test_idx, master, slave, s, lam1, full_coords, dev) -> dict | None:
    """Eq. 2's terms on the test split (whole field, eval mode, no noise)."""
    if len(test_idx) == 0:
        return None
    master.eval()
    slave.eval()
    sums = {k: 0.0 for k in TERMS + ("total",)}
    chunks = [test_idx[i : i + s["batch"]] for i in range(0, len(test_idx), s["batch"])]
    for masks, prints in _prefetched(ds, chunks):
        x, p = prepare(masks, prints, s["scale"])
        x, p = x.to(dev), p.to(dev)
        coords = full_coords[None].expand(len(x), -1, -1, -1) if full_coords is not None else None
        master_y = master(_inputs(2 * p - 1, coords))
        terms = loss_terms(master_y, slave(_inputs(master_y, coords)), slave(_inputs(x, coords)), x, p)
        total = eq2_total(terms, lam1, s["lambda2"], s["lambda3"])
        for name in TERMS:
            sums[name] += float(terms[name]) * len(x)
        sums["total"] += float(total) * len(x)
    return {k: v / len(test_idx) for k, v in sums.items()}


LOG_COLUMNS = ["epoch", "split", "lambda1", *TERMS, "total", "seconds"]


def _write_log(path: Path, rows: list[dict]) -> None:
    write_tsv(path, rows, LOG_COLUMNS)


def _plot_curves(path: Path, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    names = ("total",) + TERMS
    titles = dict(
        total="Eq. 2 total",
        ce_master="CE(Slave(Master(y)), y)",
        l1_master="L1(Master(y), x)",
        ce_slave="CE(Slave(x), y)",
        sparsity="Sparsity(Master(y))",
    )
    fig, axes = plt.subplots(1, len(names), figsize=(3.2 * len(names), 3.0), constrained_layout=True)
    for ax, k in zip(axes, names):
        for split, style in (("train", "-"), ("test", "--")):
            r = [row for row in rows if row["split"] == split]
            if r:
                ax.plot([row["epoch"] for row in r], [row[k] for row in r], style, marker="o", ms=3, label=split)
        ax.set_title(titles[k], fontsize=9)
        ax.set_xlabel("epoch")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        if k != "sparsity":
            ax.set_yscale("log")
    axes[0].legend(fontsize=8)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# -------------------------------------------------------------------------- evaluate

EVAL_COLUMNS = ["method", "family", "n", "iou", "pixel_error", "pixel_accuracy", "compares"]
_COMPARES = dict(
    slave="slave-predicted print vs simulated print of the dataset mask",
    master="simulated print of the master's mask vs target",
    identity="simulated print of the target used as mask vs target",
)


def evaluate(ds, idx, master, slave, meta: dict, batch: int = 8) -> list[dict]:
    """eval.tsv rows on held-out pairs, per family and over all: the slave against the
    simulator, and the simulator's prints of the master's masks and of identity masks
    (the target itself as the mask) against the target (unscatter.model, unscatter.metrics)."""
    from .model import simulate

    params = ds.params()
    names = ds.attrs["family_names"]
    fam_all = np.asarray(ds.group["family"][:])
    per = {m: [] for m in ("slave", "master", "identity")}
    fams = []
    for i in range(0, len(idx), batch):
        j = np.asarray(idx[i : i + batch])
        masks, prints = ds.pairs(j)
        pred = slave_prints(slave, meta, masks)
        comp = master_masks(master, meta, prints)
        pm = simulate(params, list(comp), batch=len(comp))
        pi = simulate(params, list(prints.astype(np.uint8) * 255), batch=len(comp))
        for k in range(len(j)):
            per["slave"].append(_scores(pred[k], prints[k]))
            per["master"].append(_scores(pm[k], prints[k]))
            per["identity"].append(_scores(pi[k], prints[k]))
            fams.append(names[int(fam_all[j[k]])])
    rows = []
    fams = np.array(fams, dtype=object)
    for method in ("slave", "master", "identity"):
        sc = per[method]
        for fam in ["all"] + [f for f in names if f in set(fams)]:
            sel = [k for k in range(len(sc)) if fam == "all" or fams[k] == fam]
            if not sel:
                continue
            rows.append(
                dict(
                    method=method,
                    family=fam,
                    n=len(sel),
                    **{m: float(np.nanmean([sc[k][m] for k in sel])) for m in ("iou", "pixel_error", "pixel_accuracy")},
                    compares=_COMPARES[method],
                )
            )
    return rows


def _scores(printed: np.ndarray, target: np.ndarray) -> dict:
    with np.errstate(invalid="ignore"):
        return dict(
            iou=metrics.iou(printed, target),
            pixel_error=metrics.pixel_error(printed, target),
            pixel_accuracy=float(np.mean(np.asarray(printed, bool) == np.asarray(target, bool))),
        )
