"""Print-quality metrics: one definition, used by every stage (docs/design.md, 'Metrics').

- IoU of printed vs target.
- pixel error = |printed XOR target| / |target|.
- EPE: symmetric mean distance between printed and target edges, in um.
- PV band: area that differs between prints at 90 % and 110 % of the nominal dose,
  divided by the target's edge length (um).

Multi-layer (3-D) prints, voxel arrays (layers, rows, cols), bottom layer first:

- 3-D IoU: ``iou`` of the voxel arrays.
- open-channel fraction: of the design's channels (void components inside the design's
  bounding box that open on two or more of its faces and touch none of its edges), the
  share by volume that the print leaves open end to end (its void within the channel
  connects every face the channel opens on).
- overhang thickness error: where the design has solid over void (the underside of an
  overhang), the mean extra cured thickness below it in the print (um; 0 = exact).
- wall thickness error: per layer, the printed minus the design area over the design's
  edge length, twice (both sides of a wall), averaged over layers (um; + = thicker).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def iou(printed: np.ndarray, target: np.ndarray) -> float:
    p, t = np.asarray(printed, bool), np.asarray(target, bool)
    union = np.count_nonzero(p | t)
    if union == 0:
        return 1.0  # both empty: identical
    return np.count_nonzero(p & t) / union


def pooled_iou(printed, target) -> float:
    """IoU pooled over a set of prints: the summed intersections over the summed unions.

    Unlike the mean of per-print IoU, a print counts by its area: a few stray pixels on a
    mask that prints nothing are those pixels, not an IoU of 0 against an empty print (or
    1 when the prediction is empty too) that outweighs whole prints. 1.0 when every print
    and prediction is empty."""
    inter = union = 0
    for a, b in zip(printed, target, strict=True):
        p, t = np.asarray(a, bool), np.asarray(b, bool)
        inter += np.count_nonzero(p & t)
        union += np.count_nonzero(p | t)
    return inter / union if union else 1.0


def pixel_error(printed: np.ndarray, target: np.ndarray) -> float:
    p, t = np.asarray(printed, bool), np.asarray(target, bool)
    n = np.count_nonzero(t)
    if n == 0:
        return float("nan") if np.count_nonzero(p) else 0.0
    return np.count_nonzero(p ^ t) / n


def edges(b: np.ndarray) -> np.ndarray:
    """Boundary pixels of a binary image: solid pixels with a void 4-neighbour."""
    b = np.asarray(b, bool)
    return b & ~ndimage.binary_erosion(b, border_value=0)


def area_bias_px(printed: np.ndarray, target: np.ndarray) -> float:
    """(printed area - target area) / the target's boundary pixels (``edges``): how far,
    on average, the printed edge lies outside the target's (px; nan for an empty target)."""
    n = int(np.count_nonzero(edges(target)))
    return (float(np.count_nonzero(printed)) - float(np.count_nonzero(target))) / n if n else float("nan")


def edge_length_px(b: np.ndarray) -> float:
    """Perimeter of a binary shape in pixels (scikit-image's 4-connected estimate)."""
    from skimage.measure import perimeter

    return float(perimeter(np.asarray(b, bool), neighborhood=4))


def epe_um(printed: np.ndarray, target: np.ndarray, pixel_size_um: float) -> float:
    """Symmetric mean distance between printed and target edges (um).

    Mean over printed-edge pixels of the distance to the nearest target edge, and the
    other way round, averaged. Empty vs non-empty is undefined (nan).
    """
    ep, et = edges(printed), edges(target)
    if not ep.any() and not et.any():
        return 0.0
    if not ep.any() or not et.any():
        return float("nan")
    dt_t = ndimage.distance_transform_edt(~et)
    dt_p = ndimage.distance_transform_edt(~ep)
    return 0.5 * (dt_t[ep].mean() + dt_p[et].mean()) * pixel_size_um


def pv_band_um(print_low: np.ndarray, print_high: np.ndarray, target: np.ndarray, pixel_size_um: float) -> float:
    """Area differing between the 90 % and 110 % dose prints per target edge length (um)."""
    area_px = np.count_nonzero(np.asarray(print_low, bool) ^ np.asarray(print_high, bool))
    length_px = edge_length_px(target)
    if length_px == 0:
        return float("nan")
    return area_px / length_px * pixel_size_um


def score(printed: np.ndarray, target: np.ndarray, pixel_size_um: float) -> dict:
    return dict(
        iou=iou(printed, target),
        pixel_error=pixel_error(printed, target),
        epe_um=epe_um(printed, target, pixel_size_um),
    )


# ------------------------------------------------------------------------ 3-D prints
def _channels(design: np.ndarray) -> list[tuple[np.ndarray, list]]:
    """The design's channels: (voxel mask, faces) per void component inside the design's
    bounding box that opens on two or more faces of it but touches none of the box's
    edges (enclosed by material where it opens; the space around a part is not a
    channel). Faces: (axis, side) pairs."""
    d = np.asarray(design, bool)
    if not d.any():
        return []
    box = tuple(slice(int(i.min()), int(i.max()) + 1) for i in np.nonzero(d))
    void = ~d[box]
    at_face = [np.zeros(n, bool) for n in void.shape]
    for a in at_face:
        a[[0, -1]] = True
    grids = np.meshgrid(*at_face, indexing="ij")
    box_edges = (grids[0].astype(int) + grids[1] + grids[2]) >= 2
    lab, n = ndimage.label(void)
    out = []
    for k in range(1, n + 1):
        comp = lab == k
        faces = [(ax, side) for ax in range(3) for side in (0, -1) if np.take(comp, side, axis=ax).any()]
        if len(faces) >= 2 and not (comp & box_edges).any():
            full = np.zeros_like(d)
            full[box] = comp
            out.append((full, faces))
    return out


def open_channel_fraction(printed: np.ndarray, design: np.ndarray) -> float:
    """Share (by volume) of the design's channels left open end to end by the print; nan
    when the design has no channel."""
    chans = _channels(design)
    if not chans:
        return float("nan")
    p = np.asarray(printed, bool)
    d = np.asarray(design, bool)
    box = tuple(slice(int(i.min()), int(i.max()) + 1) for i in np.nonzero(d))
    open_vol = total = 0
    for comp, faces in chans:
        total += int(comp.sum())
        free = (comp & ~p)[box]
        lab, n = ndimage.label(free)
        for k in range(1, n + 1):
            c = lab == k
            if all(np.take(c, side, axis=ax).any() for ax, side in faces):
                open_vol += int(comp.sum())
                break
    return open_vol / total


def overhang_thickness_error_um(printed: np.ndarray, design: np.ndarray, layer_um: float) -> float:
    """Mean extra cured thickness (um) under the design's overhangs; nan without overhangs."""
    p, d = np.asarray(printed, bool), np.asarray(design, bool)
    under = d[1:] & ~d[:-1]  # solid at layer j + 1 over void at layer j
    if not under.any():
        return float("nan")
    extra = []
    for j, r, c in zip(*np.nonzero(under)):
        k, n = int(j), 0
        while k >= 0 and not d[k, r, c] and p[k, r, c]:
            n += 1
            k -= 1
        extra.append(n)
    return float(np.mean(extra)) * float(layer_um)


def wall_thickness_error_um(printed: np.ndarray, design: np.ndarray, pixel_size_um: float) -> float:
    """Mean over the design's non-empty layers of 2 x (printed - design area) / design edge
    length, in um (+: walls print thicker)."""
    p, d = np.asarray(printed, bool), np.asarray(design, bool)
    vals = [2.0 * (int(p[j].sum()) - int(d[j].sum())) / max(edge_length_px(d[j]), 1.0) for j in range(len(d)) if d[j].any()]
    return float(np.mean(vals)) * float(pixel_size_um) if vals else float("nan")


def score3d(printed: np.ndarray, design: np.ndarray, pixel_size_um: float, layer_um: float) -> dict:
    """Every 3-D metric of a voxel print against its design."""
    return dict(iou=iou(printed, design), open_channels=open_channel_fraction(printed, design),
                overhang_error_um=overhang_thickness_error_um(printed, design, layer_um),
                wall_error_um=wall_thickness_error_um(printed, design, pixel_size_um))
