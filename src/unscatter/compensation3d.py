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
att_length_um, spread, layer_um), written by a 3-D calibration or by hand.
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
    """att_length_um, spread and layer_um from a depth file, each checked against its
    bounds (InputError naming the file)."""
    d = read_yaml(path)
    if not isinstance(d, dict):
        raise InputError(path, "a depth file is a mapping: att_length_um, spread, layer_um")
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
        raise InputError(path, f"unknown key(s) {', '.join(unknown)}; a depth file has att_length_um, spread, layer_um")
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
    depth = load_depth(depth_path)
    p = load_params(params)
    loaded = {k: read_design3d(v) for k, v in found.items()}  # every design checked before the first optimisation
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
