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
- The information of one print at parameters u is F = J^T J / v with J the derivative of
  the print (smooth threshold, ``TEMPERATURE``) with respect to u at every pixel, and v
  the variance of a measured print pixel (``PIXEL_VARIANCE``, a binary pixel's largest)
  times the area over which errors are correlated (``CORRELATION_PX``, a cell's size).
  Only pixels near an edge that moves with a parameter contribute: near-threshold
  features, fine gratings and corners carry the information, solid interiors none.
- The parameters are unknown before the prints, so the criterion is the mean of
  log det(prior precision + sum of F) over draws from a prior (``design_prior``): a
  design good for one printer only is not chosen. With a calibration (``--model``) the
  draws and the prior precision come from its fit and bootstrap spread (sequential
  design: the next batch goes where the fit is least sure); the prints already made add
  their information to the prior, and effects the diagnosis could not yet decide on get
  extra weight (Ds-optimality on their parameters).
- Masks are added greedily (each step the candidate that raises the criterion most),
  the standard approximation to exact D-optimal design; every step's gain is reported.

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
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from . import masks as M
from .masks import with_fiducials
from .settings import TRIAL_MASKS
from .model import FixedMasks, Params, default_params, effect_names, extend_params, get_model, load_params, masks_to_tensor

log = logging.getLogger(__name__)

TEMPERATURE = 0.1  # smooth threshold width as a fraction of T (the calibration's coarse temperature)
PIXEL_VARIANCE = 0.25  # variance of a binary print pixel at an uncertain edge (its largest)
# Print errors are not independent from pixel to pixel: cells (10 to 15 um, 3 to 5 DMD
# pixels) move an edge over a stretch. One independent error per CORRELATION_PX^2 pixels.
CORRELATION_PX = 4
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
def information(masks: dict | np.ndarray, params: Params, U: np.ndarray, chunk: int = 8, device=None,
                progress=None) -> np.ndarray:
    """(S, B, K, K) Fisher information of each mask's print about the free parameters
    (bound units) at each of the S draws ``U``: F = J^T J / (PIXEL_VARIANCE *
    CORRELATION_PX^2) over the print's pixels (see the module doc).

    J by forward differences (backward at an upper bound): all K + 1 parameter sets of
    all draws in one batched evaluation per block of masks, whose spectra are computed
    once (``FixedMasks``)."""
    arr = np.stack(list(masks.values())) if isinstance(masks, dict) else np.asarray(masks)
    names = params.free
    model = get_model(params.model)
    lo, rng_ = _unit(params, names)
    K, S, B = len(names), len(U), len(arr)
    device = torch.device(device or "cpu")
    sets, steps = [], np.empty((S, K))
    for s in range(S):
        base = dict(params.values)
        base.update({k: float(lo[j] + U[s, j] * rng_[j]) for j, k in enumerate(names)})
        sets.append(base)
        for j, k in enumerate(names):
            u = U[s, j] + STEP if U[s, j] + STEP <= 1.0 else U[s, j] - STEP
            steps[s, j] = u - U[s, j]
            sets.append({**base, k: float(lo[j] + u * rng_[j])})
    theta = model.theta({k: [d[k] for d in sets] for k in model.names}, device)
    support = 1.01 * max(model.support_px(d) for d in sets)  # margin: theta is float32
    step = torch.as_tensor(steps, dtype=torch.float64, device=device)
    out = np.zeros((S, B, K, K))
    for b0 in range(0, B, chunk):
        sim = FixedMasks(model, masks_to_tensor(arr[b0:b0 + chunk], device), support_px=support)
        if sim.full_shape[0] % DECIMATION == 0 and sim.full_shape[1] % DECIMATION == 0:
            sim = sim.decimated(DECIMATION)
        for s in range(S):  # one draw at a time keeps the temporaries small
            sub = {k: v[s * (K + 1):(s + 1) * (K + 1)] for k, v in theta.items()}
            with torch.no_grad():
                p = sim.prints(sub, TEMPERATURE).double()  # (K + 1, b, h, w)
            J = ((p[1:] - p[:1]) / step[s][:, None, None, None]).flatten(2)  # (K, b, n)
            F = torch.einsum("kbn,lbn->bkl", J, J) * (sim.f ** 2) / (PIXEL_VARIANCE * CORRELATION_PX ** 2)
            out[s, b0:b0 + F.shape[0]] = F.cpu().numpy()
        if progress:
            progress(min(b0 + chunk, B), B)
    return out


def _logdet(A: np.ndarray) -> np.ndarray:
    sign, ld = np.linalg.slogdet(A)
    return np.where(sign > 0, ld, -np.inf)


def criterion(A: np.ndarray, focus: list[int] | None = None, focus_weight: float = 1.0) -> np.ndarray:
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


def greedy(F: np.ndarray, ids: list, count: int, prior_precision: np.ndarray, focus=None, focus_weight: float = 1.0,
           start: np.ndarray | None = None) -> Design:
    """Choose ``count`` masks greedily by the criterion. ``F``: (S, B, K, K) information
    of the candidates; ``prior_precision``: (K, K) or (S, K, K); ``start``: (S, K, K)
    information of prints already made."""
    S, B, K, _ = F.shape
    A = np.broadcast_to(prior_precision, (S, K, K)).copy()
    if start is not None:
        A = A + start
    chosen, gains = [], []
    current = float(criterion(A, focus, focus_weight))
    free = np.ones(B, bool)
    for _ in range(min(count, B)):
        trial = A[None] + np.swapaxes(F, 0, 1)  # (B, S, K, K)
        val = criterion(trial, focus, focus_weight)
        val[~free] = -np.inf
        b = int(np.argmax(val))
        gains.append(float(val[b] - current))
        current = float(val[b])
        A = trial[b]
        free[b] = False
        chosen.append(ids[b])
    return Design(chosen, gains, current, posterior_sd(A), [], np.zeros(0))


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
                 focus_weight: float = 1.0, compare: bool = True, progress: bool = True, device=None) -> dict:
    """Choose ``count`` trial masks from a pool of ``pool`` candidates (see the module doc).

    ``model``: a calibration's params.yaml or a diagnosis folder (sequential design), or
    None (before any print). ``fiducials``: the registration marks on every candidate
    (``with_fiducials``), before their information is computed. ``prints``: registration folders of prints already made (their
    masks' information joins the prior). Returns a dict: masks (id -> uint8), design
    (Design), table (rows per chosen mask), sd (rows per parameter: prior, designed,
    random paper masks of the same count), focus, seconds.
    """
    TRIAL_MASKS.make(count=count, pool=pool, draws=draws, seed=seed, size=size)
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
        from .model import EFFECTS

        fp = {p.name for e in focus_effects for p in EFFECTS[e].params}
        focus = [j for j, k in enumerate(names) if k in fp] or None

    cands = candidate_pool(pool, seed, size, fiducials=fiducials)
    bar = _bar(progress, len(cands), "information of the candidates")
    F = information(cands, params, U, device=device, progress=bar)
    start = None
    if prints:
        from .calibration import load_prints

        data = load_prints(prints)
        start = information(data.masks, params, U, device=device).sum(axis=1)
    ids = list(cands)
    d = greedy(F, ids, count, prior_precision, focus, focus_weight, start)
    d.names, d.prior_sd = names, sd0
    table = [dict(id=f"design_{i:03d}", candidate=c, pattern=c.rsplit("_", 1)[0], gain=g)
             for i, (c, g) in enumerate(zip(d.ids, d.gains))]
    out_masks = {row["id"]: cands[row["candidate"]] for row in table}
    sd_rows = [dict(parameter=k, prior_sd=float(sd0[j] * _unit(params, names)[1][j]),
                    designed_sd=float(d.sd[j] * _unit(params, names)[1][j])) for j, k in enumerate(names)]
    result = dict(masks=out_masks, design=d, table=table, sd=sd_rows, focus=focus_effects, model=params.model,
                  draws=U, criterion=d.criterion)
    if compare:  # the paper's random masks, same count, same draws and prior
        paper = M.trial_masks(count, seed=seed, size=size)
        Fp = information(paper, params, U, device=device)
        A = np.broadcast_to(prior_precision, (draws, len(names), len(names))).copy() + Fp.sum(axis=1)
        if start is not None:
            A = A + start
        sdp = posterior_sd(A)
        result["criterion_paper"] = float(criterion(A, focus, focus_weight))
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
    (predicted parameter sd: prior, designed, random paper masks), design.yaml (criterion,
    model, focus) and design.png (the masks and the sd bars)."""
    from .io import output_dir, write_png, write_tsv, write_yaml

    with output_dir(out_dir, command="masks design", inputs=list(inputs)) as tmp:
        for mid, m in result["masks"].items():
            write_png(tmp / f"{mid}.png", m)
        info = tmp / "design"
        info.mkdir()
        write_tsv(info / "design.tsv", result["table"])
        write_tsv(info / "parameters.tsv", result["sd"])
        write_yaml(info / "design.yaml", dict(
            criterion="pseudo-Bayesian D-optimality on the print's sensitivity to the parameters (unscatter.design)",
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
    fig = plt.figure(figsize=(2 * cols, 2 * rows + 3.2))
    gs = fig.add_gridspec(rows + 1, cols, height_ratios=[1] * rows + [1.6])
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
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
