"""Mask families: the paper's trial masks and its augmentation masks.

Guan et al. 2022, 'Trial data acquisition': 32 masks of three randomized families:
random grayscale checkerboards, randomly positioned and sized rectangles, and randomly
positioned circular shapes. Masks are 8-bit, 255 = 100 % dose.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from skimage.draw import disk, rectangle

TRIAL_FAMILIES = ("checkerboard", "rectangles", "circles")


def checkerboard(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """A grayscale checkerboard over a random sub-window: each cell a random dose."""
    m = np.zeros((size, size), np.uint8)
    n = int(rng.integers(2, 9))  # cells per side
    cell = int(rng.integers(size // 16, size // (n + 1) + 1))
    span = n * cell
    r0, c0 = (int(rng.integers(0, max(1, size - span))) for _ in range(2))
    # half the cells off, the others at a random dose: grey levels calibrate the dose response
    levels = rng.choice([0, 255, 1], size=(n, n), p=[0.4, 0.3, 0.3]).astype(np.float64)
    grey = levels == 1
    levels[grey] = rng.uniform(96, 255, size=int(grey.sum()))
    block = np.kron(levels, np.ones((cell, cell)))
    m[r0 : r0 + span, c0 : c0 + span] = np.clip(block, 0, 255).astype(np.uint8)[: size - r0, : size - c0]
    return m


def rectangles(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Random rectangles: sharp convex and concave corners, several sizes and doses."""
    m = np.zeros((size, size), np.uint8)
    for _ in range(int(rng.integers(2, 9))):
        h, w = (int(v) for v in rng.integers(size // 40, size // 3, size=2))
        r, c = int(rng.integers(0, size - h)), int(rng.integers(0, size - w))
        val = 255 if rng.random() < 0.7 else int(rng.integers(128, 255))
        rr, cc = rectangle((r, c), extent=(h, w), shape=m.shape)
        m[rr, cc] = np.maximum(m[rr, cc], val)
    return m


def circles(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Random discs and rings: smooth edges and small enclosed holes."""
    m = np.zeros((size, size), np.uint8)
    for _ in range(int(rng.integers(2, 10))):
        rad = float(rng.uniform(size / 80, size / 6))
        cy, cx = (float(v) for v in rng.uniform(rad, size - rad, size=2))
        val = 255 if rng.random() < 0.7 else int(rng.integers(128, 255))
        rr, cc = disk((cy, cx), rad, shape=m.shape)
        m[rr, cc] = np.maximum(m[rr, cc], val)
        if rng.random() < 0.4 and rad > size / 40:  # a ring: punch a concentric hole
            inner = rad * float(rng.uniform(0.3, 0.75))
            rr, cc = disk((cy, cx), inner, shape=m.shape)
            m[rr, cc] = 0
    return m


FAMILIES = {"checkerboard": checkerboard, "rectangles": rectangles, "circles": circles}


def trial_ids(count: int) -> list[str]:
    return [f"trial_{i:03d}" for i in range(count)]


def trial_masks(count: int = 32, seed: int = 0, size: int = 512, families=TRIAL_FAMILIES) -> dict:
    """The trial set: families in turn, each mask from its own seeded stream.

    Mask i depends only on (seed, i), so a larger count extends a smaller one.
    """
    if count < 1:
        raise ValueError("count must be at least 1")
    for f in families:
        if f not in FAMILIES:
            raise ValueError(f"unknown mask family {f!r}; known: {sorted(FAMILIES)}")
    out = {}
    for i, mid in enumerate(trial_ids(count)):
        rng = np.random.default_rng([seed, i])
        fam = families[i % len(families)]
        m = FAMILIES[fam](rng, size)
        if m.max() == 0:  # never hand the lab an empty trial mask
            m = FAMILIES["rectangles"](rng, size)
        out[mid] = m
    return out


def write_trial_masks(out_dir, count: int = 32, seed: int = 0, size: int = 512) -> list[Path]:
    """The trial masks as ``out_dir/<id>.png`` (a new folder, or an earlier one of these)."""
    from .io import output_dir, write_png

    masks = trial_masks(count, seed, size)
    with output_dir(out_dir, command="masks trial") as tmp:
        for mid, m in masks.items():
            write_png(tmp / f"{mid}.png", m)
    return [Path(out_dir) / f"{mid}.png" for mid in masks]


# ------------------------------------------------------------------ augmentation
#
# Guan et al. 2022, 'Simulator calibration': the 4,000 augmentation masks follow "the same
# scheme as the sample masks with a greater variety [of] feature numbers and sizes as well
# as four additional feature types, vertical lines with different spacing, horizontal
# ones, the combination of two, and 2D vasculature shapes". Features are mostly at full
# dose, some at a grey dose, so the slave sees grey levels like the master's masks.


def _dose(rng: np.random.Generator, grey: float = 0.3) -> int:
    """Full dose, or with probability ``grey`` a random grey level."""
    return 255 if rng.random() >= grey else int(rng.integers(64, 255))


def checkerboard_varied(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Grayscale checkerboards with more cells and smaller cells than the trial set."""
    m = np.zeros((size, size), np.uint8)
    n = int(rng.integers(2, 17))  # cells per side
    cell = int(rng.integers(max(2, size // 64), max(size // 64, size // (n + 1)) + 1))
    span = n * cell
    r0, c0 = (int(rng.integers(0, max(1, size - span))) for _ in range(2))
    levels = rng.choice([0, 255, 1], size=(n, n), p=[0.45, 0.35, 0.2]).astype(np.float64)
    grey = levels == 1
    levels[grey] = rng.uniform(64, 255, size=int(grey.sum()))
    block = np.kron(levels, np.ones((cell, cell)))
    m[r0 : r0 + span, c0 : c0 + span] = np.clip(block, 0, 255).astype(np.uint8)[: size - r0, : size - c0]
    return m


def rectangles_varied(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """1 to 30 rectangles from a few pixels to half the field; some are frames (holes)."""
    m = np.zeros((size, size), np.uint8)
    n = int(rng.integers(1, 31))
    # many features come small, few features come large
    top = max(size // 32, int(size / 2 / np.sqrt(n)))
    for _ in range(n):
        h, w = (int(v) for v in rng.integers(max(2, size // 128), top + 1, size=2))
        r, c = int(rng.integers(0, size - h)), int(rng.integers(0, size - w))
        rr, cc = rectangle((r, c), extent=(h, w), shape=m.shape)
        m[rr, cc] = np.maximum(m[rr, cc], _dose(rng))
        if rng.random() < 0.2 and min(h, w) > size // 16:  # a frame: a rectangular hole
            t = int(rng.integers(max(2, size // 128), min(h, w) // 3 + 1))
            rr, cc = rectangle((r + t, c + t), extent=(h - 2 * t, w - 2 * t), shape=m.shape)
            m[rr, cc] = 0
    return m


def circles_varied(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """1 to 30 discs and rings from a few pixels to a third of the field across."""
    m = np.zeros((size, size), np.uint8)
    n = int(rng.integers(1, 31))
    top = max(size / 40, size / 5 / np.sqrt(n) * 2)
    for _ in range(n):
        rad = float(rng.uniform(max(1.5, size / 256), top))
        cy, cx = (float(v) for v in rng.uniform(0, size, size=2))
        rr, cc = disk((cy, cx), rad, shape=m.shape)
        m[rr, cc] = np.maximum(m[rr, cc], _dose(rng))
        if rng.random() < 0.4 and rad > size / 64:  # a ring
            inner = rad * float(rng.uniform(0.3, 0.85))
            rr, cc = disk((cy, cx), inner, shape=m.shape)
            m[rr, cc] = 0
    return m


def vertical_lines(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Vertical lines of random width at random spacing (regular or irregular), over a
    random window: from dense gratings that merge in the print to isolated lines."""
    m = np.zeros((size, size), np.uint8)
    r0, r1 = sorted(int(v) for v in rng.integers(0, size, size=2))
    if r1 - r0 < size // 8:
        r0, r1 = 0, size
    width = int(rng.integers(1, max(2, size // 16)))
    gap = int(rng.integers(1, max(2, size // 8)))
    regular = rng.random() < 0.5
    c = int(rng.integers(0, width + gap))
    c_end = int(rng.integers(size // 2, size + 1))
    val = _dose(rng)
    while c < c_end:
        w = width if regular else int(rng.integers(1, 2 * width + 1))
        m[r0:r1, c : c + w] = val if regular else _dose(rng)
        c += w + (gap if regular else int(rng.integers(1, 2 * gap + 1)))
    return m


def horizontal_lines(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Horizontal lines: the vertical family turned by 90 degrees."""
    return np.ascontiguousarray(vertical_lines(rng, size).T)


def crossed_lines(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """The combination of vertical and horizontal lines: grids and meshes."""
    return np.maximum(vertical_lines(rng, size), horizontal_lines(rng, size))


def _tapered_segment(m: np.ndarray, p0, p1, w0: float, w1: float, val: int) -> None:
    """A straight segment whose width goes from w0 to w1 (a quadrilateral), with round
    ends; drawn with OpenCV at 1/16 pixel precision (fast: a tree has hundreds)."""
    import cv2

    (y0, x0), (y1, x1) = p0, p1
    d = np.hypot(y1 - y0, x1 - x0)
    if d < 1e-6:
        return
    ny, nx = -(x1 - x0) / d, (y1 - y0) / d  # unit normal
    ys = [y0 + ny * w0 / 2, y1 + ny * w1 / 2, y1 - ny * w1 / 2, y0 - ny * w0 / 2]
    xs = [x0 + nx * w0 / 2, x1 + nx * w1 / 2, x1 - nx * w1 / 2, x0 - nx * w0 / 2]
    pts = np.round(np.stack([xs, ys], axis=1) * 16).astype(np.int32)
    cv2.fillConvexPoly(m, pts, int(val), lineType=cv2.LINE_8, shift=4)
    for (y, x), w in (((y0, x0), w0), ((y1, x1), w1)):
        if w >= 2:
            cv2.circle(m, (int(round(x * 16)), int(round(y * 16))), int(round(w / 2 * 16)), int(val), -1, cv2.LINE_8, shift=4)


def vasculature(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """2D vasculature: one to three branching trees of tapered, slightly winding vessels.

    Each tree enters from a border (or starts inside), and every vessel splits into two
    thinner, shorter daughters at a random angle, down to vessels of one or two pixels.
    """
    m = np.zeros((size, size), np.uint8)
    val = _dose(rng, grey=0.2)
    for _ in range(int(rng.integers(1, 4))):
        if rng.random() < 0.7:  # enter from a border, heading inwards
            side = int(rng.integers(4))
            t = float(rng.uniform(0.15, 0.85)) * size
            start = [(0.0, t), (t, size - 1.0), (size - 1.0, t), (t, 0.0)][side]
            angle = [np.pi / 2, np.pi, -np.pi / 2, 0.0][side]  # (dy, dx) = (sin, cos)
        else:
            start = tuple(float(v) for v in rng.uniform(0.2 * size, 0.8 * size, size=2))
            angle = float(rng.uniform(-np.pi, np.pi))
        width = float(rng.uniform(size / 64, size / 20))
        length = float(rng.uniform(size / 8, size / 3))
        depth = int(rng.integers(3, 7))
        stack = [(start, angle, width, length, 0)]
        while stack:
            p, a, w, L, level = stack.pop()
            w_end = w * float(rng.uniform(0.7, 0.9))
            steps = int(rng.integers(2, 5))  # a winding vessel: a few straight pieces
            for k in range(steps):
                a += float(rng.normal(0, 0.2))
                q = (p[0] + np.sin(a) * L / steps, p[1] + np.cos(a) * L / steps)
                wa = w + (w_end - w) * k / steps
                wb = w + (w_end - w) * (k + 1) / steps
                _tapered_segment(m, p, q, wa, wb, val)
                p = q
            if level + 1 < depth and w_end > 1.2 and -size / 4 < p[0] < 1.25 * size and -size / 4 < p[1] < 1.25 * size:
                spread = float(rng.uniform(0.3, 0.8))
                share = float(rng.uniform(0.35, 0.65))  # Murray-like split of the width
                for sgn, frac in ((-1, share), (1, 1 - share)):
                    wd = max(1.0, w_end * float(np.sqrt(frac) * rng.uniform(1.0, 1.3)))
                    stack.append((p, a + sgn * spread * float(rng.uniform(0.6, 1.2)), wd, L * float(rng.uniform(0.6, 0.85)), level + 1))
    return m


AUGMENT_FAMILIES = {
    "checkerboard": checkerboard_varied,
    "rectangles": rectangles_varied,
    "circles": circles_varied,
    "vertical_lines": vertical_lines,
    "horizontal_lines": horizontal_lines,
    "crossed_lines": crossed_lines,
    "vasculature": vasculature,
}


def family_counts(count: int, families=None) -> dict:
    """How many masks of each family: ``families`` is a list of names (equal shares) or
    a mapping name -> weight; counts are proportional (largest remainder), so weights
    that are counts summing to ``count`` are kept exactly."""
    if families is None:
        families = list(AUGMENT_FAMILIES)
    weights = {f: 1.0 for f in families} if not isinstance(families, dict) else {f: float(w) for f, w in families.items()}
    for f, w in weights.items():
        if f not in AUGMENT_FAMILIES:
            raise ValueError(f"unknown augmentation family {f!r}; known: {list(AUGMENT_FAMILIES)}")
        if not w >= 0:
            raise ValueError(f"family weight must be >= 0, got {f}: {w}")
    total = sum(weights.values())
    if total <= 0:
        raise ValueError("at least one augmentation family needs a positive weight")
    exact = {f: count * w / total for f, w in weights.items()}
    counts = {f: int(np.floor(v)) for f, v in exact.items()}
    rest = count - sum(counts.values())
    for f in sorted(exact, key=lambda f: counts[f] - exact[f])[:rest]:
        counts[f] += 1
    return counts


def augmentation_families(count: int, seed: int = 0, families=None) -> list[str]:
    """The family of each of ``count`` masks: the counts of ``family_counts`` in a seeded
    random order (so any prefix mixes all families)."""
    counts = family_counts(count, families)
    labels = np.array([f for f, n in counts.items() for _ in range(n)], dtype=object)
    order = np.random.default_rng([seed, 0xA06]).permutation(len(labels))
    return labels[order].tolist()


def augmentation_mask(family: str, seed: int, index: int, size: int = 512) -> np.ndarray:
    """Mask ``index`` of an augmentation set: depends only on (family, seed, index)."""
    rng = np.random.default_rng([seed, 0xA06, index])
    gen = AUGMENT_FAMILIES[family]
    for _ in range(8):  # never an empty mask
        m = gen(rng, size)
        if m.max() > 0:
            return m
    return rectangles_varied(rng, size)
