"""Registration of confocal z-stacks to the layer masks of multi-layer prints.

A multi-layer batch (docs/design.md, 'Multi-layer (3-D) prints'): masks/<id>/NNN.png
(one layer mask a layer, bottom first), images/<id>.tif (a z-stack, one page a slice),
batch.yaml with layer_um and z_step_um.

1. **Lateral pose.** The mean of the stack's slices is a 2-D image of the print whose
   brightness follows the print's height; the mean of the layer masks is the matching
   grey mask. This pair is registered with the 2-D registration (``register_batch``: its
   pose hypotheses, print template and QC), which gives the pose (rotation, scale, shift)
   shared by every slice.
2. **z offset.** Every slice is warped to mask coordinates; the axial profile (mean signal
   over the print's footprint, background subtracted) is fitted, for a grid of the
   print's bottom position and the axial response's width (a Gaussian integrated over
   each layer), with every layer's brightness free and non-negative: a print may differ
   from its masks layer by layer (an overhang grown downward), but it spans exactly its
   layers, so its bottom and top edges place it. The fall-off of the signal with depth
   (light lost on the way in and out) comes from a fit with the masks' areas
   (``model_r2`` says how well the masks alone explain the profile).
3. **Voxel print.** Each layer is read at its centre depth (linear interpolation between
   slices), the signal's fall-off with height is undone, and the layers are thresholded
   at ``level`` of the stack's dense-polymer level (the 95th percentile of layer-centre
   signal over the masks' solid voxels). That fall-off (``dense_falloff_um``) comes from
   the dense polymer's brightness layer by layer (a robust fit of its log against
   height), not from the axial fit: a print grown beyond its masks would read there as
   fall-off and lose its lower layers.
4. **QC.** A print fails when its 2-D registration fails (the reason is kept), when the
   axial profile is not explained (R^2 below ``min_axial_r2``), or when the stack does not
   cover the print's depth.

Writes prints/<id>/NNN.png (voxel layers), overlays/<id>.png (the layer-centre slices
with the layer masks' outlines), qc.tsv (pose, bottom_um, axial_sigma_um, r2, status).
"""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage
from scipy.special import ndtr

from ..io import InputError, output_dir, read_batch_meta, read_mask, read_tsv, write_png, write_rgb, write_tsv, write_yaml

log = logging.getLogger(__name__)

AXIAL_SIGMAS_UM = (1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 11.0, 15.0, 20.0, 28.0)
FALLOFFS_UM = (float("inf"), 3000.0, 1500.0, 1000.0, 700.0, 500.0, 350.0, 250.0, 175.0)  # signal fall-off with depth
MIN_AXIAL_R2 = 0.95  # of the free-layer fit


def open_stack_batch(root) -> tuple:
    """(meta, {id: (layer mask paths bottom first, image path)}) of a multi-layer batch;
    InputError naming the file for what is missing or inconsistent."""
    root = Path(root)
    meta = read_batch_meta(root / "batch.yaml")
    for field in ("layer_um", "z_step_um"):
        if getattr(meta, field) is None:
            raise InputError(root / "batch.yaml", f"a multi-layer batch needs {field}")
    for key in ("dense_level", "dense_reference"):  # a widefield image's units; a stack's level comes from its dense polymer
        if getattr(meta, key) is not None:
            raise InputError(root / "batch.yaml", f"{key} is for single-layer batches; a z-stack's dense level is measured "
                                                  f"from its own dense polymer (remove {key})")
    mdir, idir = root / "masks", root / "images"
    for d in (mdir, idir):
        if not d.is_dir():
            raise InputError(d, "folder missing from the batch")
    prints = {}
    for f in sorted(p for p in mdir.iterdir() if not p.name.startswith(".")):
        if not f.is_dir():
            raise InputError(f, "a multi-layer batch holds one folder of layer masks per print (masks/<id>/NNN.png)")
        layers = sorted(p for p in f.glob("*.png") if not p.name.startswith("."))
        if not layers:
            raise InputError(f, "no layer masks (.png)")
        want = [f"{i:03d}.png" for i in range(len(layers))]
        if [p.name for p in layers] != want:
            missing = sorted(set(want) - {p.name for p in layers})
            raise InputError(f, f"layers must be 000.png, 001.png, ... bottom first; missing {', '.join(missing) or want[-1]}")
        img = next((idir / f"{f.name}{s}" for s in (".tif", ".tiff") if (idir / f"{f.name}{s}").is_file()), None)
        if img is None:
            raise InputError(idir, f"no z-stack images/{f.name}.tif for the print {f.name!r}")
        prints[f.name] = (layers, img)
    extra = sorted(p.stem for p in idir.iterdir() if p.is_file() and not p.name.startswith(".") and p.stem not in prints)
    if extra:
        raise InputError(idir, f"z-stack(s) without layer masks: {', '.join(extra)}")
    if not prints:
        raise InputError(mdir, "no prints in the batch")
    return meta, prints


def read_stack(path: Path) -> np.ndarray:
    """A z-stack (slices, rows, cols) as float32; InputError if it is not one."""
    import tifffile

    try:
        a = tifffile.imread(path)
    except Exception as exc:  # noqa: BLE001 (any unreadable file is the same error for the user)
        raise InputError(path, f"not a readable TIFF z-stack ({exc})") from None
    if a.ndim != 3 or a.shape[0] < 3:
        raise InputError(path, f"a z-stack needs 3 or more slices (pages), found shape {a.shape}")
    return a.astype(np.float32)


def layer_weights(bottoms_um, sigma_um: float, z_um: np.ndarray, layers: int, layer_um: float) -> np.ndarray:
    """(..., Nz, L) share of a Gaussian axial response of ``sigma_um`` at depths ``z_um``
    that falls in each layer, for a print whose bottom is at ``bottoms_um`` (a number or
    an array: one weight matrix per bottom)."""
    lo = np.asarray(bottoms_um, float)[..., None, None] + np.arange(layers) * layer_um
    z = np.asarray(z_um, float)[:, None]
    return ndtr((lo + layer_um - z) / sigma_um) - ndtr((lo - z) / sigma_um)


def axial_profile(bottom_um: float, sigma_um: float, z_um: np.ndarray, area: np.ndarray, layer_um: float) -> np.ndarray:
    """Predicted axial signal at depths ``z_um``: each layer's solid share ``area`` seen
    through a Gaussian axial response of ``sigma_um`` integrated over the layer."""
    return layer_weights(bottom_um, sigma_um, z_um, len(area), layer_um) @ area


def fit_axial(profile: np.ndarray, z_um: np.ndarray, area: np.ndarray, layer_um: float) -> dict:
    """Bottom position, axial width and signal fall-off with depth that explain the
    profile best (grid search, a linear gain and offset at each point, all bottoms of a
    grid row at once in closed form): bottom_um, axial_sigma_um, falloff_um (the signal
    falls as exp(-z / falloff_um) through the stack; inf: it does not), r2."""
    best = None
    pc = profile - profile.mean()
    var = float((pc**2).sum())
    bottoms = np.arange(z_um[0] - 2 * layer_um, z_um[-1] + 1e-9, max(0.5, (z_um[1] - z_um[0]) / 4))
    for fall in FALLOFFS_UM:
        dim = np.exp(-(z_um - z_um[0]) / fall)
        for sig in AXIAL_SIGMAS_UM:
            Q = (layer_weights(bottoms, sig, z_um, len(area), layer_um) @ area) * dim  # (bottoms, Nz)
            qc = Q - Q.mean(axis=1, keepdims=True)
            sqq = (qc**2).sum(axis=1)
            sqp = qc @ pc
            with np.errstate(divide="ignore", invalid="ignore"):
                res = np.where((sqq > 0) & (sqp > 0), var - sqp**2 / sqq, np.inf)  # gain > 0 only
            k = int(np.argmin(res))
            if np.isfinite(res[k]) and (best is None or res[k] < best[0]):
                best = (float(res[k]), float(bottoms[k]), float(sig), float(fall))
    if best is None:
        return dict(bottom_um=float("nan"), axial_sigma_um=float("nan"), falloff_um=float("inf"), r2=0.0, model_r2=0.0)
    out = dict(bottom_um=best[1], axial_sigma_um=best[2], falloff_um=best[3],
               model_r2=1.0 - best[0] / var if var > 0 else 0.0)
    out.update(_fit_free_layers(profile, z_um, len(area), layer_um, bottoms, var))
    return out


def _fit_free_layers(profile: np.ndarray, z_um: np.ndarray, layers: int, layer_um: float, bottoms, var: float) -> dict:
    """The bottom position and axial width with every layer's brightness free (>= 0): the
    print's own layers may differ from its masks (an overhang grown downward, a channel
    closed, light lost with depth), but it still spans exactly its layers, so its
    bottom and top edges place it. Non-negative least squares at each grid point."""
    from scipy.optimize import nnls

    best = None
    for sig in AXIAL_SIGMAS_UM:
        for b, W in zip(bottoms, layer_weights(bottoms, sig, z_um, layers, layer_um)):
            A = np.hstack([W, np.ones((len(z_um), 1)), -np.ones((len(z_um), 1))])  # offset of either sign
            coef, res = nnls(A, profile)
            if best is None or res < best[0]:
                best = (res, float(b), float(sig))
    r2 = 1.0 - best[0] ** 2 / var if var > 0 else 0.0
    return dict(bottom_um=best[1], axial_sigma_um=best[2], r2=r2)


def register_stacks(batch_dir, out_dir, level: float = 0.5, skip_failed: bool = False, progress: bool = True,
                    min_axial_r2: float = MIN_AXIAL_R2) -> list[dict]:
    """Register every z-stack of a multi-layer batch to its layer masks; write voxel
    prints, overlays and qc.tsv (see the module doc). Raises RegistrationError after the
    output is written when a print fails QC and ``skip_failed`` is false."""
    from .batch import RegistrationError, register_batch

    batch_dir = Path(batch_dir)
    meta, prints = open_stack_batch(batch_dir)
    layer_um, step = float(meta.layer_um), float(meta.z_step_um)
    offset = float(meta.camera_offset_adu)
    masks = {mid: np.stack([read_mask(p) for p in layers]) for mid, (layers, _) in prints.items()}
    stacks = {mid: read_stack(img) for mid, (_, img) in prints.items()}
    for mid, st in stacks.items():
        if st.shape[0] * step < len(masks[mid]) * layer_um:
            raise InputError(prints[mid][1], f"{st.shape[0]} slices of {step:g} um cover {st.shape[0] * step:g} um, less "
                                             f"than the print's {len(masks[mid])} layers of {layer_um:g} um")
    with tempfile.TemporaryDirectory() as tmp:
        flat = Path(tmp) / "projection"
        (flat / "masks").mkdir(parents=True)
        (flat / "images").mkdir()
        import tifffile

        for mid in prints:
            write_png(flat / "masks" / f"{mid}.png", np.round(masks[mid].astype(np.float64).mean(0)).astype(np.uint8))
            tifffile.imwrite(flat / "images" / f"{mid}.tif", np.round(stacks[mid].mean(0)).clip(0, 65535).astype(np.uint16),
                             photometric="minisblack")
        m2 = {k: v for k, v in meta.as_dict().items() if k not in ("layer_um", "z_step_um")}
        write_yaml(flat / "batch.yaml", m2)
        register_batch(flat, Path(tmp) / "reg", level=level, skip_failed=True, progress=progress)
        rows2 = {r["id"]: r for r in read_tsv(Path(tmp) / "reg" / "qc.tsv")}

    rows = []
    with output_dir(out_dir, command="register3d", inputs=[batch_dir]) as out:
        (out / "overlays").mkdir()
        for mid in prints:
            r2 = rows2[mid]
            row = dict(id=mid, status=r2["status"], reason=r2["reason"], layers=len(masks[mid]), slices=len(stacks[mid]),
                       rotation_deg=r2["rotation_deg"], scale=r2["scale"], shift_x=r2["shift_x"], shift_y=r2["shift_y"],
                       score=r2["score"], bottom_um="", axial_sigma_um="", falloff_um="", dense_falloff_um="", axial_r2="", axial_model_r2="",
                       solid_fraction="",
                       mask=os.path.relpath((batch_dir / "masks" / mid).resolve(), Path(out_dir).resolve()))
            if r2["status"] != "ok":
                row["reason"] = f"projection: {r2['reason']}" if r2["reason"] else row["reason"]
                rows.append(row)
                continue
            M = np.array([[float(r2[f"m{a}{b}"]) for b in range(3)] for a in range(2)])
            vox, info, sheet = _voxel_print(stacks[mid] - offset, masks[mid], M, layer_um, step, level)
            row.update(bottom_um=round(info["bottom_um"], 2), axial_sigma_um=info["axial_sigma_um"],
                       falloff_um=info["falloff_um"], dense_falloff_um=round(info["dense_falloff_um"], 1),
                       axial_model_r2=round(info["model_r2"], 4),
                       axial_r2=round(info["r2"], 4), solid_fraction=round(float(vox.mean()), 5))
            reasons = []
            if not info["r2"] >= min_axial_r2:
                reasons.append(f"z offset not determined: the axial profile is explained to R^2 {info['r2']:.2f} "
                               f"(below {min_axial_r2})")
            top = info["bottom_um"] + len(masks[mid]) * layer_um
            if not (info["bottom_um"] >= -0.5 * layer_um and top <= len(stacks[mid]) * step + 0.5 * layer_um):
                reasons.append(f"the stack (0 to {len(stacks[mid]) * step:g} um) does not cover the print "
                               f"({info['bottom_um']:.0f} to {top:.0f} um)")
            write_rgb(out / "overlays" / f"{mid}.png", sheet)
            if reasons:
                row.update(status="failed", reason="; ".join(reasons))
            else:
                for j, layer in enumerate(vox):
                    write_png(out / mid / f"{j:03d}.png", layer)
            rows.append(row)
        write_tsv(out / "qc.tsv", rows)
        write_yaml(out / "batch.yaml", dict(meta.as_dict(), source_batch=str(batch_dir)))
    failed = [r for r in rows if r["status"] == "failed"]
    for r in failed:
        log.warning("%s: registration failed: %s", r["id"], r["reason"])
    if failed and not skip_failed:
        raise RegistrationError(f"{len(failed)} of {len(rows)} z-stacks failed QC (see {Path(out_dir) / 'qc.tsv'}): "
                                + "; ".join(f"{r['id']}: {r['reason']}" for r in failed[:3]))
    return rows


def dense_falloff(at: np.ndarray, solid: np.ndarray, z_um: np.ndarray, min_layers: int = 3) -> float:
    """The signal's fall-off length with height in the print (um; inf: none; negative:
    the signal grows with height, as when the stack is imaged from above), from the dense polymer's
    brightness layer by layer: the 95th percentile of each layer's signal over its mask's
    solid pixels, whose log is fitted against depth by Theil-Sen (robust to the layers
    that did not cure as their mask says). Not from the axial profile, where a print
    that grew beyond its masks (an overhang cured down to the floor) reads as fall-off."""
    from scipy.stats import theilslopes

    levels = np.array([np.percentile(a[m], 95) if m.sum() >= 16 else np.nan for a, m in zip(at, solid)])
    ok = np.isfinite(levels) & (levels > 0)
    if ok.sum() < min_layers:
        return float("inf")
    slope = float(theilslopes(np.log(levels[ok]), np.asarray(z_um, float)[ok])[0])
    return -1.0 / slope if slope != 0 else float("inf")  # negative: brighter with depth (imaged from above)


def _voxel_print(stack: np.ndarray, layers: np.ndarray, M: np.ndarray, layer_um: float, step: float, level: float):
    """(voxel print (L, S, S) bool, axial fit, overlay sheet) of one stack at pose M."""
    L, S, _ = layers.shape
    warped = np.stack([cv2.warpAffine(sl, M, (S, S), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                      borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan) for sl in stack])
    solid = layers > 0
    foot = solid.any(0)
    outside = ~ndimage.binary_dilation(foot, iterations=max(4, S // 32)) & np.isfinite(warped).all(0)
    bg = np.array([np.nanmedian(w[outside]) if outside.any() else np.nanmedian(w) for w in warped])
    sig = warped - bg[:, None, None]
    profile = np.array([np.nanmean(s[foot]) for s in sig])
    area = (layers.astype(np.float64) / 255.0)[:, foot].mean(1)
    z = np.arange(len(stack)) * step
    info = fit_axial(profile, z, area, layer_um)
    centres = (info["bottom_um"] + (np.arange(L) + 0.5) * layer_um) / step
    k0 = np.clip(np.floor(centres).astype(int), 0, len(stack) - 2)
    f = np.clip(centres - k0, 0, 1)[:, None, None]
    at = np.nan_to_num((1 - f) * sig[k0] + f * sig[k0 + 1], nan=0.0)
    falloff = dense_falloff(at, solid, centres * step)
    info["dense_falloff_um"] = falloff
    at = at * np.exp(centres * step / falloff)[:, None, None]  # undo the fall-off with depth
    dense = float(np.percentile(at[solid], 95)) if solid.any() else float(np.nanmax(at))
    vox = at >= level * dense
    # overlay: the layer-centre slices side by side, the layer masks' outlines in red
    tiles = []
    for j in range(L):
        g = np.clip(at[j] / max(dense, 1e-9), 0, 1)
        rgb = np.repeat((g * 255).astype(np.uint8)[..., None], 3, axis=2)
        edge = solid[j] & ~ndimage.binary_erosion(solid[j])
        rgb[edge] = (255, 0, 0)
        tiles.append(rgb)
    sheet = np.concatenate(tiles, axis=1)
    return vox, info, sheet
