"""Calibration of the multi-layer model's depth parameters from 3-D trial prints.

The 2-D parameters (Eq. 1, effects) come from the 2-D calibration; here the depth
parameters (``model.DEPTH_PARAMS``: attenuation length, depth diffusion), and optionally
some 2-D parameters jointly (e.g. T, which a multi-layer print's accumulated dose tests
differently from a single layer), are fitted to voxel prints (layer masks and the cured
voxels of each layer, in mask coordinates).

Objective: the mean squared difference between the smooth-threshold voxel print and the
measured one, as the 2-D calibration's (Guan et al. 2022's mean squared distance), cooled
towards the hard threshold. Search: every parameter mapped to its bounds through a
sigmoid, Adam from several starting attenuation lengths (the objective has flat regions
where the light reaches no layer below), the best start kept. Two to four parameters and
a smooth objective do not need the 2-D calibration's genetic algorithm.

The trial prints (``trial_masks3d``): overhang bridges of several spans, channels of
several widths, towers of several sizes, stairs, each a stack of layer masks.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from .model import DEPTH_PARAMS, Params, default_device, layer_dose

STARTS_UM = (30.0, 100.0, 400.0)  # starting attenuation lengths


# ------------------------------------------------------------------- trial prints
def _bridge(rng, L, n):
    d = np.zeros((L, n, n), bool)
    span = int(rng.integers(n // 5, n // 2))
    w = int(rng.integers(n // 8, n // 4))
    c0 = (n - span) // 2
    r0 = int(rng.integers(4, n - w - 4))
    pw = max(4, n // 12)
    d[:, r0:r0 + w, c0 - pw:c0] = True
    d[:, r0:r0 + w, c0 + span:c0 + span + pw] = True
    top = int(rng.integers(1, max(2, L // 3) + 1))
    d[L - top:, r0:r0 + w, c0 - pw:c0 + span + pw] = True
    return d


def _channel(rng, L, n):
    d = np.zeros((L, n, n), bool)
    d[:, n // 8:n - n // 8, n // 8:n - n // 8] = True
    width = int(rng.integers(3, n // 6))
    height = int(rng.integers(1, max(2, L // 2)))
    j0 = int(rng.integers(1, max(2, L - height)))
    c = n // 2 + int(rng.integers(-n // 8, n // 8 + 1))
    d[j0:j0 + height, c - width // 2:c - width // 2 + width, :] = False
    return d


def _tower(rng, L, n):
    d = np.zeros((L, n, n), bool)
    for _ in range(int(rng.integers(2, 5))):
        s = int(rng.integers(3, n // 4))
        r, c = (int(v) for v in rng.integers(2, n - s - 2, size=2))
        d[:, r:r + s, c:c + s] = True
    return d


def _stairs(rng, L, n):
    d = np.zeros((L, n, n), bool)
    steps = int(rng.integers(3, 7))
    w = (n - n // 4) // steps
    r0, r1 = n // 8, n - n // 8
    for k in range(steps):
        h = max(1, round(L * (k + 1) / steps))
        d[:h, r0:r1, n // 8 + k * w:n // 8 + (k + 1) * w] = True
    return d


KINDS3D = {"bridge": _bridge, "channel": _channel, "tower": _tower, "stairs": _stairs}


def _markers(d: np.ndarray) -> np.ndarray:
    """Registration marks through every layer, in three corners (an L, a bar, a square),
    clear of the test structures (which keep an eighth of the field free at each side). The mean projection of a block with a
    channel inside is one square whose size alone would set its scale; the marks fix the
    pose by their places."""
    n = d.shape[-1]
    w = max(3, n // 24)
    return corner_marks(d.copy(), w=w, arm=max(8, n // 6), square=2 * w, value=True)


def corner_marks(out: np.ndarray, w: int, arm: int, square: int, value) -> np.ndarray:
    """Draw registration marks into every layer of ``out`` (L, N, N), in place, one pixel
    in from the edges: an L of arms ``arm`` long and ``w`` wide in the top left corner, a
    bar ``arm // 2`` long in the top right, a square of side ``square`` in the bottom
    right. Their places, not their sizes, fix a print's pose."""
    N = out.shape[-1]
    out[:, 1:1 + arm, 1:1 + w] = value  # the L
    out[:, 1:1 + w, 1:1 + arm] = value
    out[:, 1:1 + w, N - 1 - arm // 2:N - 1] = value  # the bar
    out[:, N - 1 - square:N - 1, N - 1 - square:N - 1] = value  # the square
    return out


def trial_masks3d(count: int, layers: int = 8, size: int = 128, seed: int = 0) -> dict:
    """``count`` 3-D trial prints, id ``<kind>_<index>`` -> (layers, size, size) uint8
    layer masks (255 = full dose), the kinds in turn, each from its own seeded stream,
    each with registration marks in three corners (``_markers``)."""
    out = {}
    kinds = list(KINDS3D)
    for i in range(count):
        k = kinds[i % len(kinds)]
        d = _markers(KINDS3D[k](np.random.default_rng([seed, i]), layers, size))
        out[f"{k}_{i:03d}"] = (d * 255).astype(np.uint8)
    return out


# -------------------------------------------------------------------------- fitting
def _bounds(params: Params, names):
    spec = {p.name: p.bounds for p in DEPTH_PARAMS}
    return np.array([spec.get(k, params.bounds.get(k)) for k in names], dtype=np.float64)


def fit_depth(masks: list, prints: list, params: Params, layer_um: float, pixel_size_um: float,
              free2d=(), steps: int = 120, temperatures=(0.15, 0.03), starts=STARTS_UM, device=None,
              weights=None, init=None) -> dict:
    """Fit the depth parameters (and the 2-D parameters named in ``free2d``) to voxel
    prints. ``masks``: list of (L, H, W) uint8 layer masks; ``prints``: list of (L, H, W)
    bool voxel prints; ``weights``: a weight per print (a bootstrap's counts), default 1.
    One Adam run per start of the attenuation length in ``starts``, or one run from
    ``init`` (a fit's ``u``: a warm start). Returns a dict: values (the fitted
    parameters), u (their unconstrained form), objective (the hard-threshold mean squared
    difference), seconds, starts (objective per start)."""
    dev = torch.device(device) if device else default_device()
    model = params.build()
    names = ["att_length_um", "diffusion_um", *free2d]
    B = _bounds(params, names)
    Ms = [torch.from_numpy(np.asarray(m, np.float32) / 255.0).to(dev) for m in masks]
    Ys = [torch.from_numpy(np.asarray(p, np.float32)).to(dev) for p in prints]
    W = [1.0] * len(Ys) if weights is None else [float(w) for w in weights]
    n_vox = sum(w * int(y.numel()) for w, y in zip(W, Ys))
    t0 = time.perf_counter()

    def unpack(u):
        x = torch.as_tensor(B[:, 0], dtype=u.dtype) + torch.sigmoid(u) * torch.as_tensor(B[:, 1] - B[:, 0], dtype=u.dtype)
        depth = {"att_length_um": x[0:1], "diffusion_um": x[1:2]}
        vals = dict(params.values)
        vals.update({k: x[2 + i] for i, k in enumerate(free2d)})
        return depth, model.theta({k: (v.reshape(1) if isinstance(v, torch.Tensor) else v) for k, v in vals.items()}, dev), x

    def objective(u, temperature):
        depth, theta, _ = unpack(u)
        total = 0.0
        for m, y, w in zip(Ms, Ys, W):
            if w == 0:
                continue
            dose = layer_dose(model, m, theta, depth, layer_um, pixel_size_um)[0]
            p = model.threshold.apply(dose, theta, temperature)
            total = total + w * ((p.float() - y) ** 2).sum()
        return total / n_vox

    def logit(v, lo, hi):
        f = min(max((v - lo) / (hi - lo), 1e-4), 1 - 1e-4)
        return math.log(f / (1 - f))

    inits = [[logit(att0, *B[0]), logit(2.0, *B[1])] + [logit(float(params.values[k]), *B[2 + i])
                                                        for i, k in enumerate(free2d)] for att0 in starts]
    if init is not None:
        inits = [list(np.asarray(init, np.float64))]
    results = []
    for start in inits:
        u = torch.tensor(start, dtype=torch.float32, requires_grad=True)
        opt = torch.optim.Adam([u], lr=0.1)
        for s in range(steps):
            t = temperatures[0] * (temperatures[1] / temperatures[0]) ** (s / max(steps - 1, 1))
            opt.zero_grad(set_to_none=True)
            loss = objective(u, t)
            loss.backward()
            opt.step()
        with torch.no_grad():
            hard = float(objective(u, None))
        results.append((hard, u.detach().clone()))
    best = min(results, key=lambda r: r[0])
    with torch.no_grad():
        _, _, x = unpack(best[1])
    values = {k: float(x[i]) for i, k in enumerate(names)}
    return dict(values=values, u=best[1].numpy().tolist(), objective=best[0], starts=[r[0] for r in results],
                seconds=time.perf_counter() - t0)


def voxel_prints(masks: list, params: Params, depth: dict, layer_um: float, pixel_size_um: float, device=None) -> list:
    """Hard-threshold voxel prints of layer masks under a model and depth parameters."""
    dev = torch.device(device) if device else default_device()
    model = params.build()
    theta = model.theta(params.values, dev)
    out = []
    with torch.no_grad():
        for m in masks:
            d = layer_dose(model, torch.from_numpy(np.asarray(m, np.float32) / 255.0).to(dev), theta, depth, layer_um,
                           pixel_size_um)[0]
            out.append((d >= theta["T"].reshape(-1)[0]).cpu().numpy())
    return out


# ---------------------------------------------------------------- from registration
def load_voxel_prints(prints_dir) -> tuple[dict, dict, dict]:
    """(layer masks, voxel prints, batch meta) of the usable prints of a z-stack
    registration (``register_stacks``'s output): id -> (L, H, W) arrays; failed prints are
    never read."""
    from pathlib import Path

    from .io import InputError, read_mask, read_print, read_tsv, read_yaml

    prints_dir = Path(prints_dir)
    meta = read_yaml(prints_dir / "batch.yaml")
    masks, prints = {}, {}
    for r in read_tsv(prints_dir / "qc.tsv"):
        if r["status"] != "ok":
            continue
        mdir = (prints_dir / r["mask"]).resolve()
        layers = sorted(mdir.glob("*.png"))
        if not layers:
            raise InputError(mdir, f"layer masks of print {r['id']!r} not found")
        masks[r["id"]] = np.stack([read_mask(p) for p in layers])
        files = [prints_dir / r["id"] / p.name for p in layers]
        missing = [f for f in files if not f.is_file()]
        if missing:
            raise InputError(missing[0], "voxel print listed as ok in qc.tsv but missing")
        prints[r["id"]] = np.stack([read_print(f) for f in files])
    if not prints:
        raise InputError(prints_dir / "qc.tsv", "no usable (ok) voxel prints")
    return masks, prints, meta


def load_voxel_batches(prints_dirs, pixel_size_um=None) -> tuple[dict, dict, float, float]:
    """(layer masks, voxel prints, layer_um, pixel_size_um) of the usable prints of one or
    several z-stack registrations. With several, an id is ``<batch folder>:<id>``. The
    batches must share the layer thickness and the DMD pixel size (``pixel_size_um``:
    the model's, used where a batch.yaml gives none): a model has one of each."""
    from pathlib import Path

    from .io import InputError

    dirs = [Path(prints_dirs)] if isinstance(prints_dirs, (str, Path)) else [Path(d) for d in prints_dirs]
    if not dirs:
        raise ValueError("no registered 3-D batches given")
    masks, prints, geometry = {}, {}, None
    for d in dirs:
        m, p, meta = load_voxel_prints(d)
        px = float(meta.get("pixel_size_um") or pixel_size_um or 0)
        dz = meta.get("layer_um")
        if not px > 0 or not isinstance(dz, (int, float)) or not dz > 0:
            raise InputError(d / "batch.yaml", "needs pixel_size_um and layer_um (positive numbers)")
        if geometry is None:
            geometry = (float(dz), px, d)
        elif not (math.isclose(dz, geometry[0], rel_tol=1e-6) and math.isclose(px, geometry[1], rel_tol=1e-6)):
            raise InputError(d / "batch.yaml", f"layer_um {dz:g} and pixel_size_um {px:g} differ from "
                             f"{geometry[2] / 'batch.yaml'} ({geometry[0]:g}, {geometry[1]:g}); calibrate batches of "
                             "one layer thickness and pixel size together")
        key = (lambda k: f"{d.name}:{k}") if len(dirs) > 1 else (lambda k: k)
        for k in p:
            masks[key(k)], prints[key(k)] = m[k], p[k]
    return masks, prints, geometry[0], geometry[1]


def bootstrap_depth(masks: list, prints: list, params: Params, layer_um: float, pixel_size_um: float, fit: dict,
                    free2d=(), replicates: int = 8, steps: int = 40, seed: int = 0) -> list[dict]:
    """The depth fit redone on ``replicates`` resamples of the prints (with replacement),
    each warm-started from ``fit`` (fit_depth's result) at the fit's final temperature:
    the fitted values of each replicate."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(replicates):
        counts = np.bincount(rng.integers(0, len(prints), len(prints)), minlength=len(prints))
        r = fit_depth(masks, prints, params, layer_um, pixel_size_um, free2d=free2d, steps=steps,
                      temperatures=(0.05, 0.03), init=fit["u"], weights=counts)
        out.append(r["values"])
    return out


def calibrate3d(prints_dirs, params_path, out_dir, free2d=("sigma_px", "T"), holdout: float = 1 / 3, seed: int = 0,
                steps: int = 80, bootstrap: int = 8) -> dict:
    """Fit the depth parameters (and ``free2d``) to registered voxel prints (one or
    several registered batches), the 2-D model from ``params_path``. A share ``holdout``
    of the prints is kept out of the fit and scored (voxel IoU, the fitted model against
    the measured print); ``bootstrap`` resamples of the fitted prints give the
    parameters' spread (their standard deviation). Writes into ``out_dir``: params.yaml
    (the 2-D model with the jointly fitted values), depth.yaml (att_length_um,
    diffusion_um, layer_um), fit.tsv (per print: fit or held-out, voxel IoU),
    bootstrap.tsv (the replicates' values) and summary.yaml. Returns the summary."""
    from pathlib import Path

    from .io import output_dir, write_tsv, write_yaml
    from .metrics import iou
    from .model import load_params, save_params

    base = load_params(params_path)
    masks, prints, dz, px = load_voxel_batches(prints_dirs, base.pixel_size_um)
    ids = sorted(prints)
    rng = np.random.default_rng(seed)
    order = list(rng.permutation(len(ids)))
    n_hold = int(round(holdout * len(ids))) if len(ids) >= 3 else 0
    held = {ids[i] for i in order[:n_hold]}
    fit_ids = [k for k in ids if k not in held]
    fit_masks, fit_prints = [masks[k] for k in fit_ids], [prints[k] for k in fit_ids]
    r = fit_depth(fit_masks, fit_prints, base, float(dz), px, free2d=tuple(free2d), steps=steps)
    v = r["values"]
    t0 = time.perf_counter()
    boot = bootstrap_depth(fit_masks, fit_prints, base, float(dz), px, r, free2d=tuple(free2d), replicates=bootstrap,
                           seed=seed) if bootstrap and len(fit_ids) > 1 else []
    spread = {k: float(np.std([b[k] for b in boot], ddof=1)) for k in v} if len(boot) > 1 else None
    params = base.with_values(**{k: v[k] for k in free2d})
    depth = dict(att_length_um=v["att_length_um"], diffusion_um=v["diffusion_um"], layer_um=float(dz))
    sims = voxel_prints([masks[k] for k in ids], params, depth, float(dz), px)
    rows = [dict(id=k, use="held-out" if k in held else "fit", voxel_iou=round(iou(s, prints[k]), 5))
            for k, s in zip(ids, sims)]
    h = [row["voxel_iou"] for row in rows if row["use"] == "held-out"]
    summary = dict(values=v, spread=spread, bootstrap=len(boot), objective=r["objective"], starts=r["starts"],
                   seconds=round(r["seconds"], 1), bootstrap_seconds=round(time.perf_counter() - t0, 1),
                   prints=len(ids), held_out=len(h), heldout_voxel_iou=float(np.mean(h)) if h else None,
                   fit_voxel_iou=float(np.mean([row["voxel_iou"] for row in rows if row["use"] == "fit"])))
    sources = [str(d) for d in ([prints_dirs] if isinstance(prints_dirs, (str, Path)) else prints_dirs)]
    with output_dir(out_dir, command="calibrate3d", inputs=[*sources, params_path]) as tmp:
        save_params(tmp / "params.yaml", params, depth_fit=dict(free=list(free2d), source=sources))
        write_yaml(tmp / "depth.yaml", depth)
        write_tsv(tmp / "fit.tsv", rows)
        if boot:
            write_tsv(tmp / "bootstrap.tsv", [dict(replicate=i, **{k: round(x, 6) for k, x in b.items()})
                                              for i, b in enumerate(boot)])
        write_yaml(tmp / "summary.yaml", summary)
    return summary


def write_trial_masks3d(out_dir, count: int, layers: int, size: int, seed: int) -> list:
    """The 3-D trial prints as ``out_dir/<id>/NNN.png`` (a new folder, or an earlier one of
    these)."""
    from pathlib import Path

    from .io import output_dir, write_png

    masks = trial_masks3d(count, layers=layers, size=size, seed=seed)
    with output_dir(out_dir, command="masks trial3d") as tmp:
        for mid, m in masks.items():
            for j, layer in enumerate(m):
                write_png(tmp / mid / f"{j:03d}.png", layer)
    return [Path(out_dir) / mid for mid in masks]
