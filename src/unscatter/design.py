"""Designed trial masks: the prints that teach the printer model the most.

The paper prints 32 random masks (checkerboards, rectangles, circles). Most of their
pixels teach the model nothing: a large solid area prints the same under any sigma. Here
the masks are chosen from a large candidate pool so that the printer model's parameters,
the effect library's included, are identifiable from the fewest prints.

Criterion: pseudo-Bayesian D-optimality (Chaloner & Verdinelli 1995) on the sensitivity
of the simulated print to the parameters.

- The model is the base model with every library effect added (``model.extend_params``),
  so the design also teaches the effects the diagnosis may have to name. Parameters are
  scaled to their bounds (u = (theta - lower) / (upper - lower)), so no unit dominates.
- The information of one print at parameters u is F = sum over pixels of w J J^T, with J
  the derivative with respect to u of the cure margin (D - T) / T and w the pixel's
  weight under a model of the print's noise (``NOISE``, ``pixel_weights``): the margin's
  change at an edge over its gradient is how far the edge moves. Only pixels near an edge
  contribute; solid interiors none. The default noise model is the edge's: cells
  scatter the dose (``DOSE_NOISE``) over patches of a cell's size (``CORRELATION_PX``),
  which moves an edge by the dose noise over the dose's gradient, on top of a floor of
  ``EDGE_SD_PX``; each print's overall dose varies too (``PRINT_DOSE_SD``), and what a
  dose change mimics is profiled out of each print's information. A shallow edge (a grey
  level near the threshold, a grating whose lines merge in the dose) moves further with
  a parameter and as much further with the noise: it prints as patches where the cells
  push the dose across the threshold, and teaches no more per length of edge than a
  steep one. The older model (``NOISE = "pixel"``: every uncertain pixel an independent
  binary pixel of the smooth print, ``TEMPERATURE``) counted such a band's width of
  uncertain pixels as that many measurements, and filled the designs with near-threshold
  areas whose patchy prints carried much of the diagnosis's held-out error.
- The parameters are unknown before the prints, so the criterion is the mean of
  log det(prior precision + sum of F) over draws from a prior (``design_prior``): a
  design good for one printer only is not chosen. With a calibration (``--model``) the
  draws and the prior precision come from its fit and bootstrap spread (sequential
  design: the next batch goes where the fit is least sure); the prints already made add
  their information to the prior, and effects the diagnosis could not yet decide on get
  extra weight (Ds-optimality on their parameters).
- Masks are added greedily (each step the candidate that raises the criterion most),
  the standard approximation to exact D-optimal design; every step's gain is reported.
- ``criterion="discrimination"`` adds a term for telling the library's effects apart
  (``discrimination``): for every candidate effect at a size drawn from
  ``EFFECT_SIZES`` and every rival (the model without it, or with one other effect in
  its place), the lack of fit that the rival's best linearised fit leaves (Atkinson &
  Fedorov's T-optimality), summed as log(1 + T) over the pairs. ``separation.tsv``
  reports every pair for the design and for random paper masks.
- ``criterion="paired"`` adds, for every candidate effect, the paired t-statistic over
  prints that the diagnosis's acceptance computes, as the design predicts it from each
  print's share of the effect's lack of fit under the model without it (``paired``): the
  test over prints refuses an effect whose evidence sits in one or two prints, however
  large. ``paired.tsv`` reports every effect's predicted t for the design and for random
  paper masks. The default (``trial_masks.criterion``) since 2026-11-30: through the
  registration it named more effects than ``d`` from the same labs at 8 and at 32 prints
  (docs/trial-masks.md, "Spreading the evidence over the prints"); ``criterion="d"`` is D-optimality alone.

D-optimality (and not A- or E-optimality) because it is invariant to re-scaling each
parameter, minimises the volume of the parameters' joint confidence region, and its
greedy form has a guarantee (the log det is submodular in the added prints).

Jacobians by forward differences over parameter sets evaluated in one batched pass of
``model.FixedMasks`` (the masks' spectra are computed once and reused by every parameter
set); on a grid of every second pixel (``FixedMasks.decimated``), exact for kernels of
sigma above ~3 px and accurate enough to rank masks below that.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from . import masks as M
from .masks import with_fiducials
from .settings import TRIAL_MASKS
from .model import FixedMasks, Params, default_params, effect_names, extend_params, get_model, load_params, masks_to_tensor

log = logging.getLogger(__name__)

TEMPERATURE = 0.1  # pixel model: smooth threshold width as a fraction of T (the calibration's coarse temperature)
PIXEL_VARIANCE = 0.25  # pixel model: variance of a binary print pixel at an uncertain edge (its largest)
# Print errors are not independent from pixel to pixel: cells (10 to 15 um, 3 to 5 DMD
# pixels) move an edge over a stretch. One independent error per CORRELATION_PX^2 pixels.
CORRELATION_PX = 4
# The edge model of the print noise (``NOISE = "edge"``): cells scatter the dose by
# DOSE_NOISE (a share of T) over patches of CORRELATION_PX, which moves an edge by
# DOSE_NOISE T / |grad D| as one over a patch, and the edge's measured place has a floor
# of EDGE_SD_PX (registration, the camera's pixels). One independent measurement of the
# edge's place per CORRELATION_PX of edge: a shallow edge (near-threshold grey, a thin
# line's faint sides) moves further with a parameter, and as much further with the
# noise, so it teaches no more than a steep one. The edges are found from the cure
# margin (D - T) / T, smooth at every kernel width (``pixel_weights``), and each print's
# overall dose is a nuisance of PRINT_DOSE_SD (``print_gram``). ``NOISE = "pixel"``:
# every pixel near an edge of the smooth print (``TEMPERATURE``) an independent binary
# pixel of PIXEL_VARIANCE per CORRELATION_PX^2, which counts a shallow edge's wide band of
# uncertain pixels as that many measurements.
NOISE = "edge"
DOSE_NOISE = 0.03  # the cells' dose noise, a share of T (the virtual lab's 3 %; random labs 1 to 6 %)
EDGE_SD_PX = 0.5
PRINT_DOSE_SD = 0.02  # print-to-print dose, relative (the virtual lab's 1.5 %; random labs 0 to 4 %)
STEP = 0.01  # finite-difference step, as a share of each parameter's bound range
DECIMATION = 2  # Jacobians on every 2nd pixel

# Design prior: where a lab's printer may lie, before any print (the parameters' bounds
# are wider: they bound the search, not the belief). Per parameter: ("log", lo, hi),
# ("uniform", lo, hi) or ("normal", mean, sd), clipped to the bounds.
PRIOR = {
    "c1": ("normal", 0.0, 0.04), "c2": ("normal", 0.0, 0.04), "c3": ("normal", -0.04, 0.04), "c4": ("normal", -0.04, 0.04),
    "ill_xy": ("normal", 0.0, 0.03), "ill_xr2": ("normal", 0.0, 0.03), "ill_yr2": ("normal", 0.0, 0.03),
    "ill_r4": ("normal", 0.0, 0.03),
    "dose_gamma": ("log", 0.8, 1.25),
    "sigma_px": ("log", 1.5, 8.0),
    "aniso_ratio": ("log", 0.8, 1.4), "aniso_angle_deg": ("uniform", -45.0, 45.0),
    "tail_fraction": ("uniform", 0.0, 0.3), "tail_length_px": ("log", 5.0, 30.0),
    "T": ("uniform", 0.3, 0.75),
    "edge_offset_px": ("uniform", -2.0, 2.0),
}

POOL_PATTERNS = ("checkerboard", "rectangles", "circles", "composite", "graded_grid", "dots", "lines", "partial",
                 "near_threshold", "grating_cutoff", "ramp_steps")
# share of the pool per pattern (composites and graded grids pack many features into one print)
POOL_WEIGHTS = {"composite": 4.0, "graded_grid": 3.0, "ramp_steps": 1.5}


# ------------------------------------------------------------------ candidate masks
_TILE_PATTERNS = ("grating", "dots", "lines", "partial", "near_threshold", "circles", "rectangles", "siemens_star",
                  "ramp_steps")


def ramp_steps(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Blocks of stepped grey levels (a density step wedge) with corners at a drawn
    angle: where the print stops along the wedge measures the threshold and the dose
    response, its corners the kernel."""
    n = int(rng.integers(4, 9))
    levels = np.linspace(float(rng.uniform(60, 110)), float(rng.uniform(180, 255)), n)
    if rng.random() < 0.5:
        levels = levels[::-1]
    m = np.zeros((size, size), np.float64)
    w = size * float(rng.uniform(0.6, 0.9)) / n
    h = size * float(rng.uniform(0.25, 0.6))
    r0 = float(rng.uniform(0, size - h))
    c0 = float(rng.uniform(0, size - n * w))
    gap = max(2.0, w * float(rng.uniform(0.1, 0.4)))
    ax = np.arange(size, dtype=np.float64)
    for i, lv in enumerate(levels):
        cols = (ax >= c0 + i * w) & (ax < c0 + (i + 1) * w - gap)
        rows = (ax >= r0) & (ax < r0 + h)
        m[np.ix_(rows, cols)] = lv
    m = np.round(m).astype(np.uint8)
    k = int(rng.integers(4))
    return np.ascontiguousarray(np.rot90(m, k))


def graded_grid(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """A checkerboard whose cells grow geometrically (about 3 to 40 px) along one axis and
    whose grey level rises (0.35 to 1 of full dose) along the other, over a drawn part of
    the field at a drawn angle: corners and edges at every pitch, dose and place in one
    print, with no period to register by."""
    lo, hi = float(rng.uniform(2.5, 5)), float(rng.uniform(25, 45))
    g0, g1 = float(rng.uniform(0.35, 0.55)), float(rng.uniform(0.85, 1.0))
    th = np.deg2rad(float(rng.uniform(-45, 45)))
    ax = np.arange(size, dtype=np.float64) - size / 2
    X, Y = ax[None, :], ax[:, None]
    u = (np.cos(th) * X + np.sin(th) * Y) / size + 0.5  # 0..1 across (inside the inscribed square)
    v = (-np.sin(th) * X + np.cos(th) * Y) / size + 0.5
    # cell index along u of a geometric chirp: cell k spans lo * r^k
    r = (hi / lo) ** (1 / 8)
    pos = u * size
    k = np.floor(np.log1p(np.clip(pos, 0, None) * (r - 1) / lo) / np.log(r))
    cell = lo * r ** k
    row = np.floor(v * size / cell)
    on = (np.mod(k + row, 2) == 0)
    grey = g0 + (g1 - g0) * v
    r0, r1, c0, c1 = M._window(rng, size, 0.5, 0.95)
    inside = np.zeros((size, size), bool)
    inside[r0:r1, c0:c1] = True
    keep = inside & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
    return np.where(on & keep, np.round(255 * grey), 0).astype(np.uint8)


def composite(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Four features, one a quadrant, each drawn from the test patterns at half the
    field: more edges of different kinds per print, and no period across the field (so
    registration cannot slip by one)."""
    half = size // 2
    m = np.zeros((size, size), np.uint8)
    kinds = rng.choice(len(_TILE_PATTERNS), size=4, replace=False)
    for q, k in enumerate(kinds):
        name = _TILE_PATTERNS[int(k)]
        gen = ramp_steps if name == "ramp_steps" else M.TEST_PATTERNS[name]
        tile = gen(rng, half)
        r, c = divmod(q, 2)
        m[r * half:(r + 1) * half, c * half:(c + 1) * half] = tile
    return m


def pattern(name: str):
    """The generator of a pool pattern: (rng, size) -> uint8 mask."""
    if name == "composite":
        return composite
    if name == "ramp_steps":
        return ramp_steps
    if name == "graded_grid":
        return graded_grid
    if name in M.TEST_PATTERNS:
        return M.TEST_PATTERNS[name]
    raise ValueError(f"unknown pool pattern {name!r}; known: {', '.join(POOL_PATTERNS)}")


def candidate_pool(count: int, seed: int = 0, size: int = 512, patterns=POOL_PATTERNS, fiducials: bool = False) -> dict:
    """``count`` candidate masks, id ``<pattern>_<index>`` -> uint8 mask; patterns in the
    shares of ``POOL_WEIGHTS`` (1 for the others), each mask from its own seeded stream.
    Masks that would print nothing at full dose (all below grey 60) are redrawn, before
    the registration marks are added (``fiducials``)."""
    w = np.array([POOL_WEIGHTS.get(p, 1.0) for p in patterns])
    n = np.floor(w / w.sum() * count).astype(int)
    n[np.argsort(-w)[: count - n.sum()]] += 1
    out = {}
    for j, (p, k) in enumerate(zip(patterns, n)):
        gen = pattern(p)
        for i in range(int(k)):
            rng = np.random.default_rng([seed, j, i])
            m = gen(rng, size)
            while m.max() < 60:
                m = gen(rng, size)
            out[f"{p}_{i:03d}"] = with_fiducials(m) if fiducials else m
    return out


# ------------------------------------------------------------------------- the prior
def full_params(base: Params | None = None) -> Params:
    """The model the design is for: ``base`` (default: Eq. 1 at its defaults) with every
    library effect added."""
    base = base if base is not None else default_params("eq1")
    return extend_params(base, effect_names())


def _unit(params: Params, names):
    lo = np.array([params.bounds[k][0] for k in names], dtype=np.float64)
    hi = np.array([params.bounds[k][1] for k in names], dtype=np.float64)
    return lo, hi - lo


def design_prior(params: Params, draws: int, seed: int = 0, fitted: Params | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(draws, K) parameter draws in bound units and the (K,) prior standard deviation
    in the same units, for the free parameters of ``params``.

    Without ``fitted`` the draws come from ``PRIOR``. With a calibration or a diagnosis
    (``fitted``), its parameters are drawn around its values with its bootstrap spread
    (``std``; a tenth of the bound range where it has none) and the effects it lacks from
    ``PRIOR``: the next prints are designed for this printer, and still for the effects
    it may have.
    """
    names = params.free
    lo, rng_ = _unit(params, names)
    g = np.random.default_rng([seed, 77])
    extras = (fitted.info.get("parameter_extras", {}) if fitted is not None else {})
    U = np.empty((draws, len(names)))
    sd = np.empty(len(names))
    for j, k in enumerate(names):
        blo, bhi = params.bounds[k]
        if fitted is not None and k in fitted.values:
            mean = float(fitted.values[k])
            s = float(extras.get(k, {}).get("std") or 0.1 * (bhi - blo))
            x = mean + s * g.standard_normal(draws)
            sd[j] = s
        else:
            kind, a, b = PRIOR.get(k, ("uniform", blo, bhi))
            if kind == "log":
                x = np.exp(g.uniform(math.log(a), math.log(b), draws))
                sd[j] = (b - a) / math.sqrt(12)
            elif kind == "uniform":
                x = g.uniform(a, b, draws)
                sd[j] = (b - a) / math.sqrt(12)
            else:
                x = a + b * g.standard_normal(draws)
                sd[j] = b
        U[:, j] = (np.clip(x, blo, bhi) - lo[j]) / rng_[j]
        sd[j] /= rng_[j]
    return U, sd


# ---------------------------------------------------------------------- information
def _margin_sets(arr: np.ndarray, params: Params, sets: list, per_draw: int, chunk: int, device, progress):
    """Cure margins of every mask in ``arr`` under every parameter set of ``sets`` (dicts
    of every model value; ``per_draw`` consecutive sets belong to one draw): yields (first
    mask, draw, margins (per_draw, b, h, w) float64, the first set's |grad margin| (b, h,
    w) per design pixel, the grid's step f in design pixels: each sample stands for f^2
    pixels). The margin is the absorbed dose's relative excess over the threshold,
    (D - T) / T: smooth at every kernel width, where the print jumps from 0 to 1 within a
    pixel. Its gradient comes from the dose's spectrum (exact where the grid resolves the
    dose; finite differences over two samples were 23 % low at an edge of sigma 1.5 px on
    the 2-px grid). One batched evaluation per block of masks, whose spectra
    are computed once (``FixedMasks``); on every ``DECIMATION``-th pixel where the size
    allows."""
    model = get_model(params.model)
    device = torch.device(device or "cpu")
    theta = model.theta({k: [d[k] for d in sets] for k in model.names}, device)
    support = 1.01 * max(model.support_px(d) for d in sets)  # margin: theta is float32
    S, B = len(sets) // per_draw, len(arr)
    for b0 in range(0, B, chunk):
        sim = FixedMasks(model, masks_to_tensor(arr[b0:b0 + chunk], device), support_px=support)
        if sim.full_shape[0] % DECIMATION == 0 and sim.full_shape[1] % DECIMATION == 0:
            sim = sim.decimated(DECIMATION)
        for s in range(S):  # one draw at a time keeps the temporaries small
            sub = {k: v[s * per_draw:(s + 1) * per_draw] for k, v in theta.items()}
            with torch.no_grad():
                T = sub["T"].double().reshape(-1, 1, 1, 1)
                # the first set's dose with its gradient, the others' without (the Hessian's FFTs once)
                D0, gy, gx = sim.dose({k: v[:1] for k, v in sub.items()}, gradient=True)
                D = torch.cat([D0, sim.dose({k: v[1:] for k, v in sub.items()})]) if per_draw > 1 else D0
                g = torch.sqrt(gx[0].double() ** 2 + gy[0].double() ** 2) / T[0]
                yield b0, s, D.double() / T - 1.0, g, sim.f
        if progress:
            progress(min(b0 + chunk, B), B)


def _noise(noise: str | None) -> str:
    noise = noise or NOISE
    if noise not in ("edge", "pixel"):
        raise ValueError(f"unknown noise model {noise!r}: edge or pixel")
    return noise


def response(m: torch.Tensor, noise: str | None = None) -> torch.Tensor:
    """What the information differentiates, from margins ``m``: the margin itself (edge
    model) or the smooth print sigmoid(m / TEMPERATURE) (pixel model)."""
    return m if _noise(noise) == "edge" else torch.sigmoid(m / TEMPERATURE)


def pixel_weights(m: torch.Tensor, g: torch.Tensor, f: int, noise: str | None = None) -> torch.Tensor:
    """(b, n) weight of each sample's squared derivative of ``response`` in the
    information, for the margins ``m`` (b, h, w) and their gradients' size ``g`` (b, h,
    w; per design pixel) at every ``f``-th design pixel (see ``NOISE``).

    Edge model: with g = |grad m| per design pixel, a change dm of the margin moves the
    edge by dm / g, and the edge's place has the spread sigma_m / g with sigma_m^2 =
    DOSE_NOISE^2 + EDGE_SD_PX^2 g^2. Per unit length of edge and one measurement per
    CORRELATION_PX of it, that is dm^2 / (sigma_m^2 CORRELATION_PX). The length comes from
    the co-area formula (the edge's length element is phi(m) |grad m| dA for phi of unit
    integral in m): the weight is phi(m) g / (CORRELATION_PX sigma_m^2). phi is a Gaussian
    of m as wide as the edge's own spread (the information is where the edge may fall),
    widened by half a sample's span of m, so that the grid resolves it: the sum over the
    samples is the integral within 0.5 % wherever the edge falls between them."""
    b = m.shape[0]
    if _noise(noise) == "pixel":
        return torch.full((b, m[0].numel()), 1.0 / (PIXEL_VARIANCE * CORRELATION_PX ** 2), dtype=m.dtype, device=m.device)
    var_m = DOSE_NOISE ** 2 + (EDGE_SD_PX * g) ** 2
    width = var_m + (0.5 * f * g) ** 2
    phi = torch.exp(-0.5 * m ** 2 / width) / torch.sqrt(2 * math.pi * width)
    return (phi * g / (CORRELATION_PX * var_m)).reshape(b, -1)


def _gram(J: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """(b, K, K) sum over pixels of w J J^T for J (K, b, n) and weights w (b, n): one
    batched matrix product (a three-operand einsum took 8 times as long)."""
    Jw = (J * w.sqrt()[None]).transpose(0, 1)  # (b, K, n)
    return Jw @ Jw.transpose(1, 2)


def print_gram(J: torch.Tensor, m0: torch.Tensor, g0: torch.Tensor, f: int, noise: str | None = None) -> torch.Tensor:
    """(b, K, K) information of each print about the K columns J (K, b, n) (changes of
    ``response`` on the print's samples), at the margins ``m0`` (b, h, w) whose gradients
    have the size ``g0``, on the grid of every ``f``-th design pixel.

    Edge model: each print's overall dose is a nuisance. It is off by PRINT_DOSE_SD from
    print to print (lamp, ink batch), which moves all of that print's edges at once, so a
    column that a dose change mimics teaches less: the dose column (dm / d log dose =
    m + 1) is profiled out of the print's Gram under a prior of PRINT_DOSE_SD (a Schur
    complement of one column)."""
    w = pixel_weights(m0, g0, f, noise)
    if _noise(noise) == "pixel":
        return _gram(J, w) * f ** 2
    A = _gram(torch.cat([J, (m0 + 1.0).flatten(1)[None]]), w) * f ** 2
    c = A[:, :-1, -1]
    d = A[:, -1, -1] + 1.0 / PRINT_DOSE_SD ** 2
    return A[:, :-1, :-1] - c[:, :, None] * c[:, None, :] / d[:, None, None]


def _differences(p: torch.Tensor, steps: np.ndarray) -> torch.Tensor:
    """(K, b, n) forward differences of ``p`` (K + 1 + ..., b, h, w: the values at a draw,
    then at each of its K steps, ``_jacobian_sets``) over the (K,) ``steps``."""
    K = len(steps)
    return ((p[1:K + 1] - p[:1]) / torch.as_tensor(steps, dtype=p.dtype, device=p.device)[:, None, None, None]).flatten(2)


def _jacobian_sets(params: Params, U: np.ndarray, extra=None) -> tuple[list, np.ndarray]:
    """Per draw u of ``U`` (bound units of ``params.free``): the values at u, then at u
    moved by a forward-difference step in each parameter (backward at an upper bound),
    then ``extra(u_values)``'s sets. Returns the sets and the (S, K) steps."""
    names = params.free
    lo, rng_ = _unit(params, names)
    steps = np.where(U + STEP <= 1.0, STEP, -STEP)

    def at(u):
        out = dict(params.values)
        out.update({k: float(lo[j] + u[j] * rng_[j]) for j, k in enumerate(names)})
        return out

    sets = []
    for u, st in zip(U, steps):
        base = at(u)
        sets.append(base)
        sets += [at(u + st[j] * (np.arange(len(names)) == j)) for j in range(len(names))]
        if extra is not None:
            sets += extra(base)
    return sets, steps


def information(masks: dict | np.ndarray, params: Params, U: np.ndarray, chunk: int = 8, device=None,
                progress=None) -> np.ndarray:
    """(S, B, K, K) Fisher information of each mask's print about the free parameters
    (bound units) at each of the S draws ``U``: F = sum over the print's pixels of w J J^T,
    w the pixel's weight under the noise model (``pixel_weights``; see the module doc).

    J by forward differences (backward at an upper bound): all K + 1 parameter sets of
    all draws in one batched evaluation per block of masks (``_margin_sets``)."""
    arr = np.stack(list(masks.values())) if isinstance(masks, dict) else np.asarray(masks)
    names = params.free
    K, S, B = len(names), len(U), len(arr)
    sets, steps = _jacobian_sets(params, U)
    out = np.zeros((S, B, K, K))
    for b0, s, m, g, f in _margin_sets(arr, params, sets, K + 1, chunk, device, progress):
        F = print_gram(_differences(response(m), steps[s]), m[0], g, f)
        out[s, b0:b0 + F.shape[0]] = F.cpu().numpy()
    return out


# ------------------------------------------------------------ telling effects apart
# The sizes of the library's effects that a design for telling them apart aims at: from
# about the smallest the diagnosis should name to moderate ones (a design that separates
# small effects separates large ones too; a draw near an effect's neutral value teaches
# nothing about it). Per parameter: ("pm", a, b) a magnitude uniform in [a, b] with a random
# sign; ("log_inv", a, b) log-uniform in [a, b], inverted with probability 1/2; or a
# ``PRIOR`` kind.
EFFECT_SIZES = {
    "tail_fraction": ("uniform", 0.08, 0.3), "tail_length_px": ("log", 5.0, 30.0),
    "aniso_ratio": ("log_inv", 1.12, 1.4), "aniso_angle_deg": ("uniform", -45.0, 45.0),
    "dose_gamma": ("log_inv", 1.12, 1.35),
    "ill_xy": ("normal", 0.0, 0.06), "ill_xr2": ("normal", 0.0, 0.06), "ill_yr2": ("normal", 0.0, 0.06),
    "ill_r4": ("pm", 0.08, 0.2),
    "edge_offset_px": ("pm", 0.5, 2.0),
}
RIVAL_PRECISION = 1.0  # prior precision of the share of a rival effect's drawn size that its fit may use


def _draw(kind: str, a: float, b: float, g: np.random.Generator, n: int) -> np.ndarray:
    if kind == "log":
        return np.exp(g.uniform(math.log(a), math.log(b), n))
    if kind == "uniform":
        return g.uniform(a, b, n)
    if kind == "normal":
        return a + b * g.standard_normal(n)
    if kind == "pm":
        return g.uniform(a, b, n) * g.choice([-1.0, 1.0], n)
    if kind == "log_inv":
        return np.exp(g.uniform(math.log(a), math.log(b), n) * g.choice([-1.0, 1.0], n))
    raise ValueError(f"unknown kind of draw {kind!r}")


@dataclass
class Rivals:
    """The columns of a discrimination Gram matrix (``discrimination_gram``): the free
    parameters ``names`` (bound units, at the null point: the candidate effects neutral),
    then one column per candidate effect (its change at a drawn size)."""

    names: list
    effects: list  # the candidate effects, in column order after the parameters
    own: dict  # effect -> indices of its parameters among ``names``
    base: list  # indices of the parameters that belong to no candidate effect
    prior_precision: np.ndarray  # (K,) of the parameters, bound units

    def column(self, effect: str) -> int:
        return len(self.names) + self.effects.index(effect)

    def pairs(self) -> list:
        """(effect, rival, columns the rival's fit may use): the rival is the model
        without the candidate effects (None) or with one other effect (its parameters and
        the secant to its drawn size)."""
        out = []
        for e in self.effects:
            out.append((e, None, list(self.base)))
            for r in self.effects:
                if r != e:
                    out.append((e, r, list(self.base) + list(self.own[r]) + [self.column(r)]))
        return out


def added_params(params: Params, effect: str) -> list:
    """The parameter specs that ``effect`` adds to ``params``' base model (an effect may
    replace a base term and carry its parameters: anisotropy's kernel has sigma_px)."""
    from .model import EFFECTS, split_model_name

    base_names = set(get_model(split_model_name(params.model)[0]).specs)
    return [p for p in EFFECTS[effect].params if p.name not in base_names]


def rivals_of(params: Params, sd: np.ndarray) -> Rivals:
    """The candidate effects of a design for ``params``: the library's effects whose
    parameters are all at their neutral values (those a diagnosis of it may still add)."""
    from .model import EFFECTS

    names = params.free
    effects, own = [], {}
    for e in EFFECTS:
        added = [p for p in added_params(params, e) if p.name in names]
        idx = [names.index(p.name) for p in added]
        if idx and all(abs(float(params.values[p.name]) - float(p.default)) < 1e-12 for p in added):
            effects.append(e)
            own[e] = idx
    used = {j for idx in own.values() for j in idx}
    return Rivals(list(names), effects, own, [j for j in range(len(names)) if j not in used], 1.0 / np.asarray(sd) ** 2)


def null_point(params: Params, U: np.ndarray, rivals: Rivals) -> np.ndarray:
    """``U`` (bound units) with the candidate effects' parameters at their neutral values."""
    lo, rng_ = _unit(params, rivals.names)
    U0 = U.copy()
    for e in rivals.effects:
        for j in rivals.own[e]:
            U0[:, j] = (float(params.values[rivals.names[j]]) - lo[j]) / rng_[j]
    return U0


def discrimination_gram(masks: dict | np.ndarray, params: Params, U: np.ndarray, rivals: Rivals, seed: int = 0,
                        chunk: int = 8, device=None, progress=None) -> np.ndarray:
    """(S, B, Q, Q) Gram matrix of each mask's columns at each of the S draws (in the
    information's units: ``print_gram``, on the margin under the edge model): the
    derivatives with respect to the K free parameters at the draw's null point (``U``
    with the candidate effects neutral), then each candidate effect's change at a size
    drawn from ``EFFECT_SIZES``. Q = K + candidate effects. Under the edge model an
    effect's column is its change of the margin, near linear in its size (an edge offset
    of e moves the margin by exactly e |grad m|), so a rival's derivatives can fit what
    they can reproduce; a change of the thresholded print is not linear, and part of an
    edge shift that a change of T reproduces was left as lack of fit. Sums over masks: a
    design's Gram is the sum of its masks'."""
    arr = np.stack(list(masks.values())) if isinstance(masks, dict) else np.asarray(masks)
    names = rivals.names
    K, S, B, E = len(names), len(U), len(arr), len(rivals.effects)
    g = np.random.default_rng([seed, 78])

    def sized(null: dict) -> list:  # each candidate effect at a drawn size
        out = []
        for e in rivals.effects:
            v = dict(null)
            for j in rivals.own[e]:
                k = names[j]
                kind, a, b = EFFECT_SIZES.get(k, PRIOR.get(k, ("uniform",) + tuple(params.bounds[k])))
                v[k] = float(np.clip(_draw(kind, a, b, g, 1)[0], *params.bounds[k]))
            out.append(v)
        return out

    sets, steps = _jacobian_sets(params, null_point(params, U, rivals), sized)
    out = np.zeros((S, B, K + E, K + E))
    for b0, s, m, g, f in _margin_sets(arr, params, sets, K + 1 + E, chunk, device, progress):
        p = response(m)
        C = torch.cat([_differences(p, steps[s]), (p[K + 1:] - p[:1]).flatten(2)])  # (Q, b, n)
        G = print_gram(C, m[0], g, f)
        out[s, b0:b0 + G.shape[0]] = G.cpu().numpy()
    return out


def separation(G: np.ndarray, rivals: Rivals) -> dict:
    """{(effect, rival): (..., S) lack of fit}: what remains of the effect's change (at
    its drawn size) after the rival's best linear fit, in units of the print noise's
    variance: the non-centrality of a test of the rival against the effect (near 1 or
    below, the rival absorbs the effect within the noise).
    T = d'd - b' (G_RR + P_R)^-1 b, with P_R the rival's prior precision (its parameters',
    ``RIVAL_PRECISION`` for the share of its own size): Atkinson & Fedorov's (1975)
    T-optimality criterion, linearised. ``G``: (..., S, Q, Q) from ``discrimination_gram``."""
    out = {}
    for e, r, cols in rivals.pairs():
        q = rivals.column(e)
        out[(e, r)] = G[..., q, q] - np.einsum("...i,...i->...", G[..., cols, q], _rival_fit(G, rivals, cols, q))
    return out


def _rival_fit(G: np.ndarray, rivals: Rivals, cols: list, q: int) -> np.ndarray:
    """(..., len(cols)) the rival's linearised fit of the effect column ``q`` from its
    columns ``cols``, penalised by their prior precision: (G_RR + P_R)^-1 G_Rq."""
    prec = np.array([rivals.prior_precision[c] if c < len(rivals.names) else RIVAL_PRECISION for c in cols])
    A = G[..., cols, :][..., :, cols] + np.diag(prec)
    return np.linalg.solve(A, G[..., cols, q][..., None])[..., 0]


def discrimination(G: np.ndarray, rivals: Rivals) -> np.ndarray:
    """Mean over draws of sum over (effect, rival) pairs of log(1 + T): every effect is to
    stand out from the model without it and from every other effect in its place, and
    the log spends prints where a pair is least apart (``separation``). (..., S, Q, Q) -> (...)."""
    return sum(np.log1p(np.clip(T, 0.0, None)) for T in separation(G, rivals).values()).mean(axis=-1)


PAIRED_NOISE = 4.0  # ``paired``: the variance of a print's gain from the noise, per unit of its lack of fit


def per_print_lack_of_fit(G_prints: np.ndarray, rivals: Rivals) -> dict:
    """{effect: (..., S, n) lack of fit of each print}: what the model without the
    candidate effects (rival None) leaves of the effect's change in each of n prints, its
    parameters fitted to all of them (``separation``'s T split by print: the prints' T
    sum to the design's less the rival prior's share, beta' P beta). ``G_prints``:
    (..., S, n, Q, Q) per print."""
    G_sum = G_prints.sum(axis=-3)
    cols = list(rivals.base)
    Gp_rr = G_prints[..., cols, :][..., :, cols]
    out = {}
    for e in rivals.effects:
        q = rivals.column(e)
        beta = _rival_fit(G_sum, rivals, cols, q)  # (..., S, R)
        out[e] = (G_prints[..., q, q] - 2.0 * np.einsum("...sr,...snr->...sn", beta, G_prints[..., cols, q])
                  + np.einsum("...sr,...snrk,...sk->...sn", beta, Gp_rr, beta))
    return out


def paired(G_prints: np.ndarray, rivals: Rivals) -> np.ndarray:
    """Mean over draws of sum over the candidate effects of log(1 + t), t the paired
    t-statistic that the diagnosis's acceptance computes over prints, as the design
    predicts it: with T_i the lack of fit of print i (``per_print_lack_of_fit``), its
    gain from the effect is T_i with a noise of variance ``PAIRED_NOISE`` T_i, so
    t = sqrt(n) mean(T) / sqrt(var(T) + PAIRED_NOISE mean(T)). A design whose evidence for
    an effect sits in one or two prints has a large total lack of fit and a small t: the
    test over prints sees the other prints gain nothing. (..., S, n, Q, Q) -> (...)."""
    return _paired_value(paired_t(G_prints, rivals))


def _paired_value(t: dict) -> np.ndarray:
    """``paired`` from its effects' t (``paired_t``)."""
    return sum(np.log1p(v) for v in t.values()).mean(axis=-1)


def paired_t(G_prints: np.ndarray, rivals: Rivals) -> dict:
    """{effect: (..., S) the paired t-statistic over prints that ``paired`` predicts}."""
    n = G_prints.shape[-3]
    out = {}
    for e, T in per_print_lack_of_fit(G_prints, rivals).items():
        T = np.clip(T, 0.0, None)
        m = T.mean(axis=-1)
        out[e] = np.sqrt(n) * m / np.sqrt(T.var(axis=-1) + PAIRED_NOISE * m + 1e-12)
    return out


def _logdet(A: np.ndarray) -> np.ndarray:
    sign, ld = np.linalg.slogdet(A)
    return np.where(sign > 0, ld, -np.inf)


def criterion_d(A: np.ndarray, focus: list[int] | None = None, focus_weight: float = 1.0) -> np.ndarray:
    """Mean over draws of log det A (D-optimality), plus ``focus_weight`` times log det of
    the information on the ``focus`` parameters after the others are accounted for
    (Ds-optimality: the Schur complement). ``A``: (..., S, K, K) -> (...)."""
    val = _logdet(A).mean(axis=-1)
    if focus:
        rest = [j for j in range(A.shape[-1]) if j not in focus]
        Aff = A[..., focus, :][..., :, focus]
        if rest:
            Afr = A[..., focus, :][..., :, rest]
            Arr = A[..., rest, :][..., :, rest]
            Aff = Aff - Afr @ np.linalg.solve(Arr, np.swapaxes(Afr, -1, -2))
        val = val + focus_weight * _logdet(Aff).mean(axis=-1)
    return val


def posterior_sd(A: np.ndarray) -> np.ndarray:
    """(K,) predicted standard deviation of each parameter (bound units), the mean over
    draws of sqrt(diag(A^-1))."""
    return np.sqrt(np.clip(np.diagonal(np.linalg.inv(A), axis1=-2, axis2=-1), 0, None)).mean(axis=0)


@dataclass
class Design:
    ids: list  # chosen candidate ids, in the order chosen
    gains: list  # criterion gain of each
    criterion: float
    sd: np.ndarray  # (K,) predicted parameter sd (bound units) with the chosen masks
    names: list  # the parameters
    prior_sd: np.ndarray
    separation: dict = field(default_factory=dict)  # (effect, rival) -> mean T with the chosen masks (``separation``)
    paired_t: dict = field(default_factory=dict)  # paired only: effect -> predicted paired t over the prints


def greedy(F: np.ndarray, ids: list, count: int, prior_precision: np.ndarray, focus=None, focus_weight: float = 1.0,
           start: np.ndarray | None = None, G: np.ndarray | None = None, rivals: Rivals | None = None,
           G_start: np.ndarray | None = None, kind: str = "discrimination") -> Design:
    """Choose ``count`` masks greedily by the criterion. ``F``: (S, B, K, K) information
    of the candidates; ``prior_precision``: (K, K) or (S, K, K); ``start``: (S, K, K)
    information of prints already made. With ``G`` ((S, B, Q, Q), ``discrimination_gram``)
    and ``rivals`` the criterion adds ``discrimination`` (``kind`` "discrimination";
    ``G_start``: (S, Q, Q), the prints already made) or ``paired`` (``kind`` "paired";
    ``G_start``: (S, n, Q, Q), each print already made)."""
    S, B, K, _ = F.shape
    A = np.broadcast_to(prior_precision, (S, K, K)).copy()
    if start is not None:
        A = A + start
    extra = G is not None and rivals is not None and bool(rivals.effects)
    by_print = extra and kind == "paired"
    if by_print:  # each chosen print's Gram: the paired test is over prints
        Gacc = np.zeros((S, 0) + G.shape[2:]) if G_start is None else np.asarray(G_start, float)
    elif extra:
        Gacc = np.zeros((S,) + G.shape[2:]) if G_start is None else G_start.copy()

    def value(A_, G_):
        if not extra:
            return criterion_d(A_, focus, focus_weight)
        if by_print:
            return criterion_d(A_, focus, focus_weight) + (paired(G_, rivals) if G_.shape[-3] else 0.0)
        return criterion_d(A_, focus, focus_weight) + discrimination(G_, rivals)

    chosen, gains = [], []
    current = float(value(A, Gacc if extra else None))
    free = np.ones(B, bool)
    for _ in range(min(count, B)):
        trial = A[None] + np.swapaxes(F, 0, 1)  # (B, S, K, K)
        if by_print:  # (B, S, n + 1, Q, Q)
            gtrial = np.concatenate([np.broadcast_to(Gacc[None], (B,) + Gacc.shape),
                                     np.swapaxes(G, 0, 1)[:, :, None]], axis=2)
        else:
            gtrial = Gacc[None] + np.swapaxes(G, 0, 1) if extra else None
        val = value(trial, gtrial)
        val[~free] = -np.inf
        b = int(np.argmax(val))
        gains.append(float(val[b] - current))
        current = float(val[b])
        A = trial[b]
        if extra:
            Gacc = np.array(gtrial[b])
        free[b] = False
        chosen.append(ids[b])
    d = Design(chosen, gains, current, posterior_sd(A), [], np.zeros(0))
    if extra:
        d.separation = {k: float(v.mean()) for k, v in separation(Gacc.sum(axis=1) if by_print else Gacc,
                                                                     rivals).items()}
    if by_print:
        d.paired_t = {k: float(v.mean()) for k, v in paired_t(Gacc, rivals).items()}
    return d


# ------------------------------------------------------------------------ the command
def undecided_effects(diagnosis_dir) -> list[str]:
    """Effects the diagnosis tried in its last round and could not decide on: not
    accepted, but the upper end of the held-out gain's interval is positive."""
    from .io import read_tsv

    path = Path(diagnosis_dir) / "ranking.tsv"
    if not path.is_file():
        return []
    rows = [r for r in read_tsv(path) if r["candidate"] != "(control)"]
    if not rows:
        return []
    last = max(int(r["round"]) for r in rows)
    return [r["candidate"] for r in rows if int(r["round"]) == last and str(r["accepted"]) != "True"
            and float(r["ci_hi"]) > 0]


def design_masks(count: int, *, model=None, prints=None, pool: int = TRIAL_MASKS.default.pool,
                 draws: int = TRIAL_MASKS.default.draws, seed: int = TRIAL_MASKS.default.seed,
                 size: int = TRIAL_MASKS.default.size, fiducials: bool = TRIAL_MASKS.default.fiducials,
                 criterion: str = TRIAL_MASKS.default.criterion, focus_weight: float = 1.0, compare: bool = True,
                 progress: bool = True, device=None) -> dict:
    """Choose ``count`` trial masks from a pool of ``pool`` candidates (see the module doc).

    ``model``: a calibration's params.yaml or a diagnosis folder (sequential design), or
    None (before any print). ``fiducials``: the registration marks on every candidate
    (``with_fiducials``), before their information is computed. ``prints``: registration folders of prints already made (their
    masks' information joins the prior). Returns a dict: masks (id -> uint8), design
    (Design), table (rows per chosen mask), sd (rows per parameter: prior, designed,
    random paper masks of the same count), focus, seconds.
    """
    TRIAL_MASKS.make(count=count, pool=pool, draws=draws, seed=seed, size=size, criterion=criterion)
    t0 = time.perf_counter()
    fitted, focus_effects = None, []
    if model is not None:
        fitted = load_params(model)
        if Path(model).is_dir():
            focus_effects = undecided_effects(model)
    params = full_params(fitted)  # the fit's values and bounds, the effects it lacks at their neutral values
    names = params.free
    U, sd0 = design_prior(params, draws, seed, fitted)
    prior_precision = np.diag(1.0 / sd0 ** 2)
    focus = None
    if focus_effects:
        fp = {p.name for e in focus_effects for p in added_params(params, e)}
        focus = [j for j, k in enumerate(names) if k in fp] or None

    cands = candidate_pool(pool, seed, size, fiducials=fiducials)
    bar = _bar(progress, len(cands), "information of the candidates")
    F = information(cands, params, U, device=device, progress=bar)
    start = None
    if prints:
        from .prints import load_prints

        data = load_prints(prints)
        start = information(data.masks, params, U, device=device).sum(axis=1)
    rivals = rivals_of(params, sd0) if criterion in ("discrimination", "paired") else None
    G = G_start = None
    if rivals is not None and rivals.effects:  # none left: D-optimality alone
        G = discrimination_gram(cands, params, U, rivals, seed, device=device)
        if prints:
            G_start = discrimination_gram(data.masks, params, U, rivals, seed, device=device)
            if criterion != "paired":
                G_start = G_start.sum(axis=1)
    ids = list(cands)
    d = greedy(F, ids, count, prior_precision, focus, focus_weight, start, G, rivals, G_start, kind=criterion)
    d.names, d.prior_sd = names, sd0
    table = [dict(id=f"design_{i:03d}", candidate=c, pattern=c.rsplit("_", 1)[0], gain=g)
             for i, (c, g) in enumerate(zip(d.ids, d.gains))]
    out_masks = {row["id"]: cands[row["candidate"]] for row in table}
    sd_rows = [dict(parameter=k, prior_sd=float(sd0[j] * _unit(params, names)[1][j]),
                    designed_sd=float(d.sd[j] * _unit(params, names)[1][j])) for j, k in enumerate(names)]
    result = dict(masks=out_masks, design=d, table=table, sd=sd_rows, focus=focus_effects, model=params.model,
                  draws=U, criterion=d.criterion, criterion_kind=criterion,
                  separation=[dict(effect=e, rival=r or "(none)", designed=t) for (e, r), t in d.separation.items()],
                  paired=[dict(effect=e, designed_t=t) for e, t in d.paired_t.items()])
    if compare:  # the paper's random masks, same count, same draws and prior
        paper = M.trial_masks(count, seed=seed, size=size)
        Fp = information(paper, params, U, device=device)
        A = np.broadcast_to(prior_precision, (draws, len(names), len(names))).copy() + Fp.sum(axis=1)
        if start is not None:
            A = A + start
        sdp = posterior_sd(A)
        result["criterion_paper"] = float(criterion_d(A, focus, focus_weight))
        if rivals is not None and rivals.effects:
            Gpp = discrimination_gram(paper, params, U, rivals, seed, device=device)
            if criterion == "paired":
                if G_start is not None:
                    Gpp = np.concatenate([G_start, Gpp], axis=1)
                Gp = Gpp.sum(axis=1)
                tp = paired_t(Gpp, rivals)  # once: ``paired`` of the same prints, from its t
                result["criterion_paper"] += float(_paired_value(tp))
                for row in result["paired"]:
                    row["paper_t"] = float(tp[row["effect"]].mean())
            else:
                Gp = Gpp.sum(axis=1) + (G_start if G_start is not None else 0.0)
                result["criterion_paper"] += float(discrimination(Gp, rivals))
            Tp = separation(Gp, rivals)
            for row in result["separation"]:
                row["paper"] = float(Tp[(row["effect"], None if row["rival"] == "(none)" else row["rival"])].mean())
        for j, row in enumerate(sd_rows):
            row["paper_sd"] = float(sdp[j] * _unit(params, names)[1][j])
    result["seconds"] = time.perf_counter() - t0
    return result


def _bar(progress: bool, total: int, desc: str):
    if not progress:
        return None
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit="mask")

    def update(done, _total):
        bar.n = done
        bar.refresh()
        if done >= _total:
            bar.close()

    return update


def write_design(out_dir, result: dict, inputs=()) -> list[Path]:
    """OUT/<id>.png, the masks (a mask folder as ``masks trial`` writes, ready to print), and
    OUT/design/: design.tsv (the chosen candidates and their gains), parameters.tsv
    (predicted parameter sd: prior, designed, random paper masks), separation.tsv (with
    the discrimination or paired criterion: every effect's lack of fit under every rival),
    paired.tsv (paired: every effect's predicted paired t over the prints),
    design.yaml (criterion, its kind, noise model, model, focus) and design.png (the
    masks, the sd bars and the separations)."""
    from .io import output_dir, write_png, write_tsv, write_yaml

    with output_dir(out_dir, command="masks design", inputs=list(inputs)) as tmp:
        for mid, m in result["masks"].items():
            write_png(tmp / f"{mid}.png", m)
        info = tmp / "design"
        info.mkdir()
        write_tsv(info / "design.tsv", result["table"])
        write_tsv(info / "parameters.tsv", result["sd"])
        if result.get("separation"):
            write_tsv(info / "separation.tsv", result["separation"])
        if result.get("paired"):
            write_tsv(info / "paired.tsv", result["paired"])
        kind = result.get("criterion_kind", "d")
        sep = bool(result.get("separation"))
        write_yaml(info / "design.yaml", dict(
            criterion="pseudo-Bayesian D-optimality on the print's sensitivity to the parameters (unscatter.design)"
                      + ("; plus every effect's evidence spread over the prints (the diagnosis's paired test, "
                         "paired.tsv)" if sep and kind == "paired" else
                         "; plus telling the library's effects apart (linearised T-optimality, separation.tsv)"
                         if sep else ""),
            criterion_kind=result.get("criterion_kind", "d"), noise=NOISE,
            model=result["model"], draws=int(len(result["draws"])), focus_effects=list(result["focus"]),
            criterion_designed=float(result["criterion"]), criterion_paper=result.get("criterion_paper"),
            seconds=float(result["seconds"])))
        _figure(info / "design.png", result)
    return [Path(out_dir) / f"{mid}.png" for mid in result["masks"]]


def _figure(path: Path, result: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ms = list(result["masks"].items())
    n = len(ms)
    cols = min(8, n)
    rows = -(-n // cols)
    sep = result.get("separation") or []
    fig = plt.figure(figsize=(2 * cols, 2 * rows + 3.2 + (3.2 if sep else 0)))
    gs = fig.add_gridspec(rows + 1 + bool(sep), cols, height_ratios=[1] * rows + [1.6] + ([1.6] if sep else []))
    for i, (mid, m) in enumerate(ms):
        ax = fig.add_subplot(gs[i // cols, i % cols])
        ax.imshow(m, cmap="gray", vmin=0, vmax=255)
        ax.set_title(result["table"][i]["pattern"], fontsize=7)
        ax.axis("off")
    ax = fig.add_subplot(gs[rows, :])
    sd = result["sd"]
    x = np.arange(len(sd))
    rel = lambda key: [r[key] / r["prior_sd"] if r["prior_sd"] else np.nan for r in sd]  # noqa: E731
    ax.bar(x - 0.2, rel("designed_sd"), 0.4, label="designed")
    if "paper_sd" in sd[0]:
        ax.bar(x + 0.2, rel("paper_sd"), 0.4, label="paper (random)")
    ax.set_xticks(x, [r["parameter"] for r in sd], rotation=60, fontsize=7)
    ax.set_yscale("log")
    ax.set_ylabel("predicted sd / prior sd")
    ax.legend(fontsize=7)
    if sep:  # how far each effect stands out from each rival (separation.tsv)
        ax = fig.add_subplot(gs[rows + 1, :])
        x = np.arange(len(sep))
        ax.bar(x - 0.2, [r["designed"] for r in sep], 0.4, label="designed")
        if "paper" in sep[0]:
            ax.bar(x + 0.2, [r["paper"] for r in sep], 0.4, label="paper (random)")
        ax.set_xticks(x, [f"{r['effect']} vs {r['rival']}" for r in sep], rotation=75, fontsize=6)
        ax.set_yscale("log")
        ax.set_ylabel("lack of fit T (noise variances)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
