"""Multi-layer compensation: all layer masks of a 3-D design optimised at once (ILT)
through the multi-layer printer model (``model.layer_dose``).

Every layer's light reaches the layers below it, so a layer mask cannot be chosen alone:
an overhang's own layers cure the void beneath them, channels close from above, walls
thicken with the light of every layer over them. The masks of all layers are the
variables of one optimisation: Adam on their logits, the smooth threshold cooled as in
2-D (``compensation.optimise_mask``), coarse to fine, with the same edge weighting and
sparsity term; each layer's exposure is bounded (``exposure_max`` of full grey).

The baseline is the identical layer masks (the design itself) at the best uniform dose:
the grey level that maximises the model's 3-D IoU (``best_uniform_dose``).

The depth parameters (``model.DEPTH_PARAMS``) are read from a depth file (YAML:
att_length_um, diffusion_um, layer_um), written by a 3-D calibration or by hand.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from .compensation import coarse_to_fine
from .io import InputError, read_mask, read_yaml
from .model import DEPTH_PARAMS, Params, default_device, layer_dose, load_params

log = logging.getLogger(__name__)

ILT3D_DEFAULTS = dict(
    # (grid pixel in design pixels, Adam steps), coarse to fine; the last stage must be 1
    schedule=((4, 40), (2, 25), (1, 10)),
    lr=0.25,
    temperature=(0.3, 0.03),
    edge_weight=3.0,
    edge_px=None,  # None: one kernel sigma
    sparsity=0.02,
    margin_px=None,  # None: two kernel sigmas
    exposure_max=1.0,  # each layer's mask stays at or below this share of full grey
    init_logit=3.0,
    threads=1,
    device=None,
)
UNIFORM_DOSES = tuple(np.round(np.linspace(0.3, 1.0, 15), 3))


def load_depth(path) -> dict:
    """att_length_um, diffusion_um and layer_um from a depth file, each checked against its
    bounds (InputError naming the file)."""
    d = read_yaml(path)
    if not isinstance(d, dict):
        raise InputError(path, "a depth file is a mapping: att_length_um, diffusion_um, layer_um")
    out = {}
    for spec in DEPTH_PARAMS:
        v = d.get(spec.name)
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not spec.bounds[0] <= v <= spec.bounds[1]:
            raise InputError(path, f"{spec.name} must be a number in [{spec.bounds[0]:g}, {spec.bounds[1]:g}], found {v!r}")
        out[spec.name] = float(v)
    lu = d.get("layer_um")
    if not isinstance(lu, (int, float)) or isinstance(lu, bool) or not 1 <= lu <= 1000:
        raise InputError(path, f"layer_um must be a layer thickness in um (1 to 1000), found {lu!r}")
    out["layer_um"] = float(lu)
    unknown = sorted(set(d) - set(out))
    if unknown:
        raise InputError(path, f"unknown key(s) {', '.join(unknown)}; a depth file has att_length_um, diffusion_um, layer_um")
    return out


def read_design3d(folder) -> np.ndarray:
    """A 3-D design: ``folder`` holds one PNG a layer (nonzero = solid), bottom first by
    name. Returns (L, H, W) bool."""
    folder = Path(folder)
    files = sorted(p for p in folder.glob("*.png") if not p.name.startswith("."))
    if not files:
        raise InputError(folder, "a 3-D design is a folder of layer PNGs (bottom first); none here")
    layers = [read_mask(p) > 0 for p in files]
    if len({m.shape for m in layers}) != 1:
        raise InputError(folder, "the layers differ in size")
    return np.stack(layers)


def best_uniform_dose(design: np.ndarray, params: Params, depth: dict, pixel_size_um: float,
                      doses=UNIFORM_DOSES, device=None) -> tuple[float, float]:
    """(dose, 3-D IoU): the grey level of the identical layer masks that the model prints
    best (the dose is linear in the grey level, so one simulation serves every level)."""
    from .metrics import iou

    dev = torch.device(device) if device else default_device()
    model = params.build()
    theta = model.theta(params.values, dev)
    with torch.no_grad():
        dose = layer_dose(model, torch.from_numpy(design.astype(np.float32)).to(dev), theta, depth,
                          depth["layer_um"], pixel_size_um)[0]
        T = theta["T"].reshape(-1)[0]
        scores = [iou((k * dose >= T).cpu().numpy(), design) for k in doses]
    i = int(np.argmax(scores))
    return float(doses[i]), float(scores[i])


def optimise_layers(design: np.ndarray, params, depth: dict, pixel_size_um: float | None = None,
                    **settings) -> tuple[np.ndarray, dict]:
    """ILT over all layers: the uint8 layer masks (L, H, W) whose multi-layer print
    matches ``design`` (L, H, W bool), and a summary (loss per step, seconds, the model's
    3-D IoU of the result and of the identical masks at the best uniform dose)."""
    unknown = sorted(set(settings) - set(ILT3D_DEFAULTS))
    if unknown:
        raise ValueError(f"unknown 3-D compensation setting(s) {unknown}; known: {sorted(ILT3D_DEFAULTS)}")
    s = {**ILT3D_DEFAULTS, **{k: v for k, v in settings.items() if v is not None}}
    if not s["schedule"] or s["schedule"][-1][0] != 1:
        raise ValueError("the schedule must end at full resolution (scale 1)")
    if not 0 < float(s["exposure_max"]) <= 1:
        raise ValueError("exposure_max must be in (0, 1]")
    p = params if isinstance(params, Params) else load_params(params)
    px = float(pixel_size_um or p.pixel_size_um or 0)
    if not px > 0:
        raise ValueError("the DMD pixel size is needed (params.yaml's pixel_size_um, or pixel_size_um=)")
    d = np.asarray(design, bool)
    if d.ndim != 3:
        raise ValueError(f"a 3-D design is (layers, rows, cols), got shape {d.shape}")
    L, H, W = d.shape
    dev = torch.device(s["device"]) if s["device"] else default_device()
    model = p.build()
    t_start = time.perf_counter()
    old = torch.get_num_threads()
    if s["threads"]:
        torch.set_num_threads(int(s["threads"]))
    try:
        theta = model.theta(p.values, dev)
        sigma = model.support_px(p) / 4.0
        edge_px = float(s["edge_px"]) if s["edge_px"] is not None else sigma
        margin = int(math.ceil(s["margin_px"] if s["margin_px"] is not None else 2.0 * sigma))
        weight = np.empty(d.shape, np.float32)
        far = np.empty(d.shape, bool)
        for j in range(L):
            dist = np.where(d[j], ndimage.distance_transform_edt(d[j]), ndimage.distance_transform_edt(~d[j]))
            weight[j] = 1.0 + float(s["edge_weight"]) * (dist <= edge_px)
            far[j] = ~ndimage.binary_dilation(d[j], iterations=margin) if margin > 0 and d[j].any() else ~d[j]
        full = lambda a: torch.from_numpy(np.asarray(a, np.float32)).to(dev)  # noqa: E731
        y, w, outside = full(d), full(weight), full(far)
        c = float(s["init_logit"])
        z = ((2 * y - 1) * c)[:, None]  # (L, 1, H, W)
        emax = float(s["exposure_max"])
        stages = [(sc, n) for sc, n in s["schedule"] if H % sc == 0 and W % sc == 0]

        def loss_fn(z, sc, temperature, pooled):
            ys, ws, os_ = pooled
            m = emax * torch.sigmoid(z[:, 0])
            dose = layer_dose(model, m, theta, depth, depth["layer_um"], px, scale=sc)[0]
            printed = model.threshold.apply(dose, theta, temperature)
            return (ws * (printed - ys) ** 2).sum() / ws.sum() + float(s["sparsity"]) * (m * os_).mean()

        z, losses = coarse_to_fine(z, stages, s["lr"], s["temperature"], (y[:, None], w[:, None], outside[:, None]),
                                   loss_fn)
        step = len(losses)
        masks = torch.round(emax * torch.sigmoid(z.detach())[:, 0] * 255).to(torch.uint8).cpu().numpy()
        seconds = time.perf_counter() - t_start
        with torch.no_grad():
            hard = layer_dose(model, torch.from_numpy(masks.astype(np.float32) / 255).to(dev), theta, depth,
                              depth["layer_um"], px)[0] >= theta["T"].reshape(-1)[0]
    finally:
        torch.set_num_threads(old)
    from .metrics import iou

    dose, base = best_uniform_dose(d, p, depth, px, device=dev)
    info = dict(seconds=seconds, steps=step, loss=losses, model_iou=iou(hard.cpu().numpy(), d),
                identical_best_dose=dose, identical_model_iou=base)
    return masks, info


def compensate3d_designs(designs, out_dir, params, depth_path, names=None, **settings) -> list[dict]:
    """Compensate every 3-D design (a folder of layer PNGs, or a folder of such folders)
    into ``out_dir/<design>/NNN.png`` (one mask a layer, bottom first), with
    ``out_dir/compensation3d.tsv`` (per design: the model's 3-D IoU of the masks and of the
    identical masks at the best uniform dose, that dose, seconds). ``out_dir``: a new
    folder or an earlier output of this command."""
    from .io import output_dir, write_png, write_tsv

    designs = Path(designs)
    loaded = _designs3d(designs, names)  # every design checked before the first optimisation
    depth = load_depth(depth_path)
    p = load_params(params)
    rows = []
    with output_dir(out_dir, command="compensate3d", inputs=[designs, Path(params), Path(depth_path)]) as tmp:
        for name, d in loaded.items():
            masks, info = optimise_layers(d, p, depth, **settings)
            for j, m in enumerate(masks):
                write_png(tmp / name / f"{j:03d}.png", m)
            rows.append(dict(design=name, layers=len(d), model_iou=info["model_iou"],
                             identical_best_dose=info["identical_best_dose"],
                             identical_model_iou=info["identical_model_iou"], seconds=round(info["seconds"], 2)))
            log.info("%s: 3-D IoU %.4f (identical masks at %.2f: %.4f), %.1f s", name, info["model_iou"],
                     info["identical_best_dose"], info["identical_model_iou"], info["seconds"])
        write_tsv(tmp / "compensation3d.tsv", rows)
    return rows


# ---------------------------------------------------------------------- benchmark
def _designs3d(designs, names=None) -> dict:
    """name -> (L, H, W) bool of a folder of 3-D designs, or of one design's folder."""
    designs = Path(designs)
    if any(designs.glob("*.png")):
        found = {designs.name: designs}
    else:
        found = {p.name: p for p in sorted(designs.iterdir()) if p.is_dir() and not p.name.startswith(".")}
    if names:
        missing = sorted(set(names) - set(found))
        if missing:
            raise InputError(designs, f"no 3-D design(s) {', '.join(missing)} here")
        found = {k: found[k] for k in names}
    if not found:
        raise InputError(designs, "no 3-D designs (folders of layer PNGs)")
    return {k: read_design3d(v) for k, v in found.items()}


def job_margin(n: int) -> int:
    """The margin (DMD pixels) around an n x n design in the 3-D print job: room for the
    registration marks, kept clear of the design by half of it."""
    return max(12, n // 6)


def frame3d(layers: np.ndarray, margin: int) -> np.ndarray:
    """The layer masks (L, n, n) in a field ``margin`` larger on each side, with
    registration marks through every layer in three corners of the margin (an L, a bar,
    a square: their places fix the pose of a print that alone would not, such as a hollow
    tube, whose rotation and scale its one ring cannot tell), each in the margin's outer
    half."""
    L, n, _ = layers.shape
    N = n + 2 * margin
    out = np.zeros((L, N, N), layers.dtype)
    out[:, margin:margin + n, margin:margin + n] = layers
    from .calibration3d import corner_marks

    w = max(2, margin // 3)
    return corner_marks(out, w=w, arm=N // 5, square=w, value=np.iinfo(np.uint8).max if layers.dtype == np.uint8 else 1)


def unframe3d(vox: np.ndarray, n: int, what) -> np.ndarray:
    """The design's field of a voxel print of a framed job mask (``frame3d``)."""
    N = vox.shape[-1]
    if N == n:
        return vox
    m = (N - n) // 2
    if vox.shape[-2] != N or N - n != 2 * m or m != job_margin(n):
        raise InputError(what, f"voxel print of {vox.shape[-2]}x{N} px fits neither its design ({n}x{n}) nor its "
                         f"print job ({n + 2 * job_margin(n)} px with the registration marks' margin)")
    return vox[..., m:m + n, m:m + n]


def write_job3d(designs, compensated, params, depth_path, out_dir, names=None) -> list[dict]:
    """The print job of the 3-D benchmark: masks/<design>__ilt/ (the compensated layer
    masks) and masks/<design>__identical/ (the design at the model's best uniform dose),
    each framed by a margin with registration marks (``frame3d``), job.tsv and a
    batch.yaml to complete (layer_um from the depth file). ``names``: the designs
    (default: every design compensated)."""
    from .io import output_dir, read_tsv, write_png, write_tsv, write_yaml
    from .settings import PAPER_PIXEL_SIZE_UM

    if not names:  # the designs that were compensated
        names = sorted(q.name for q in Path(compensated).iterdir() if q.is_dir() and not q.name.startswith("."))
    ds = _designs3d(designs, names)
    depth = load_depth(depth_path)
    p = load_params(params)
    px = float(p.pixel_size_um or PAPER_PIXEL_SIZE_UM)
    table = Path(compensated) / "compensation3d.tsv"
    known = {r["design"]: r["identical_best_dose"] for r in read_tsv(table)} if table.is_file() else {}
    rows = []
    with output_dir(out_dir, command="benchmark3d job", inputs=[designs, compensated, params, depth_path]) as tmp:
        for name, d in ds.items():
            files = sorted((Path(compensated) / name).glob("*.png"))
            if len(files) != len(d):
                raise InputError(Path(compensated) / name, f"{len(files)} layer masks for a design of {len(d)} layers")
            # the dose compensate3d found for the same model, else found here
            dose = float(known[name]) if name in known else best_uniform_dose(d, p, depth, px)[0]
            m = job_margin(d.shape[-1])
            ilt = frame3d(np.stack([read_mask(f) for f in files]), m)
            same = frame3d((d * round(255 * dose)).astype(np.uint8), m)
            for j in range(len(d)):
                write_png(tmp / "masks" / f"{name}__ilt" / f"{j:03d}.png", ilt[j])
                write_png(tmp / "masks" / f"{name}__identical" / f"{j:03d}.png", same[j])
            rows += [dict(id=f"{name}__ilt", design=name, method="ilt", grey="", margin_px=m),
                     dict(id=f"{name}__identical", design=name, method="identical", grey=dose, margin_px=m)]
        write_tsv(tmp / "job.tsv", rows)
        write_yaml(tmp / "batch.yaml", dict(pixel_size_um=px, exposure_s=20.0, max_intensity_mw_cm2=20.8, material="FILL IN",
                                            notes="FILL IN: 3-D benchmark prints", layer_um=depth["layer_um"],
                                            z_step_um=10.0))
    return rows


def score3d_prints(prints: dict, designs: dict, pixel_size_um: float, layer_um: float) -> list[dict]:
    """Rows of the 3-D metrics: ``prints`` id '<design>__<method>' -> voxel print or None
    (a print that failed registration)."""
    from .metrics import score3d

    rows = []
    for pid, vox in prints.items():
        name, _, method = pid.partition("__")
        row = dict(id=pid, design=name, method=method, status="ok" if vox is not None else "failed")
        if vox is not None:
            row.update({k: round(float(v), 5) for k, v in score3d(vox, designs[name], pixel_size_um, layer_um).items()})
        rows.append(row)
    return rows


def score3d_batch(registered, designs, out_dir, names=None) -> list[dict]:
    """Score a registered 3-D benchmark batch (``register_stacks`` output) against the
    designs (a print of a framed job mask is cut back to its design's field):
    metrics.tsv and sections.png (xz and yz cross-sections through the middle of
    each design, the design's outline in red) in ``out_dir``."""
    from .io import output_dir, read_print, read_tsv, read_yaml, write_tsv

    registered = Path(registered)
    ds = _designs3d(designs, names)
    meta = read_yaml(registered / "batch.yaml")
    prints = {}
    for r in read_tsv(registered / "qc.tsv"):
        name = r["id"].partition("__")[0]
        if name not in ds:
            continue
        prints[r["id"]] = (unframe3d(np.stack([read_print(registered / r["id"] / f"{j:03d}.png")
                                               for j in range(len(ds[name]))]), ds[name].shape[-1], registered / r["id"])
                           if r["status"] == "ok" else None)
    rows = score3d_prints(prints, ds, float(meta["pixel_size_um"]), float(meta["layer_um"]))
    with output_dir(out_dir, command="benchmark3d score", inputs=[registered, designs]) as tmp:
        write_tsv(tmp / "metrics.tsv", rows)
        sections_figure(tmp / "sections.png", prints, ds)
    return rows


def sections_figure(path: Path, prints: dict, designs: dict) -> None:
    """xz and yz cross-sections (top up) of every print through its design's middle, with
    the design's outline."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ids = list(prints)
    fig, axes = plt.subplots(len(ids), 2, figsize=(8, 1.6 * len(ids) + 0.4), squeeze=False)
    for i, pid in enumerate(ids):
        d = designs[pid.partition("__")[0]]
        vox = prints[pid]
        for k, (ax, cut) in enumerate(zip(axes[i], ("xz", "yz"))):
            mid = d.shape[1 + k] // 2
            dsec = d[:, mid, :] if cut == "xz" else d[:, :, mid]
            img = np.zeros(dsec.shape) if vox is None else (vox[:, mid, :] if cut == "xz" else vox[:, :, mid])
            ax.imshow(img[::-1], cmap="gray", aspect="auto", interpolation="nearest")
            ax.contour(dsec[::-1].astype(float), levels=[0.5], colors="red", linewidths=0.8)
            ax.set_title(f"{pid} {cut}" + (" (failed)" if vox is None else ""), fontsize=7)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
