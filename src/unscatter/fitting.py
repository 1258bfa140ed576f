"""Fitting a printer model to measured prints: what calibration and diagnosis share.

- the objective (``OBJECTIVES``: the paper's mismatch, pixel_error, dice), evaluated on
  every f-th pixel of the prints through ``model.FixedMasks`` (``Objective``), with the
  per-print error that is its held-out metric (``per_print_error``);
- the search: a GA (DEAP) on the free parameters scaled to their bounds (``Space``,
  ``run_ga``), then a gradient refinement on the smooth model (``refine``), kept only if
  it lowers the hard objective (``fit_params``); sampling factors chosen so the kernel
  found is not aliased (``band_factor``);
- folds and resamples: k-fold cross-validation over prints and a bootstrap over prints,
  each a small refit around the full-data optimum (``cross_validate``, ``bootstrap``),
  run in this process or in worker processes (``Refits``, ``default_workers``).

``unscatter.calibration`` fits Eq. 1 (Guan et al. 2022) with it; ``unscatter.diagnosis``
fits the candidate effects with it and scores models by the same held-out error.
"""

from __future__ import annotations

import logging
import os
import random
from dataclasses import dataclass

import numpy as np
import torch

from . import metrics
from .model import FixedMasks, Params, canonical, keep_freed_memory, periods, unwrapped

log = logging.getLogger(__name__)

OBJECTIVES = {
    "mismatch": (
        "mean over prints and pixels of (measured - simulated)^2, hard threshold, full resolution "
        "(Guan et al. 2022, 'Simulator calibration': mean squared distance averaged over the trial pairs)"),
    "dice": (
        "mean over prints of |measured XOR simulated| / (|measured| + |simulated| + area_floor x pixels), hard "
        "threshold, full resolution: 1 - Dice per print, a monotone function of each print's IoU (IoU = D / (2 - D)), "
        "so the fit is scored as the prints are"),
    "pixel_error": (
        "mean over prints of |measured XOR simulated| / max(|measured|, area_floor x pixels), hard threshold, full "
        "resolution: each print's pixel error (unscatter.metrics), so that a thin or small print weighs as much as a "
        "large one (the paper's squared distance weighs prints by their area)"),
}
OBJECTIVE = OBJECTIVES["mismatch"]

# The GA's operators (DEAP; ``run_ga``), for the calibration and the diagnosis alike: crossover
# and mutation probabilities, tournament size, individuals kept unchanged (elite).
SEARCH = dict(cxpb=0.7, mutpb=0.3, tournament=3, elite=2)
# dice, pixel_error: a print's area counts as at least about this share of the field
AREA_FLOOR = 0.02


def build_objective(sim: FixedMasks, prints: np.ndarray, factor: int, objective: str = "mismatch",
                    area_floor: float = 0.02) -> Objective:
    """``Objective.build`` for one of ``OBJECTIVES``, on every ``factor``-th pixel."""
    return Objective.build(sim, prints, factor, print_weights(prints, objective, area_floor),
                           dice_floor=area_floor if objective == "dice" else None)


def per_print_error(simulated: np.ndarray, measured: np.ndarray, objective: str = "mismatch", area_floor: float = 0.02,
                    weights=None) -> np.ndarray:
    """Each print's share of the objective (its mean over prints is the objective):
    mismatch, mismatch times ``weights`` (pixel_error: ``print_weights`` of all the
    prints), or 1 - Dice."""
    s, m = np.asarray(simulated, bool), np.asarray(measured, bool)
    B = len(m)
    xor = (s != m).reshape(B, -1).sum(axis=1).astype(np.float64)
    npx = m[0].size if B else 1
    if objective == "dice":
        return xor / (s.reshape(B, -1).sum(axis=1) + m.reshape(B, -1).sum(axis=1) + area_floor * npx)
    w = np.ones(B) if weights is None else np.asarray(weights, np.float64)
    return xor / npx * w


def mask_threshold(masks: np.ndarray, prints: np.ndarray, objective: str = "mismatch", area_floor: float = 0.02,
                   weights=None) -> int:
    """The grey level t (1 to 256) at which the mask itself, ``mask >= t``, best matches
    ``prints`` by ``objective`` (``per_print_error``; ``weights`` as there): the model-free
    baseline a printer model must beat. Every t is scored at once from each print's
    histogram of mask grey levels among its printed and unprinted pixels (t = 256: nothing
    prints). Masks hold few grey levels, so the best t is a run of equal scores between
    two levels present; the middle of the first such run is taken (a held-out grey level
    inside it is not pushed to either side)."""
    masks = np.asarray(masks)
    if masks.dtype != np.uint8:
        raise TypeError(f"masks must be uint8 grey levels, got {masks.dtype}")
    m = np.asarray(prints, bool)
    B = len(m)
    if B == 0:
        raise ValueError("no prints to choose the mask's threshold on")
    grey = masks.reshape(B, -1).astype(np.int64) + 256 * np.arange(B)[:, None]
    printed = np.bincount(grey[m.reshape(B, -1)], minlength=256 * B).reshape(B, 256)
    dark = np.bincount(grey[~m.reshape(B, -1)], minlength=256 * B).reshape(B, 256)
    # column j is t = j + 1: the printed pixels of grey < t are missed, the unprinted ones of grey >= t print
    xor = (np.cumsum(printed, axis=1) + dark.sum(axis=1, keepdims=True) - np.cumsum(dark, axis=1)).astype(np.float64)
    npx = m[0].size
    if objective == "dice":
        lit = (printed + dark).sum(axis=1, keepdims=True) - np.cumsum(printed + dark, axis=1)  # pixels the mask prints
        den = lit + m.reshape(B, -1).sum(axis=1, keepdims=True) + area_floor * npx
        err = np.divide(xor, den, out=np.zeros_like(xor), where=den > 0)  # both empty: no error
    else:
        w = np.ones(B) if weights is None else np.asarray(weights, np.float64)
        err = xor / npx * w[:, None]
    e = err.mean(axis=0)
    best = np.flatnonzero(e <= e.min() * (1 + 1e-12) + 1e-300)
    run = np.split(best, np.flatnonzero(np.diff(best) > 1) + 1)[0]  # the first run of tied t
    return int(run[len(run) // 2]) + 1


def mask_heldout(masks: np.ndarray, prints: np.ndarray, folds: list, objective: str = "mismatch",
                 area_floor: float = 0.02, weights=None) -> tuple[np.ndarray, list]:
    """The mask itself as a held-out prediction, the baseline every model must beat: each
    fold's prints (``folds``: index arrays) predicted as ``mask >= t``, t chosen on the
    other folds' prints by the objective (``mask_threshold``; ``weights``: of all the
    prints). Returns the predictions and each fold's t."""
    B = len(prints)
    w = np.ones(B) if weights is None else np.asarray(weights, np.float64)
    sims = np.zeros(np.shape(prints), bool)
    ts = []
    for test in folds:
        train = np.setdiff1d(np.arange(B), test)
        ts.append(mask_threshold(masks[train], prints[train], objective, area_floor, w[train]))
        sims[test] = masks[test] >= ts[-1]
    return sims, ts


def print_weights(prints: np.ndarray, objective: str = "mismatch", area_floor: float = 0.02) -> np.ndarray:
    """Per-print weights (mean 1) that make the weighted mean of per-print mismatch the
    ``objective`` (``OBJECTIVES``): ones for the paper's mismatch, and for pixel_error
    pixels / max(printed area, area_floor x pixels), normalised to mean 1."""
    if objective not in OBJECTIVES:
        raise ValueError(f"unknown objective {objective!r}; known: {sorted(OBJECTIVES)}")
    B = len(prints)
    if objective in ("mismatch", "dice") or B == 0:
        return np.ones(B)
    npx = prints[0].size
    area = np.asarray(prints, bool).reshape(B, -1).sum(axis=1)
    w = npx / np.maximum(area, float(area_floor) * npx)
    return w / w.mean()



def grid_factor(shape, size: int | None) -> int:
    """Decimation factor (1, 2, 4 or 8) leaving about ``size`` samples a side."""
    if not size:
        return 1
    f = 1
    while f < 8 and min(shape) / (2 * f) >= size:
        f *= 2
    return f


GA_BAND_TOL = 0.1  # GA: dose errors up to ~1e-2 (2 % of a threshold of 0.5) are fine for a coarse search
BAND_TOL = 0.01  # refinement and checks: dose errors ~1e-3 (measured: ~ a tenth of the dropped transfer)


def band_factor(sim: FixedMasks, model, values: dict, fmax: int, tol: float = BAND_TOL) -> int:
    """Largest decimation factor <= fmax at which the kernel for ``values`` leaves at
    most ``tol`` of its transfer beyond the samples' Nyquist frequency."""
    f = fmax
    while f > 1 and sim.dropped(model.theta(values, sim.masks.device), f) > tol:
        f //= 2
    return f


# ------------------------------------------------------------------------ objective


class Objective:
    """Weighted mean over prints of mean((measured - simulated)^2) on one grid; with
    ``dice_floor`` (a share of the field) each print's |measured XOR simulated| /
    (|measured| + |simulated| + dice_floor x pixels) instead, 1 - Dice."""

    def __init__(self, sim: FixedMasks, target: torch.Tensor, weights=None, chunk: int | None = None,
                 dice_floor: float | None = None):
        self.sim = sim
        self.target = target  # (B, h, w) measured print (0/1) at the sim's sample points
        B = target.shape[0]
        self.dice_floor = dice_floor
        self.tsum = target.sum(dim=(1, 2))
        self.floor_px = None if dice_floor is None else float(dice_floor) * target.shape[1] * target.shape[2]
        self.raw_weights = np.ones(B) if weights is None else np.asarray(weights, np.float64)
        w = torch.as_tensor(self.raw_weights.astype(np.float32))
        self.weights = (w / w.sum()).to(target.device, torch.float32)
        npx = target.shape[1] * target.shape[2]
        # for a binary simulated print s: (t - s)^2 = t^2 + s (1 - 2 t), so one masked sum per print
        self.base = (target**2).mean(dim=(1, 2))
        self.gain = (1 - 2 * target) / npx
        # blocks of individuals x masks with ~16 MB of spectra: big enough to amortise
        # reading the precomputed spectra, small enough to reuse freed memory instead of
        # faulting in fresh pages (which costs more than the arithmetic here)
        per = sim.shape[0] * (sim.shape[1] // 2 + 1) * 8  # one mask, one individual
        self.chunk = chunk or max(1, int(16e6 // (B * per)))
        self.block = B if self.chunk * B * per <= 32e6 else max(1, int(16e6 // (self.chunk * per)))

    @classmethod
    def build(cls, sim: FixedMasks, prints: np.ndarray, factor: int, weights=None, dice_floor: float | None = None):
        """The objective on every ``factor``-th pixel of the full-resolution one.

        ``sim`` is the full-resolution evaluator of the prints' masks; the samples are
        exact dose values, so this is an unbiased subsample of the full objective.
        """
        target = torch.from_numpy(np.ascontiguousarray(prints[:, ::factor, ::factor], dtype=np.float32))
        return cls(sim.decimated(factor) if factor > 1 else sim, target.to(sim.masks.device), weights, dice_floor=dice_floor)

    def subset(self, idx, weights=None) -> Objective:
        """The objective on prints ``idx``, their weights times ``weights`` (e.g. bootstrap counts)."""
        idx = np.asarray(idx)
        t = self.target[torch.as_tensor(idx, device=self.target.device)]
        w = self.raw_weights[idx] * (1.0 if weights is None else np.asarray(weights, np.float64))
        return Objective(self.sim.subset(idx), t, w, dice_floor=self.dice_floor)

    def per_print(self, theta) -> torch.Tensor:
        """(P, B) mean squared distance per print, hard threshold."""
        out = []
        P = next(iter(theta.values())).shape[0]
        with torch.no_grad():
            for i in range(0, P, self.chunk):
                sub = {k: v[i : i + self.chunk] for k, v in theta.items()}
                B = self.target.shape[0]
                parts = []
                for j in range(0, B, self.block):
                    sl = slice(j, j + self.block) if self.block < B else None
                    s = self.sim.prints(sub, masks=sl)
                    sl = sl or slice(None)
                    if self.floor_px is None:
                        parts.append(self.base[sl][None] + torch.where(s, self.gain[sl], 0.0).sum(dim=(2, 3)))
                    else:
                        S = s.sum(dim=(2, 3)).to(torch.float32)
                        inter = torch.where(s, self.target[sl], 0.0).sum(dim=(2, 3))
                        t = self.tsum[sl][None]
                        parts.append((t + S - 2 * inter) / (t + S + self.floor_px))
                out.append(torch.cat(parts, dim=1))
        return torch.cat(out)

    def hard(self, theta) -> np.ndarray:
        return (self.per_print(theta) @ self.weights).cpu().numpy().astype(np.float64)

    def smooth(self, theta, temperature: float) -> torch.Tensor:
        s = self.sim.prints(theta, temperature)
        if self.floor_px is None:
            return ((s - self.target[None]) ** 2).mean(dim=(2, 3)) @ self.weights
        S, inter, t = s.sum(dim=(2, 3)), (s * self.target[None]).sum(dim=(2, 3)), self.tsum[None]
        return ((t + S - 2 * inter) / (t + S + self.floor_px)) @ self.weights


class Space:
    """The free parameters scaled to the unit box [0, 1]^d (the GA's genome).

    A parameter that repeats itself (``model.periods``: an ellipse's angle) has no bound
    a search need stop at: where the box spans its period, a coordinate beyond [0, 1]
    is wrapped into it rather than clipped, and a value is encoded as its repeat nearest
    the box's centre."""

    def __init__(self, params: Params, lower=None, upper=None):
        self.params = params
        self.names = params.free
        self.lo = np.array([params.bounds[k][0] for k in self.names]) if lower is None else np.asarray(lower, float)
        self.hi = np.array([params.bounds[k][1] for k in self.names]) if upper is None else np.asarray(upper, float)
        per = periods(params)
        self.period = np.array([per.get(k, 0.0) for k in self.names])  # 0: not periodic
        # the coordinates that wrap: the box spans a whole period
        self.wraps = (self.period > 0) & (np.abs((self.hi - self.lo) - self.period) <= 1e-9 * np.maximum(self.period, 1))

    def decode(self, g) -> dict:
        g = np.atleast_2d(np.asarray(g, float))
        g = np.where(self.wraps, np.mod(g, 1.0), np.clip(g, 0, 1))
        v = self.lo + g * (self.hi - self.lo)
        out = {k: np.full(len(g), float(x)) for k, x in self.params.values.items()}
        for i, k in enumerate(self.names):
            out[k] = v[:, i]
        return out

    def encode(self, values: dict) -> np.ndarray:
        v = np.array([float(values[k]) for k in self.names])
        centre = 0.5 * (self.lo + self.hi)
        per = np.where(self.period > 0, self.period, 1.0)
        v = np.where(self.period > 0, v - per * np.round((v - centre) / per), v)
        return (v - self.lo) / (self.hi - self.lo)

    def around(self, values: dict, span: float) -> Space:
        """A box of +- span x (full range) around ``values``, inside the full bounds (the
        whole period for a parameter that wraps)."""
        full_lo = np.array([self.params.bounds[k][0] for k in self.names])
        full_hi = np.array([self.params.bounds[k][1] for k in self.names])
        c = np.array([values[k] for k in self.names])
        r = span * (full_hi - full_lo)
        lo, hi = np.maximum(full_lo, c - r), np.minimum(full_hi, c + r)
        full = Space(self.params)
        return Space(self.params, np.where(full.wraps, full_lo, lo), np.where(full.wraps, full_hi, hi))


# ------------------------------------------------------------------------------- GA


def _deap_types():
    from deap import base, creator

    if not hasattr(creator, "UnscatterFitness"):
        creator.create("UnscatterFitness", base.Fitness, weights=(-1.0,))
    if not hasattr(creator, "UnscatterIndividual"):
        creator.create("UnscatterIndividual", list, fitness=creator.UnscatterFitness)
    return creator.UnscatterIndividual


def run_ga(space: Space, objective: Objective, model, device, seed: int, population: int, generations: int,
           cxpb=0.7, mutpb=0.3, tournament=3, elite=2, init=(), progress=True, desc="GA"):
    """DEAP GA on the unit box; the population is evaluated as one batch per generation.

    Returns (best values dict, best objective, history rows).
    """
    from deap import algorithms, base, tools
    from tqdm import tqdm

    Individual = _deap_types()
    d = len(space.names)
    tb = base.Toolbox()
    tb.register("mate", tools.cxSimulatedBinaryBounded, eta=15.0, low=0.0, up=1.0)
    tb.register("mutate", tools.mutPolynomialBounded, eta=20.0, low=0.0, up=1.0, indpb=1.0 / max(d, 1))
    tb.register("select", tools.selTournament, tournsize=tournament)

    def evaluate(inds):
        inds = [i for i in inds if not i.fitness.valid]
        if inds:
            theta = model.theta(space.decode([list(i) for i in inds]), device)
            for ind, f in zip(inds, objective.hard(theta)):
                ind.fitness.values = (float(f),)
        return len(inds)

    state = random.getstate()  # DEAP draws from the random module: seed it, then restore
    random.seed(seed)
    try:
        pop = [Individual(list(np.clip(g, 0, 1))) for g in init][:population]
        pop += [Individual([random.random() for _ in range(d)]) for _ in range(population - len(pop))]
        history = []
        nevals = evaluate(pop)
        bar = tqdm(range(generations + 1), desc=desc, disable=not progress, unit="gen", leave=False)
        for gen in bar:
            if gen > 0:
                elites = [tb.clone(i) for i in tools.selBest(pop, elite)]
                off = algorithms.varAnd(tb.select(pop, len(pop) - elite), tb, cxpb, mutpb)
                nevals = evaluate(off)
                pop = elites + off
            fits = np.array([i.fitness.values[0] for i in pop])
            best = tools.selBest(pop, 1)[0]
            vals = space.decode(list(best))
            history.append(dict(generation=gen, nevals=nevals, best=float(fits.min()), mean=float(fits.mean()), std=float(fits.std()),
                                **{k: float(vals[k][0]) for k in space.names}))
            bar.set_postfix(best=f"{fits.min():.5f}")
        bar.close()
    finally:
        random.setstate(state)
    best = tools.selBest(pop, 1)[0]
    return {k: float(v[0]) for k, v in space.decode(list(best)).items()}, float(best.fitness.values[0]), history


# ----------------------------------------------------------------------- refinement


# a temperature's L-BFGS stops when the objective changes by less than this share of its start (test_diagnosis'
# recovery test: at 1e-4 the lamp-field draw stopped in the valley where the field terms trade, 3.7 % above the truth's
# objective; at 1e-5 it reached the optimum in 2/3 of 1e-6's time, but the fold fits of two other draws stayed so
# close to their common start that the spread they give was 6 to 9 times smaller than the error)
REFINE_TOL = 1e-6


def refine(space: Space, objective: Objective, model, values: dict, device, temperatures=(0.1, 0.03), iters=12,
           tol: float | None = None, endpoints: bool = False):
    """L-BFGS on the free parameters through the smooth (sigmoid) model, one run per
    temperature (coarse to fine), each from the last one's end.

    Works in unit-box coordinates of the full bounds and clips to them at the end.
    ``iters`` caps each run's iterations; with ``tol`` a run stops earlier, once the
    smooth objective changes by less than ``tol`` of its value at the run's start (or the
    step in the unit box is that small): it runs to convergence, not to a fixed budget.
    Returns the values at the last temperature, or with ``endpoints`` the values at the
    end of every temperature's run (the smoothest optimum is not the hard one's, and
    the lowest temperature's objective is rough: the caller judges them by the hard
    objective, as ``fit_params`` does).
    """
    u = torch.tensor(space.encode(values), dtype=torch.float32, device=device, requires_grad=True)
    lo = torch.tensor(space.lo, dtype=torch.float32, device=device)
    span = torch.tensor(space.hi - space.lo, dtype=torch.float32, device=device)
    fixed = {k: torch.tensor([float(v)], device=device) for k, v in values.items() if k not in space.names}

    def theta_of(u):
        free = lo + span * u
        th = dict(fixed)
        for i, k in enumerate(space.names):
            th[k] = free[i : i + 1]
        return {k: th[k] for k in model.names}

    # kernel parameters stay within their bounds, where the evaluator's padding holds the kernel
    # (the support grows with sigma and the tail's length, and with an aspect ratio away from 1);
    # a parameter that wraps (an angle) goes where it will, and is wrapped into its box at the end
    kern = [i for i, k in enumerate(space.names) if any(p.name == k for kt in model.kernels for p in kt.params)
            and not space.wraps[i]]
    boxed = [i for i in range(len(space.names)) if not space.wraps[i]]

    def clamp():
        with torch.no_grad():  # stay where the evaluator's padding holds the kernel
            for i in boxed:
                u[i].clamp_(-0.5, 1.5)
            for i in kern:
                u[i].clamp_(0.0, 1.0)

    ends = []
    for temp in temperatures:
        scale = 1.0
        if tol:  # the objective in units of its start, so that the tolerance is relative
            clamp()
            with torch.no_grad():
                scale = max(float(objective.smooth(theta_of(u), temp)[0]), 1e-12)
        opt = torch.optim.LBFGS([u], lr=1.0, max_iter=iters, line_search_fn="strong_wolfe",
                                **({"tolerance_change": float(tol)} if tol else {}))

        def closure():
            opt.zero_grad()
            clamp()
            loss = objective.smooth(theta_of(u), temp)[0] / scale
            loss.backward()
            return loss

        opt.step(closure)
        ends.append({k: float(v[0]) for k, v in space.decode(u.detach().cpu().numpy().astype(float)).items()})
    return ends if endpoints else ends[-1]


def hard_scores(objective: Objective, model, values: list, device) -> np.ndarray:
    """The hard objective of each of several parameter sets (dicts of the same keys), as one batch."""
    return objective.hard(model.theta({k: np.array([v[k] for v in values]) for k in values[0]}, device))


BOUND_TOL = 5e-3  # a value within this share of its range of a bound is on it (``on_bounds``)


def on_bounds(value_sets: list, bounds: dict, names, wrap: dict | None = None) -> dict:
    """The parameters of which any of ``value_sets`` (dicts) lies on a bound of the search,
    within ``BOUND_TOL`` of its range: name -> "lower" or "upper". The calibration flags its
    fit so; the diagnosis its fit and its fold fits, whose spread a bound cuts short
    (``diagnosis.fold_spread``: the fold fits of a heavy tail whose length the prints do
    not pin down piled up at its 40 px bound; docs/diagnosis.md, "Fits that reach the optimum").
    The parameters in ``wrap`` (``model.periods``) have no bound a search stops at."""
    out = {}
    for n in names:
        if wrap and n in wrap:
            continue
        lo, hi = bounds[n]
        tol = BOUND_TOL * (hi - lo)
        v = np.array([vs[n] for vs in value_sets], float)
        if (v <= lo + tol).any():
            out[n] = "lower"
        elif (v >= hi - tol).any():
            out[n] = "upper"
    return out


# ------------------------------------------------------------------------ one fit


@dataclass
class Fit:
    values: dict
    objective: float  # hard objective on the check grid
    objective_ga: float  # the GA best on the check grid
    refined: bool  # refinement kept
    history: list
    factors: dict  # decimation factors used: ga, refine, check
    # the refinement's own optimum: the end of the temperature with the lowest hard objective, whether or not it beats
    # the GA's best (None without refinement). The GA's population holds the start, so where the start is the fit on a
    # superset of these prints, ``values`` is often that start itself (``diagnosis.fold_spread``)
    refined_values: dict | None = None


def fit_params(space: Space, model, obj, f_ga: int, f_ref: int | None, f_check: int, device, seed: int, s: dict,
               population: int, generations: int, init=(), desc="GA", history=True) -> Fit:
    """GA on every ``f_ga``-th pixel, then the refinement on every ``f_ref``-th pixel
    (None: no refinement; ``s['temperatures']``, at most ``s['refine_iters']`` L-BFGS
    iterations each, stopping at ``s['refine_tol']``): the end of the temperature with
    the lowest hard objective on every ``f_check``-th pixel is kept if it is lower than
    the GA's. ``obj(f)`` gives the objective at factor f.

    A factor is lowered when the kernel found is too narrow for it (``band_factor``).
    """
    sim = obj(f_ga).sim  # any evaluator: band_factor needs only its grid and model
    while True:
        best, _, hist = run_ga(space, obj(f_ga), model, device, seed, population, generations, s["cxpb"], s["mutpb"],
                               s["tournament"], s["elite"], init=init, progress=s["progress"], desc=desc)
        f_ok = band_factor(sim, model, best, f_ga, GA_BAND_TOL)
        if f_ok == f_ga:
            break
        log.info("the kernel found is too narrow for every-%d-th-pixel sampling; GA again at every %d-th pixel", f_ga, f_ok)
        f_ga = f_ok
    check = obj(min(f_check, band_factor(sim, model, best, f_check)))
    f_best = float(check.hard(model.theta(best, device))[0])
    values, f, kept, own = best, f_best, False, None
    factors = dict(ga=f_ga, check=min(f_check, band_factor(sim, model, best, f_check)))
    if f_ref is not None:
        f_ref = band_factor(sim, model, best, f_ref)
        factors["refine"] = f_ref
        ends = refine(Space(space.params), obj(f_ref), model, best, device, s["temperatures"], s["refine_iters"],
                      tol=s.get("refine_tol"), endpoints=True)
        scores = hard_scores(check, model, ends, device)
        i = int(np.argmin(scores))
        own = ends[i]
        if scores[i] < f_best:  # the refinement is kept only if the hard objective improves
            values, f, kept = ends[i], float(scores[i]), True
    return Fit(values, f, f_best, kept, hist if history else [], factors, own)



# ------------------------------------------------------------------- folds, resamples


def default_workers(device: torch.device | None = None) -> int:
    """Fits run in one process per CPU core this process may use (one on a GPU)."""
    if device is not None and torch.device(device).type != "cpu":
        return 1
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def _refit(refit: dict, idx, weights, seed: int, desc: str) -> Fit:
    """A cheaper fit on a subset/resample: small GA in a box around the full-data optimum,
    then the refinement. The GA is not seeded with the optimum itself: an elite copy of it
    would survive most small refits and shrink the bootstrap spread to nothing."""
    s, m, device, values = refit["s"], refit["model"], refit["device"], refit["values"]
    box = refit["space"].around(values, s["refit_span"])
    cache: dict[int, Objective] = {}

    def obj(f):
        if f not in cache:
            cache[f] = refit["obj"](f).subset(idx, weights)
        return cache[f]

    return fit_params(box, m, obj, refit["f_ga"], refit["f_ref"] if s["refine"] else None, refit["f_ref"], device, seed,
                      dict(s, progress=False), s["refit_population"], s["refit_generations"], desc=desc, history=False)


# a worker process's refit context (``Refits`` with workers > 1), built once by its initializer
_REFITS: dict = {}


def _refits_init(build, args: tuple) -> None:
    torch.set_num_threads(1)
    keep_freed_memory()
    _REFITS.clear()
    _REFITS["refit"] = build(*args)


def _refits_one(idx, weights, seed: int, desc: str) -> Fit:
    return _refit(_REFITS["refit"], idx, weights, seed, desc)


class Refits:
    """Runs the refits of the folds and of the bootstrap (``_refit``): in this process
    (``workers`` 1), or in ``workers`` spawned processes, each on one torch thread with
    its own copy of the refit context, ``build(*args)`` (``build``: a module-level
    function, so that it pickles; it must build what ``refit`` holds, objective and
    model, from the same inputs). A refit depends only on its prints, weights and seed,
    so the results are those of one process on one thread, whatever the number of
    workers (``tests/test_calibration.py``). A pool that breaks (a script without an
    ``if __name__ == "__main__":`` guard, which spawn needs) is warned about and the
    refits go on in this process."""

    def __init__(self, refit: dict, workers: int = 1, build=None, args: tuple = ()):
        self.refit, self.workers, self.pool = refit, int(workers), None
        if self.workers > 1 and build is not None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            # spawn, not fork: a forked child of a process whose torch threads have run can hang
            self.pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                            initializer=_refits_init, initargs=(build, args))
            log.info("the refits run in %d worker processes", self.workers)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)
            self.pool = None

    def run(self, tasks: list) -> list:
        """The ``Fit`` of each task (idx, weights, seed, desc), in the order given."""
        if self.pool is not None and len(tasks) > 1:
            from concurrent.futures.process import BrokenProcessPool

            try:
                futures = [self.pool.submit(_refits_one, *task) for task in tasks]
                return [f.result() for f in futures]
            except BrokenProcessPool as exc:
                log.warning("the refits' worker processes stopped (%s); the refits go on in this process (a script "
                            "that calibrates with workers > 1 needs its top level under `if __name__ == '__main__':`, "
                            "as multiprocessing's spawn requires)", exc)
                self.close()
        return [_refit(self.refit, *task) for task in tasks]


def cross_validate(data, full: Objective, refit: dict, seed: int, folds: int, per_print: list, runner: Refits | None = None):
    """k-fold over prints: refit without a fold, score the fold's prints (IoU, pixel
    error, the objective's error), and the mask itself beside it: ``mask >= t`` with t
    chosen on the fold's training prints (``mask_threshold``), the baseline a printer
    model must beat. ``data``: the prints (``prints.PrintSet``: labels, masks, prints);
    ``runner``: where the refits run (None: in this process)."""
    B = len(data)
    folds = int(folds or 0)
    if folds < 2 or B < 2:
        return [], dict(folds=0, note="cross-validation off" if folds < 2 else "too few prints for cross-validation")
    k = min(folds, B)
    perm = np.random.default_rng([seed, 7]).permutation(B)
    m, device, s = refit["model"], refit["device"], refit["s"]
    objective, floor = s["objective"], s["area_floor"]
    weights = print_weights(data.prints, objective, floor)
    runner = runner or Refits(refit)
    tests = np.array_split(perm, k)
    trains = [np.setdiff1d(np.arange(B), test) for test in tests]
    fits = runner.run([(train, None, seed + 1000 + i, f"cv fold {i}") for i, train in enumerate(trains)])
    bases, ts = mask_heldout(data.masks, data.prints, tests, objective, floor, weights)
    rows, sims_all, base_all, order = [], [], [], []
    for i, (test, train, fit, t) in enumerate(zip(tests, trains, fits, ts)):
        with torch.no_grad():
            sims = full.subset(test).sim.prints(m.theta(fit.values, device))[0].cpu().numpy()
        base = bases[test]
        err = per_print_error(sims, data.prints[test], objective, floor, weights[test])
        err_base = per_print_error(base, data.prints[test], objective, floor, weights[test])
        for j, sim, b, e, eb in zip(test, sims, base, err, err_base):
            p = data.prints[j]
            rows.append(dict(fold=i, id=data.labels[j], n_train=len(train), iou=metrics.iou(sim, p), pixel_error=metrics.pixel_error(sim, p),
                             mismatch=float(np.mean(sim != p)), in_sample_iou=per_print[j]["iou"], error=float(e),
                             mask_threshold=t, mask_iou=metrics.iou(b, p), mask_error=float(eb)))
        sims_all += list(sims)
        base_all += list(base)
        order += list(test)
    pe = [r["pixel_error"] for r in rows if np.isfinite(r["pixel_error"])]
    error, mask_error = float(np.mean([r["error"] for r in rows])), float(np.mean([r["mask_error"] for r in rows]))
    summary = dict(folds=k, heldout_iou_mean=float(np.mean([r["iou"] for r in rows])),
                   heldout_iou_median=float(np.median([r["iou"] for r in rows])),
                   heldout_iou_pooled=metrics.pooled_iou(sims_all, data.prints[order]),
                   heldout_pixel_error_mean=float(np.mean(pe)) if pe else None,
                   heldout_mismatch_mean=float(np.mean([r["mismatch"] for r in rows])),
                   in_sample_iou_mean=float(np.mean([r["iou"] for r in per_print])),
                   heldout_error=error,
                   mask_baseline=dict(
                       heldout_error=mask_error, heldout_iou_mean=float(np.mean([r["mask_iou"] for r in rows])),
                       heldout_iou_pooled=metrics.pooled_iou(base_all, data.prints[order]),
                       thresholds=sorted(set(ts)),
                       note="the mask itself printed where its grey level >= t, t chosen on each fold's training prints "
                            "by the objective: no printer model"),
                   beats_mask=bool(error < mask_error))
    # does the mask score better by held-out IoU, print by print (paired t-test, one-sided)?
    d = np.array([r["mask_iou"] - r["iou"] for r in rows], np.float64)
    d = d[np.isfinite(d)]
    if len(d) >= 3 and d.std() > 0:
        from scipy.stats import ttest_rel

        summary["mask_baseline"]["iou_better_p"] = float(ttest_rel(d, np.zeros_like(d), alternative="greater").pvalue)
    return rows, summary


def bootstrap(data, refit: dict, seed: int, replicates: int, runner: Refits | None = None):
    """Refit on prints resampled with replacement; spread of each free parameter.
    ``runner``: where the refits run (None: in this process)."""
    n = int(replicates or 0)
    names = refit["space"].names
    if n < 1:
        return [], dict(method="none", replicates=0)
    B = len(data)
    rng = np.random.default_rng([seed, 11])
    tasks, skipped = [], 0
    for r in range(n):
        counts = rng.multinomial(B, np.full(B, 1.0 / B))
        idx = np.nonzero(counts)[0]
        pr = data.prints[idx]
        if not pr.any() or pr.all():  # a resample without edges identifies nothing
            skipped += 1
            continue
        tasks.append((r, idx, counts[idx]))
    fits = (runner or Refits(refit)).run([(idx, w, seed + 2000 + r, f"bootstrap {r}") for r, idx, w in tasks])
    rows = [dict(replicate=r, prints=len(idx), objective=fit.objective, **{k: fit.values[k] for k in names})
            for (r, idx, _), fit in zip(tasks, fits)]
    out = dict(method="bootstrap over prints (refits: small GA around the full-data optimum + refinement)", replicates=n,
               used=len(rows), parameters={})
    if skipped:
        out["note"] = f"{skipped} of {n} bootstrap resamples had no edges (all empty or all solid) and were skipped"
    if len(rows) >= 2:
        per = periods(refit["space"].params)
        once = [canonical(row, per) for row in rows]  # an ellipse written once
        for k in names:
            v = unwrapped([row[k] for row in once], per.get(k))  # an angle's spread across its wrap
            out["parameters"][k] = dict(std=float(v.std(ddof=1)), q05=float(np.quantile(v, 0.05)), q95=float(np.quantile(v, 0.95)))
    return rows, out



# -------------------------------------------------------------------------- figures


def residual_rgb(measured: np.ndarray, simulated: np.ndarray) -> np.ndarray:
    """Measured minus simulated: red +1 (printed, not simulated), blue -1, grey both, white neither."""
    m, s = np.asarray(measured, bool), np.asarray(simulated, bool)
    rgb = np.full(m.shape + (3,), 255, np.uint8)
    rgb[m & s] = (190, 190, 190)
    rgb[m & ~s] = (215, 40, 40)
    rgb[~m & s] = (40, 90, 215)
    return rgb
