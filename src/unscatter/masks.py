"""Mask families: the paper's trial masks, its augmentation masks, and test patterns.

Guan et al. 2022, 'Trial data acquisition': 32 masks of three randomized families:
random grayscale checkerboards, randomly positioned and sized rectangles, and randomly
positioned circular shapes. The test patterns (gratings, Siemens stars, graded dots and
lines, partial prints) are the prints registration is benchmarked on. Masks are 8-bit,
255 = 100 % dose.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
from skimage.draw import disk, rectangle

from .settings import TRIAL_MASKS

TRIAL_FAMILIES = ("checkerboard", "rectangles", "circles")


# Registration marks: three solid squares at full grey in three corners of the field,
# with a cleared band around each. A print's pose then rests on three features far apart,
# whatever the rest of the mask is: one block or dot whose scale only its size would set,
# a star or grating that maps onto itself turned or shifted, a near-threshold feature that
# may not cure at all (its not curing is then measured, not a failed registration). Large
# enough to cure at the field's corners in a dim, strongly scattering lab (40 px: the
# centre dose stays above 0.95 of the plateau up to a scatter sigma of 9 px, 26 um on the
# paper's printer).
FIDUCIAL_PX = 40
FIDUCIAL_INSET_PX = 28  # from the field's edge to the mark
FIDUCIAL_GUARD_PX = 20  # cleared around the mark (about twice a strong scatter's sigma)


@functools.lru_cache(maxsize=8)
def fiducial_marks(size: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """(marks, cleared): boolean masks of the three registration marks (top left, top
    right, bottom left: no turn of the field maps them onto themselves) and of the area
    around them that no other feature may use; on a field of ``size`` px, the sizes
    above scaled by size / 512. Read-only, and kept for the last few sizes: a benchmark
    job asks for them for every mask."""
    marks = np.zeros((size, size), bool)
    clear = np.zeros((size, size), bool)
    k = size / 512  # the sizes above are for the paper's 512 px field
    w, a, g = (max(1, round(v * k)) for v in (FIDUCIAL_PX, FIDUCIAL_INSET_PX, FIDUCIAL_GUARD_PX))
    for r, c in ((a, a), (a, size - a - w), (size - a - w, a)):
        marks[r : r + w, c : c + w] = True
        clear[max(0, r - g) : r + w + g, max(0, c - g) : c + w + g] = True
    marks.setflags(write=False)
    clear.setflags(write=False)
    return marks, clear


def dense_reference_mask(size: int = 512) -> np.ndarray:
    """A dense reference (batch.yaml ``dense_reference``): a centred square of 5/8 of the
    field at full grey, to be printed 3 to 5 times as long as the trial prints so that its
    polymer cures through, and imaged as they are; the registration measures the fully
    cured polymer's level on its interior (``imaging.flatfield.reference_level``)."""
    m = np.zeros((size, size), np.uint8)
    a = (size - round(size * 5 / 8)) // 2
    m[a : size - a, a : size - a] = 255
    return m


def with_fiducials(mask: np.ndarray) -> np.ndarray:
    """``mask`` with the registration marks (``fiducial_marks``) and their cleared band."""
    marks, clear = fiducial_marks(mask.shape[0])
    out = mask.copy()
    out[clear] = 0
    out[marks] = 255
    return out


def carries_marks(mask: np.ndarray) -> bool:
    """Whether ``mask`` holds the registration marks (``with_fiducials``): the three
    squares at full grey and nothing else in their cleared band. A square field only."""
    if mask.ndim != 2 or mask.shape[0] != mask.shape[1] or mask.shape[0] < 64:
        return False
    marks, clear = fiducial_marks(mask.shape[0])
    return bool((mask[marks] == 255).all() and not mask[clear & ~marks].any())


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


_TRIAL = TRIAL_MASKS.default


def trial_masks(count: int = _TRIAL.count, seed: int = _TRIAL.seed, size: int = _TRIAL.size, families=TRIAL_FAMILIES) -> dict:
    """The trial set: families in turn, each mask from its own seeded stream.

    Mask i depends only on (seed, i), so a larger count extends a smaller one.
    """
    TRIAL_MASKS.make(count=count, seed=seed, size=size)
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


def write_trial_masks(out_dir, count: int = _TRIAL.count, seed: int = _TRIAL.seed, size: int = _TRIAL.size,
                      fiducials: bool = _TRIAL.paper_fiducials) -> list[Path]:
    """The trial masks as ``out_dir/<id>.png`` (a new folder, or an earlier one of these),
    with the registration marks (``with_fiducials``) where ``fiducials``."""
    from .io import output_dir, write_png

    masks = trial_masks(count, seed, size)
    if fiducials:
        masks = {mid: with_fiducials(m) for mid, m in masks.items()}
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


# ------------------------------------------------------------------ test patterns
#
# Registration has to hold on any print a lab images, not only on the trial families it
# was tuned on. The test patterns are the prints that are hard to register: gratings (a
# shift by whole periods fits almost as well as the true pose), gratings cut off by the
# field edge or truncated (only one end fixes the phase), Siemens stars (every spatial
# frequency around one centre), isolated dots and lines of graded size (the smallest do
# not print), and prints of which only part cures (a grey ramp; a whole pattern near the
# cure threshold). The paper's three trial families are part of the set, so a benchmark
# over the test patterns also covers what registration was tuned on.

_ORIENTATIONS = (0.0, 90.0, 45.0, -45.0, None)  # None: a random angle


def _test_dose(rng: np.random.Generator) -> int:
    """Mostly full dose; sometimes a grey level that still prints in most labs."""
    return 255 if rng.random() < 0.8 else int(rng.integers(170, 256))


def _line_angle(rng: np.random.Generator, angle_deg=None) -> float:
    """Direction of the lines from the x axis (degrees): 0, 90, +-45 or a random angle."""
    if angle_deg is not None:
        return float(angle_deg)
    a = _ORIENTATIONS[int(rng.integers(len(_ORIENTATIONS)))]
    return float(rng.uniform(-90.0, 90.0)) if a is None else a


def _pitch(rng: np.random.Generator, lo: int = 3, hi: int = 30) -> int:
    """A grating pitch in mask pixels, log-uniform: every octave of pitch equally often."""
    return int(np.clip(np.round(np.exp(rng.uniform(np.log(lo), np.log(hi)))), lo, hi))


def _line_width(pitch: int, duty: float) -> int:
    """Line width of a grating: the duty cycle on whole pixels, never 0 or the full pitch."""
    return int(np.clip(np.round(duty * pitch), 1, pitch - 1))


def _window(rng: np.random.Generator, size: int, lo: float = 0.25, hi: float = 0.85):
    """A random axis-aligned sub-window (r0, r1, c0, c1) of the field."""
    h, w = (int(v) for v in rng.uniform(lo * size, hi * size, size=2))
    r0, c0 = int(rng.integers(0, size - h + 1)), int(rng.integers(0, size - w + 1))
    return r0, r0 + h, c0, c0 + w


def _across(size: int, angle_deg: float) -> np.ndarray:
    """The coordinate across lines that run at ``angle_deg`` from the x axis (pixels)."""
    ax = np.arange(size, dtype=np.float64)
    th = np.deg2rad(angle_deg)
    return -np.sin(th) * ax[None, :] + np.cos(th) * ax[:, None]


def grating_lines(size: int, pitch: float, width: float, angle_deg: float, phase: float = 0.0) -> np.ndarray:
    """Boolean field of parallel lines: ``width`` px wide every ``pitch`` px, at ``angle_deg``
    from the x axis (0: horizontal lines, 90: vertical). At 0 or 90 degrees with whole-pixel
    pitch and width every period has exactly that many pixels on."""
    return np.mod(_across(size, angle_deg) - phase, pitch) < width


def grating(rng: np.random.Generator, size: int = 512, *, pitch=None, duty=None, angle_deg=None) -> np.ndarray:
    """A line grating of 3 to 30 px pitch (duty cycle 0.3 to 0.7) over a random sub-window,
    at 0, 90, +-45 degrees or a random angle."""
    pitch = int(pitch) if pitch is not None else _pitch(rng)
    width = _line_width(pitch, float(duty) if duty is not None else float(rng.uniform(0.3, 0.7)))
    angle = _line_angle(rng, angle_deg)
    r0, r1, c0, c1 = _window(rng, size)
    on = grating_lines(size, pitch, width, angle, float(rng.integers(0, pitch)))
    m = np.zeros((size, size), np.uint8)
    m[r0:r1, c0:c1] = np.where(on[r0:r1, c0:c1], _test_dose(rng), 0)
    return m


def grating_cutoff(rng: np.random.Generator, size: int = 512, *, pitch=None, duty=None, angle_deg=None,
                   variant=None) -> np.ndarray:
    """A grating that breaks its period at one place only.

    ``variant='edge'``: the grating runs to the edge of the mask field on one side, so the
    print ends there with the field and not with a line. ``variant='truncated'``: lines at
    0 or 90 degrees whose last line is cut short, so only that end differs from a shift by
    whole periods.
    """
    variant = variant or ("edge", "truncated")[int(rng.integers(2))]
    if variant == "edge":
        pitch = int(pitch) if pitch is not None else _pitch(rng)
        width = _line_width(pitch, float(duty) if duty is not None else float(rng.uniform(0.3, 0.7)))
        angle = _line_angle(rng, angle_deg)
        win = list(_window(rng, size))
        side = int(rng.integers(4))  # top, bottom, left, right
        win[side] = (0, size, 0, size)[side]
        r0, r1, c0, c1 = win
        on = grating_lines(size, pitch, width, angle, float(rng.integers(0, pitch)))
        m = np.zeros((size, size), np.uint8)
        m[r0:r1, c0:c1] = np.where(on[r0:r1, c0:c1], _test_dose(rng), 0)
        return m
    if variant != "truncated":
        raise ValueError(f"variant must be 'edge' or 'truncated', not {variant!r}")
    # horizontal lines from row r0, whole periods and then one line cut short; turned by 90
    # degrees half of the time. At least 2 px lines so that a part of one can remain.
    pitch = int(pitch) if pitch is not None else _pitch(rng, lo=4)
    width = max(2, _line_width(pitch, float(duty) if duty is not None else float(rng.uniform(0.3, 0.7))))
    angle = _line_angle(rng, angle_deg) if angle_deg is not None else (0.0, 90.0)[int(rng.integers(2))]
    if angle not in (0.0, 90.0):
        raise ValueError("a truncated grating runs at 0 or 90 degrees")
    periods = max(3, int(rng.uniform(0.2, 0.8) * size / pitch))
    periods = min(periods, (size - width) // pitch)
    extent = periods * pitch + int(rng.integers(1, width))  # the last line keeps 1..width-1 px
    r0 = int(rng.integers(0, size - extent + 1))
    _, _, c0, c1 = _window(rng, size)
    rows = np.arange(size)
    on = (np.mod(rows - r0, pitch) < width) & (rows >= r0) & (rows < r0 + extent)
    m = np.zeros((size, size), np.uint8)
    m[np.ix_(on, np.arange(c0, c1))] = _test_dose(rng)
    return np.ascontiguousarray(m.T) if angle == 90.0 else m


def siemens_star(rng: np.random.Generator, size: int = 512, *, spokes=None) -> np.ndarray:
    """A Siemens star of 8 to 36 spokes: every pitch from the rim down to where the
    spokes merge at the centre; sometimes with a small open centre."""
    n = int(spokes) if spokes is not None else int(rng.integers(8, 37))
    radius = float(rng.uniform(0.12, 0.45)) * size
    cy, cx = (float(v) for v in rng.uniform(radius + 2, size - radius - 2, size=2))
    ax = np.arange(size, dtype=np.float64)
    dy, dx = ax[:, None] - cy, ax[None, :] - cx
    r = np.hypot(dy, dx)
    phi = np.arctan2(dy, dx) + float(rng.uniform(0, 2 * np.pi))
    star = (r <= radius) & (np.mod(phi * n / (2 * np.pi), 1.0) < 0.5)
    if rng.random() < 0.3:
        star &= r >= float(rng.uniform(0.03, 0.12)) * radius
    return np.where(star, _test_dose(rng), 0).astype(np.uint8)


def _graded_sizes(rng: np.random.Generator, lo: int = 1, hi: int = 20) -> np.ndarray:
    """6 to 10 sizes from ``lo`` to ``hi`` px, geometric steps (both ends always present)."""
    return np.unique(np.round(np.geomspace(lo, hi, int(rng.integers(6, 11))))).astype(int)


def dots(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Isolated dots of graded diameter (1 to 20 px) on a grid: diameter grows along the
    rows (or the columns), 1 to 4 repeats; at least 25 px between the largest dots."""
    d = _graded_sizes(rng)
    if rng.random() < 0.5:
        d = d[::-1]
    cell = int(min(rng.integers(45, 65), (size - 16) // len(d)))
    reps = int(rng.integers(1, 5))
    gw, gh = len(d) * cell, reps * cell
    x0 = int(rng.integers(8, size - gw - 8 + 1)) + cell // 2
    y0 = int(rng.integers(8, size - gh - 8 + 1)) + cell // 2
    ax = np.arange(size, dtype=np.float64)
    j = np.clip(np.round((ax - x0) / cell).astype(int), 0, len(d) - 1)  # nearest grid column
    i = np.clip(np.round((ax - y0) / cell).astype(int), 0, reps - 1)
    diam = d[j][None, :].astype(np.float64)
    # even diameters are centred between pixels, so a dot of d px is d px across
    cx = (x0 + j * cell)[None, :] + 0.5 * (diam % 2 == 0)
    cy = (y0 + i * cell)[:, None] + 0.5 * (diam % 2 == 0)
    on = (ax[None, :] - cx) ** 2 + (ax[:, None] - cy) ** 2 <= (diam / 2) ** 2
    m = np.where(on, _test_dose(rng), 0).astype(np.uint8)
    return np.ascontiguousarray(m.T) if rng.random() < 0.5 else m


def lines(rng: np.random.Generator, size: int = 512, *, angle_deg=None) -> np.ndarray:
    """Isolated parallel lines of graded width (1 to 20 px), 24 to 40 px apart, at 0, 90,
    +-45 degrees or a random angle; the set is kept inside the field at any angle."""
    w = _graded_sizes(rng)
    if rng.random() < 0.5:
        w = w[::-1]
    gap = int(rng.integers(24, 41))
    left = np.concatenate([[0], np.cumsum(w[:-1] + gap)]).astype(np.float64)  # left edge of each line
    across = float(left[-1] + w[-1])
    angle = _line_angle(rng, angle_deg)
    c, s = abs(np.cos(np.deg2rad(angle))), abs(np.sin(np.deg2rad(angle)))
    # half-extent of the set along x and y: (c L + s A) / 2 and (s L + c A) / 2 must stay
    # within the field, 8 px margin
    room = size / 2 - 8
    lmax = min((2 * room - s * across) / c if c > 1e-9 else np.inf, (2 * room - c * across) / s if s > 1e-9 else np.inf)
    length = float(min(rng.uniform(0.3, 0.85) * size, lmax))
    hx, hy = (c * length + s * across) / 2, (s * length + c * across) / 2
    xc = float(rng.uniform(hx + 8, size - hx - 8)) if size - 2 * hx > 16 else size / 2
    yc = float(rng.uniform(hy + 8, size - hy - 8)) if size - 2 * hy > 16 else size / 2
    xc, yc = np.round(xc), np.round(yc)
    ax = np.arange(size, dtype=np.float64)
    th = np.deg2rad(angle)
    X, Y = ax[None, :] - xc, ax[:, None] - yc
    along = np.cos(th) * X + np.sin(th) * Y
    u = _across(size, angle) - (-np.sin(th) * xc + np.cos(th) * yc) + np.round(across / 2)
    idx = np.clip(np.searchsorted(left, u, side="right") - 1, 0, len(w) - 1)  # the line to the left
    on = (u >= 0) & (u - left[idx] < w[idx]) & (np.abs(along) <= length / 2)
    return np.where(on, _test_dose(rng), 0).astype(np.uint8)


def _solid_base(rng: np.random.Generator, size: int, kinds) -> np.ndarray:
    """A pattern of relative dose in [0, 1] to be given a grey level: a block, one of the
    trial families, a grating of 10 px pitch or more, or a Siemens star."""
    kind = kinds[int(rng.integers(len(kinds)))]
    if kind == "block":
        r0, r1, c0, c1 = _window(rng, size, 0.3, 0.9)
        b = np.zeros((size, size))
        b[r0:r1, c0:c1] = 1.0
        return b
    if kind == "grating":
        return grating(rng, size, pitch=_pitch(rng, lo=10)) > 0
    gen = siemens_star if kind == "siemens_star" else FAMILIES[kind]
    return gen(rng, size) > 0


def partial(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """A pattern under a grey ramp: full dose (200 to 255) at one end of the pattern, 20 to
    90 at the other, so the print ends where the dose falls below the cure threshold
    (where depends on the lab) and the rest of the mask never prints."""
    base = _solid_base(rng, size, ("block", "rectangles", "circles", "checkerboard", "grating"))
    while not base.any():  # a small field can leave a drawn pattern empty
        base = _solid_base(rng, size, ("block", "rectangles", "circles", "checkerboard", "grating"))
    hi, lo = float(rng.uniform(200, 255)), float(rng.uniform(20, 90))
    th = float(rng.uniform(0, 2 * np.pi))
    t = _across(size, np.rad2deg(th))
    on = t[base > 0]
    t = np.clip((t - on.min()) / max(on.max() - on.min(), 1.0), 0, 1)  # 0..1 across the pattern
    return np.round(base * (hi + (lo - hi) * t)).astype(np.uint8)


def near_threshold(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """A whole pattern at one grey level of 90 to 150 (dose 0.35 to 0.59 of full): near
    the cure threshold, so the print is thin, partial or absent depending on the lab and
    on the illumination field."""
    base = _solid_base(rng, size, ("block", "rectangles", "circles", "checkerboard", "grating", "siemens_star"))
    return np.where(base > 0, int(rng.integers(90, 151)), 0).astype(np.uint8)


TEST_PATTERNS = {
    **FAMILIES,
    "grating": grating,
    "grating_cutoff": grating_cutoff,
    "siemens_star": siemens_star,
    "dots": dots,
    "lines": lines,
    "partial": partial,
    "near_threshold": near_threshold,
}


def test_pattern_of(mask_id: str) -> str:
    """The pattern of a test mask id such as ``grating_cutoff_012``."""
    return mask_id.rsplit("_", 1)[0]


def test_pattern_masks(count: int, seed: int = 0, size: int = 512, patterns=None) -> dict:
    """``count`` test masks, id ``<pattern>_<index>`` -> uint8 mask.

    Patterns are drawn in shuffled rounds: each run of ``len(patterns)`` consecutive masks
    holds every pattern once, in a random order, so any set at least that large covers
    them all. Mask i depends only on (seed, i), so a larger count extends a smaller one.
    """
    names = list(patterns) if patterns is not None else list(TEST_PATTERNS)
    unknown = [p for p in names if p not in TEST_PATTERNS]
    if unknown or not names:
        raise ValueError(f"unknown test patterns {unknown}; known: {list(TEST_PATTERNS)}")
    if count < 1:
        raise ValueError("count must be at least 1")
    out = {}
    for i in range(count):
        order = np.random.default_rng([seed, 0x7E5, i // len(names)]).permutation(len(names))
        name = names[order[i % len(names)]]
        rng = np.random.default_rng([seed, 0x7E57, i])
        for _ in range(8):  # never hand the lab an empty mask
            m = TEST_PATTERNS[name](rng, size)
            if m.max() > 0:
                break
        else:
            m = rectangles(rng, size)
        out[f"{name}_{i:03d}"] = m
    return out


test_pattern_of.__test__ = test_pattern_masks.__test__ = False  # library functions, not pytest tests
