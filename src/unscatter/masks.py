"""Mask families: the paper's trial masks (and, later, the augmentation families).

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
    from .io import write_png

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for mid, m in trial_masks(count, seed, size).items():
        p = out_dir / f"{mid}.png"
        write_png(p, m)
        paths.append(p)
    return paths
