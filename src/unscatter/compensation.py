"""Compensation of designs: masks that print what was designed (Guan et al. 2022,
'Results', Fig. 5), by three methods.

- ``nn``: the trained master network's mask (``training.compensate_nn``; the paper).
- ``ilt``: the mask optimised for the design directly, by gradient descent through the
  calibrated printer simulator (Eq. 1 with the smooth threshold), as inverse lithography
  does in chip making. The mask is ``255 * sigmoid(z)`` (so it stays in [0, 255]); the
  loss is the edge-weighted squared mismatch between the smooth print and the design,
  plus a sparsity term on mask dose outside the design dilated by a margin; with
  ``robust`` it is the mean over 90, 100 and 110 % of the nominal dose (what the PV
  band measures). Adam for a fixed number of steps, coarse to fine: most steps run on
  the design region downsampled 4x and 2x (the model evaluates Eq. 1 on a coarser grid
  exactly, since the kernel removes what the coarse grid cannot hold), the last ones at
  full resolution; the threshold's temperature anneals from soft to nearly hard.
- ``nn+ilt``: the network's mask as the start of a few ILT steps.

Outputs: the 8-bit mask of the design region, and the full DMD frame (2560 x 1600
mirrors; Guan et al. 2022, 'Bioprinting setup') with the mask placed at an offset
(centred by default) and every other mirror off.

Nothing here imports the virtual lab: the printer is known only through params.yaml.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage

from .io import InputError, list_pngs, output_dir, read_mask, write_png, write_tsv, write_yaml
from . import settings as S
from .model import Params, default_device, load_params

log = logging.getLogger(__name__)

METHODS = S.METHODS

# Guan et al. 2022, 'Bioprinting setup': the DMD has 2560 x 1600 micro-mirrors (rows, cols here).
DMD_FRAME = (1600, 2560)

# ILT settings. Timings and the choice of these numbers: benchmarks/bench_compensation.py.
ILT_DEFAULTS = dict(
    # (grid pixel in design pixels, Adam steps), coarse to fine; the last stage must be 1.
    # ~0.4 s per 512 x 512 design on one core; longer schedules gain < 1e-4 IoU (the sweep).
    schedule=((4, 60), (2, 40), (1, 20)),
    lr=0.25,  # Adam step on the mask's logits
    temperature=(0.3, 0.03),  # smooth threshold's width as a fraction of T: start, end (geometric)
    edge_weight=3.0,  # extra weight of pixels within edge_px of the design's edge
    edge_px=None,  # None: one kernel sigma (a quarter of the model's kernel support)
    sparsity=0.02,  # weight of the mean mask dose outside the dilated design
    margin_px=None,  # dilation of the design for the sparsity term; None: two kernel sigmas
    robust=S.COMPENSATION.default.robust,  # optimise over 90/100/110 % of the nominal dose at once
    doses=(0.9, 1.0, 1.1),  # the robust doses (docs/design.md, 'Metrics': the PV band's 90 and 110 %)
    init_logit=3.0,  # start: sigmoid(+-3) = 0.95 / 0.05 dose; also the clip of a given start mask
    # torch CPU threads while optimising (None: leave torch's setting). One: a second thread
    # gains ~10 % on these small FFTs and loses several times that on a busy machine.
    threads=1,
    device=None,  # torch device (None: cuda if available, else cpu)
)

# nn+ilt: the network's mask is already close, so a short, cooler refinement (~0.17 s).
NN_ILT_DEFAULTS = dict(ILT_DEFAULTS, schedule=((2, 16), (1, 8)), temperature=(0.1, 0.03), lr=0.2)


# --------------------------------------------------------------------------- inputs


def load_printer(model) -> Params:
    """A calibrated printer: a Params, a params file, or a model folder holding one
    (a calibration's params.yaml, a diagnosis's model.yaml)."""
    if isinstance(model, Params):
        return model
    if model is None:
        raise ValueError("ILT needs the calibrated printer model (params.yaml or a calibration folder)")
    return load_params(model)


def as_design(design) -> np.ndarray:
    """A design (bool, uint8 0/255, or a path to a PNG) as a 2-D bool array (True = solid)."""
    if isinstance(design, (str, Path)):
        design = read_mask(design)
    d = np.asarray(design)
    if d.ndim != 2:
        raise ValueError(f"a design is one 2-D image, got shape {d.shape}")
    return d != 0


def _settings(defaults: dict, given: dict) -> dict:
    unknown = sorted(set(given) - set(defaults))
    if unknown:
        raise ValueError(f"unknown compensation setting(s) {unknown}; known: {sorted(defaults)}")
    s = dict(defaults)
    s.update({k: v for k, v in given.items() if v is not None})
    sched = tuple((int(a), int(b)) for a, b in s["schedule"])
    if not sched or sched[-1][0] != 1:
        raise ValueError(f"the ILT schedule must end at full resolution (scale 1), got {sched}")
    if any(a < 1 or b < 0 for a, b in sched):
        raise ValueError(f"ILT schedule entries are (scale >= 1, steps >= 0), got {sched}")
    s["schedule"] = sched
    t0, t1 = (float(t) for t in s["temperature"])
    if not (t0 > 0 and t1 > 0):
        raise ValueError("the threshold temperatures must be > 0")
    s["temperature"] = (t0, t1)
    return s


@contextlib.contextmanager
def _torch_threads(n):
    if not n:
        yield
        return
    old = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old)


# ------------------------------------------------------------------------------ ILT


def _pool(a: torch.Tensor, s: int) -> torch.Tensor:
    return F.avg_pool2d(a, s) if s > 1 else a


def coarse_to_fine(z: torch.Tensor, stages, lr: float, temperatures, targets, loss_fn) -> tuple[torch.Tensor, list]:
    """Adam on mask logits ``z`` (N, 1, H, W) over ``stages`` of (grid scale, steps),
    coarse to fine: the logits are carried to each grid (averaged down at the start,
    bilinear up later), ``targets`` ((N, 1, H, W) tensors) are averaged to it, and the
    smooth threshold's temperature falls geometrically from the first to the second of
    ``temperatures`` over all steps. ``loss_fn(z, scale, temperature, pooled targets)``
    gives the loss. Returns the logits on the last grid and the loss per step."""
    total = max(sum(n for _, n in stages), 1)
    (t0, t1), step, losses, scale = temperatures, 0, [], None
    for sc, n in stages:
        z = _pool(z, sc) if scale is None else F.interpolate(z, scale_factor=scale / sc, mode="bilinear", align_corners=False)
        scale = sc
        if n == 0:
            continue
        pooled = [_pool(t, sc)[:, 0] for t in targets]
        z = z.detach().requires_grad_(True)
        opt = torch.optim.Adam([z], lr=float(lr))
        for _ in range(n):
            temperature = t0 * (t1 / t0) ** (step / max(total - 1, 1))
            step += 1
            opt.zero_grad(set_to_none=True)
            loss = loss_fn(z, sc, temperature, pooled)
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
    return z, losses


def optimise_mask(design, params, init=None, **settings) -> tuple[np.ndarray, dict]:
    """ILT: the uint8 mask whose simulated print matches ``design``, and a summary.

    ``params``: a Params, a params.yaml, or a calibration folder. ``init``: a uint8 start
    mask (e.g. the network's); default the design itself. ``settings``: see
    ``ILT_DEFAULTS``. The summary holds the loss per step, the seconds taken, and the
    model's (hard-threshold) IoU of the result and of the identical mask.
    """
    s = _settings(ILT_DEFAULTS, settings)
    p = load_printer(params)
    d = as_design(design)
    H, W = d.shape
    dev = torch.device(s["device"]) if s["device"] else default_device()
    model = p.build()
    t_start = time.perf_counter()
    with _torch_threads(s["threads"]):
        theta = model.theta(p.values, dev)
        sigma = model.support_px(p) / 4.0  # the kernel support is 4 sigma
        edge_px = float(s["edge_px"]) if s["edge_px"] is not None else sigma
        margin = int(math.ceil(s["margin_px"] if s["margin_px"] is not None else 2.0 * sigma))

        # edge-weighted target, and where the sparsity term counts (all at full resolution)
        dist = np.where(d, ndimage.distance_transform_edt(d), ndimage.distance_transform_edt(~d))
        weight = 1.0 + float(s["edge_weight"]) * (dist <= edge_px)
        far = ~ndimage.binary_dilation(d, iterations=margin) if margin > 0 else ~d
        full = lambda a: torch.from_numpy(np.asarray(a, np.float32))[None, None].to(dev)  # noqa: E731
        y, w, outside = full(d), full(weight), full(far)

        c = float(s["init_logit"])
        if init is None:
            z = (2 * y - 1) * c
        else:
            m0 = np.asarray(init)
            if m0.shape != d.shape:
                raise ValueError(f"start mask {m0.shape} and design {d.shape} differ in size")
            m0 = torch.from_numpy(m0.astype(np.float32) / 255.0).clamp(1e-6, 1 - 1e-6)
            z = torch.logit(m0).clamp(-c, c)[None, None].to(dev)

        doses = tuple(float(k) for k in s["doses"]) if s["robust"] else (1.0,)
        stages = [(sc, n) for sc, n in s["schedule"] if H % sc == 0 and W % sc == 0]
        skipped = [sc for sc, _n in s["schedule"] if H % sc or W % sc]
        if skipped:
            log.info("ILT: skipping grid scales %s that do not divide the design %s", skipped, d.shape)

        def loss_fn(z, sc, temperature, pooled):
            ys, ws, os_ = pooled
            m = torch.sigmoid(z[:, 0])
            dose = model.dose(m, theta, scale=sc)[0]  # (1, h, w): Eq. 1 before the threshold
            mismatch = 0.0
            for k in doses:  # the dose is linear in the mask: k x nominal dose is k * dose
                printed = model.threshold.apply(k * dose, theta, temperature)
                mismatch = mismatch + (ws * (printed - ys) ** 2).sum() / ws.sum()
            return mismatch / len(doses) + float(s["sparsity"]) * (m * os_).mean()

        z, losses = coarse_to_fine(z, stages, s["lr"], s["temperature"], (y, w, outside), loss_fn)
        step = len(losses)
        mask = torch.round(torch.sigmoid(z.detach())[0, 0] * 255).to(torch.uint8).cpu().numpy()
        seconds = time.perf_counter() - t_start
        with torch.no_grad():
            both = torch.from_numpy(np.stack([mask, d.astype(np.uint8) * 255]).astype(np.float32) / 255).to(dev)
            hard = model.prints(both, theta)[0].cpu().numpy()
    from .metrics import iou

    info = dict(
        seconds=seconds,
        steps=step,
        loss=losses,
        model_iou=iou(hard[0], d),
        identical_model_iou=iou(hard[1], d),
        settings={k: v for k, v in s.items() if k not in ("device", "threads")},
    )
    return mask, info


def compensate_ilt(design, params, init=None, **settings) -> np.ndarray:
    """The ILT mask (uint8) for a design; see ``optimise_mask``."""
    return optimise_mask(design, params, init=init, **settings)[0]


def _nn_mask(design: np.ndarray, train_dir, device=None) -> np.ndarray:
    if train_dir is None:
        raise ValueError("the nn methods need a training folder (master.pt from `unscatter train`)")
    try:
        from .training import compensate_nn
    except ImportError as exc:  # the network code is a separate piece of work
        raise RuntimeError(f"the nn method needs unscatter.training.compensate_nn, which is not available ({exc})") from exc
    return compensate_nn(design.astype(np.uint8) * 255, train_dir, device=device)


def compensate(design, method: str, params_path=None, train_dir=None, **settings) -> np.ndarray:
    """The uint8 mask (255 = 100 % dose) that prints ``design`` by one of ``METHODS``.

    - ``ilt``: needs ``params_path`` (params.yaml, a calibration folder, or a Params).
    - ``nn``: needs ``train_dir`` (a training folder with master.pt).
    - ``nn+ilt``: needs both; ``settings`` default to ``NN_ILT_DEFAULTS``.
    """
    if method not in METHODS:
        raise ValueError(f"unknown compensation method {method!r}; known: {', '.join(METHODS)}")
    d = as_design(design)
    if method == "ilt":
        return optimise_mask(d, params_path, **settings)[0]
    with _torch_threads(settings.get("threads")):
        start = _nn_mask(d, train_dir, settings.get("device"))
    if method == "nn":
        if set(settings) - {"device", "threads"}:
            log.info("nn: ILT settings %s ignored", sorted(set(settings) - {"device", "threads"}))
        return start
    if params_path is None:
        raise ValueError("nn+ilt refines the network's mask with ILT: it needs the calibrated params.yaml too")
    given = {k: v for k, v in settings.items() if v is not None}
    return optimise_mask(d, params_path, init=start, **{**NN_ILT_DEFAULTS, **given})[0]


# ------------------------------------------------------------------------ DMD frame


def frame_offset(shape: tuple[int, int], frame: tuple[int, int] = DMD_FRAME,
                 offset: tuple[int, int] | None = None) -> tuple[int, int]:
    """Where a mask of ``shape`` goes in the DMD frame (default centred); ValueError when it
    does not fit. Cheap, so callers check a design before optimising its mask."""
    fh, fw = (int(v) for v in frame)
    h, w = (int(v) for v in shape)
    if offset is None:
        offset = ((fh - h) // 2, (fw - w) // 2)
    oy, ox = (int(v) for v in offset)
    if oy < 0 or ox < 0 or oy + h > fh or ox + w > fw:
        raise ValueError(f"a {h}x{w} mask at offset ({oy}, {ox}) does not fit the {fh}x{fw} DMD frame")
    return oy, ox


def dmd_frame(mask: np.ndarray, frame: tuple[int, int] = DMD_FRAME, offset: tuple[int, int] | None = None) -> tuple[np.ndarray, tuple[int, int]]:
    """The full DMD frame (rows, cols) with ``mask`` at ``offset`` (row, col of its top-left
    mirror; default centred) and every other mirror off; and the offset used."""
    m = np.asarray(mask)
    if m.dtype != np.uint8 or m.ndim != 2:
        raise ValueError(f"a mask is a 2-D uint8 image, got {m.dtype} {m.shape}")
    h, w = m.shape
    oy, ox = frame_offset(m.shape, frame, offset)
    fh, fw = (int(v) for v in frame)
    out = np.zeros((fh, fw), np.uint8)
    out[oy : oy + h, ox : ox + w] = m
    return out, (oy, ox)


def write_mask_and_frame(mask, out_png, frame_png=None, frame=DMD_FRAME, offset=None) -> tuple[int, int]:
    """Write the design-region mask and (if ``frame_png``) the full DMD frame; returns the offset."""
    full, off = dmd_frame(mask, frame, offset)  # checks before anything is written
    write_png(out_png, np.asarray(mask, np.uint8))
    if frame_png is not None:
        write_png(frame_png, full)
    return off


# ------------------------------------------------------------------- a folder of designs


def select_designs(designs_dir, names=None) -> dict:
    """name -> path of the design PNGs of a folder; ``names`` (if given) picks some of them."""
    designs = list_pngs(designs_dir)
    if not designs:
        raise InputError(designs_dir, "no design .png files")
    if names:
        missing = sorted(set(names) - set(designs))
        if missing:
            raise InputError(designs_dir, f"no design {', '.join(missing)} (.png) here; there are {', '.join(sorted(designs))}")
        designs = {k: designs[k] for k in names}
    return designs


def compensate_designs(designs_dir, out_dir, method: str, params_path=None, train_dir=None, frames: bool = True,
                       frame=DMD_FRAME, offset=None, names=None, **settings) -> list[dict]:
    """Compensate every design PNG of a folder (or those in ``names``): ``out_dir/<design>.png``,
    the DMD frames in ``out_dir/frames/<design>.png``, and ``out_dir/compensation.tsv``.
    Every design is checked against the DMD frame, and the printer loaded once, before
    the first mask is optimised."""
    designs = {name: as_design(read_mask(path)) for name, path in select_designs(designs_dir, names).items()}
    for name, d in designs.items():
        try:
            frame_offset(d.shape, frame, offset)
        except ValueError as exc:
            raise InputError(Path(designs_dir) / f"{name}.png", str(exc)) from None
    printer = load_printer(params_path) if method != "nn" and params_path is not None else params_path
    rows = []
    with output_dir(out_dir, command="compensate", inputs=[designs_dir, params_path, train_dir]) as tmp:
        for name, d in designs.items():
            t = time.perf_counter()
            mask = compensate(d, method, params_path=printer, train_dir=train_dir, **settings)
            seconds = time.perf_counter() - t
            off = write_mask_and_frame(mask, tmp / f"{name}.png", tmp / "frames" / f"{name}.png" if frames else None, frame, offset)
            rows.append(dict(design=name, method=method, seconds=seconds, offset_row=off[0], offset_col=off[1],
                             mean_grey=float(mask.mean()), height=mask.shape[0], width=mask.shape[1]))
            log.info("%s: %s mask in %.2f s", name, method, seconds)
        write_tsv(tmp / "compensation.tsv", rows)
        write_yaml(tmp / "compensation.yaml", dict(method=method, params=str(params_path) if params_path is not None else None,
                                                   train_dir=str(train_dir) if train_dir is not None else None,
                                                   frame=list(frame), settings={k: v for k, v in settings.items()}))
    return rows
