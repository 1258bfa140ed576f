"""Print-quality metrics: one definition, used by every stage (docs/design.md, 'Metrics').

- IoU of printed vs target.
- pixel error = |printed XOR target| / |target|.
- EPE: symmetric mean distance between printed and target edges, in um.
- PV band: area that differs between prints at 90 % and 110 % of the nominal dose,
  divided by the target's edge length (um).
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
