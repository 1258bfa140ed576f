"""Calibration of the printer simulator on trial prints (Guan et al. 2022, 'Simulator calibration').

The paper fits Eq. 1's parameters with a genetic algorithm; the objective is "the mean
squared distance between the real printed structure and the simulator output,
averaging among all 32 trial data pairs", with the hard threshold. Here:

1. GA (DEAP) on the free parameters. The whole population is evaluated as a batch
   through ``model.FixedMasks`` (precomputed spectra), on every 4th pixel by default:
   the dose there is computed exactly (from the band-limited spectrum, at the cost of a
   128 x 128 grid) and compared with the measured print's pixel, so the objective is an
   unbiased subsample of the full-resolution one (no area averaging, whose threshold
   would shift edges).
2. Refinement: L-BFGS on the smooth (sigmoid) model, on every 2nd pixel by default,
   kept only if it lowers the hard-threshold objective on every pixel.
3. Validation: k-fold over prints (held-out IoU and pixel error) and a bootstrap over
   prints for the parameters' spread. Refits run a small GA in a box around the
   full-data optimum, then the refinement.

The objective (setting ``objective``, ``OBJECTIVES``) is the paper's mean squared
distance by default (``mismatch``); ``pixel_error`` weighs each print by the inverse of
its printed area, so that the fit is scored per print as the prints are judged (IoU,
pixel error) rather than per pixel, where large prints outweigh thin ones.

Inputs are registration outputs (``<id>.png`` prints in mask coordinates, ``qc.tsv``,
``batch.yaml``); prints with status ok or empty are used, failed ones never.
"""

from __future__ import annotations

import logging
import math
import random
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from . import metrics
from .io import InputError, output_dir, read_mask, read_print, read_tsv, read_yaml, write_rgb, write_tsv
from .settings import CALIBRATION
from .model import (
    FixedMasks,
    Params,
    default_device,
    default_params,
    get_model,
    masks_to_tensor,
    save_params,
)

log = logging.getLogger(__name__)

USABLE = ("ok", "empty")  # an empty print is a measurement too: nothing cured
STATUSES = ("ok", "empty", "failed")

# The user-facing settings (population, generations, folds, bootstrap, free_c0, refine,
# threads) take their defaults and bounds from unscatter.settings.CALIBRATION.
_D = CALIBRATION.default
DEFAULTS = dict(
    free_c0=_D.free_c0,  # the gauge: fix c0 = 1 (see unscatter.model)
    bounds=None,  # {name: (lower, upper)} over the model's defaults
    ga_size=128,  # the GA samples every f-th pixel, f leaving about this many a side
    population=_D.population,
    generations=_D.generations,
    cxpb=0.7,
    mutpb=0.3,
    tournament=3,
    elite=2,
    refine=_D.refine,
    refine_size=256,  # the refinement's sampling (None: every pixel); the final check uses every pixel
    temperatures=(0.1, 0.03),  # smooth threshold, as a fraction of T, coarse to fine
    refine_iters=10,  # L-BFGS iterations per temperature
    folds=_D.folds,  # k-fold over prints; 0 or 1: none
    bootstrap=_D.bootstrap,  # bootstrap replicates over prints; 0: none
    refit_population=12,
    refit_generations=6,
    refit_span=0.1,  # refit GA box: optimum +- span x bound range
    refit_size=256,  # refinement grid of the refits
    residual_maps=True,
    figure=True,
    progress=True,
    device=None,
    # torch CPU threads for the run (None: as configured). The tensors are small: with 2
    # threads on 2 shared cores OpenMP spin-waits, measured 3.5x slower than 1 thread on a
    # busy machine. Results depend (slightly) on the thread count: part of the settings.
    threads=_D.threads,
    # what the fit minimises (OBJECTIVES): "mismatch", the paper's mean squared distance,
    # weighs each print by its area; "dice" (1 - Dice per print, IoU's twin) and
    # "pixel_error" weigh each print as the scores of prints (IoU, pixel error) do
    objective=_D.objective,
    area_floor=0.02,  # dice, pixel_error: a print's area counts as at least about this share of the field
)

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


# ----------------------------------------------------------------------------- data


@dataclass
class PrintSet:
    """The usable trial pairs of one or more registration outputs."""

    labels: list  # unique id per print (``<dir name>/<id>`` when several dirs)
    ids: list
    dirs: list  # prints dir of each print
    status: list
    masks: np.ndarray  # (B, H, W) uint8
    prints: np.ndarray  # (B, H, W) bool
    pixel_size_um: float
    prints_dirs: list
    failed: list = field(default_factory=list)

    def __len__(self):
        return len(self.ids)


def load_prints(prints_dirs) -> PrintSet:
    """Read registration outputs; errors name the file or folder at fault."""
    if isinstance(prints_dirs, (str, Path)):
        prints_dirs = [prints_dirs]
    dirs = [Path(d) for d in prints_dirs]
    if not dirs:
        raise ValueError("no prints folders given")
    labels, ids, owners, status, masks, prints, failed = [], [], [], [], [], [], []
    pixel, pixel_src, shape, shape_src = None, None, None, None
    for d in dirs:
        if not d.is_dir():
            raise InputError(d, "prints folder does not exist")
        meta = read_yaml(d / "batch.yaml")
        try:
            px = float(meta["pixel_size_um"])
        except (KeyError, TypeError, ValueError):
            raise InputError(d / "batch.yaml", "needs a numeric pixel_size_um") from None
        if not (math.isfinite(px) and px > 0):
            raise InputError(d / "batch.yaml", f"pixel_size_um must be positive, found {px}")
        if pixel is not None and not math.isclose(px, pixel, rel_tol=1e-6):
            raise InputError(d / "batch.yaml", f"pixel_size_um {px} differs from {pixel} in {pixel_src}; calibrate batches of one printer setup together")
        pixel, pixel_src = px, d / "batch.yaml"
        rows = read_tsv(d / "qc.tsv")
        cols = set(rows[0]) if rows else set()
        missing = {"id", "status", "mask"} - cols
        if rows and missing:
            raise InputError(d / "qc.tsv", f"missing column(s) {sorted(missing)}")
        for r in rows:
            st = (r["status"] or "").strip()
            if st not in STATUSES:
                raise InputError(d / "qc.tsv", f"print {r['id']!r} has status {st!r}; expected one of {STATUSES}")
            if st == "failed":  # never fit a print that failed registration QC
                failed.append(f"{d.name}/{r['id']}" if len(dirs) > 1 else r["id"])
                continue
            mpath = Path(r["mask"])
            if not mpath.is_absolute():
                mpath = d / mpath
            mask = read_mask(mpath)
            ppath = d / f"{r['id']}.png"
            if not ppath.is_file():
                raise InputError(ppath, f"print listed in qc.tsv with status {st!r} but the file is missing")
            pr = read_print(ppath)
            if pr.shape != mask.shape:
                raise InputError(ppath, f"print is {pr.shape[0]}x{pr.shape[1]} but its mask {mpath} is {mask.shape[0]}x{mask.shape[1]}; prints must be in mask coordinates")
            if shape is not None and pr.shape != shape:
                raise InputError(ppath, f"print is {pr.shape[0]}x{pr.shape[1]}, the others are {shape[0]}x{shape[1]} (first: {shape_src})")
            shape, shape_src = pr.shape, ppath
            ids.append(r["id"])
            labels.append(f"{d.name}/{r['id']}" if len(dirs) > 1 else r["id"])
            owners.append(d)
            status.append(st)
            masks.append(mask)
            prints.append(pr)
    where = dirs[0] if len(dirs) == 1 else Path(", ".join(str(d) for d in dirs))
    if not ids:
        raise InputError(where, f"no usable prints (status ok or empty) in qc.tsv; {len(failed)} failed")
    if len(set(labels)) != len(labels):
        raise InputError(where, "the same print id appears twice")
    P = np.stack(prints)
    if not P.any():
        raise InputError(where, f"all {len(ids)} usable prints are empty (nothing cured): the threshold and the kernel cannot be identified; print at a higher dose")
    if P.all():
        raise InputError(where, f"all {len(ids)} usable prints are solid everywhere: the threshold and the kernel cannot be identified; print at a lower dose")
    return PrintSet(labels, ids, owners, status, np.stack(masks), P, pixel, dirs, failed)


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
    """The free parameters scaled to the unit box [0, 1]^d (the GA's genome)."""

    def __init__(self, params: Params, lower=None, upper=None):
        self.params = params
        self.names = params.free
        self.lo = np.array([params.bounds[k][0] for k in self.names]) if lower is None else np.asarray(lower, float)
        self.hi = np.array([params.bounds[k][1] for k in self.names]) if upper is None else np.asarray(upper, float)

    def decode(self, g) -> dict:
        g = np.atleast_2d(np.asarray(g, float))
        v = self.lo + np.clip(g, 0, 1) * (self.hi - self.lo)
        out = {k: np.full(len(g), float(x)) for k, x in self.params.values.items()}
        for i, k in enumerate(self.names):
            out[k] = v[:, i]
        return out

    def encode(self, values: dict) -> np.ndarray:
        return np.array([(values[k] - lo) / (hi - lo) for k, lo, hi in zip(self.names, self.lo, self.hi)])

    def around(self, values: dict, span: float) -> Space:
        """A box of +- span x (full range) around ``values``, inside the full bounds."""
        full_lo = np.array([self.params.bounds[k][0] for k in self.names])
        full_hi = np.array([self.params.bounds[k][1] for k in self.names])
        c = np.array([values[k] for k in self.names])
        r = span * (full_hi - full_lo)
        return Space(self.params, np.maximum(full_lo, c - r), np.minimum(full_hi, c + r))


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


def refine(space: Space, objective: Objective, model, values: dict, device, temperatures=(0.1, 0.03), iters=12) -> dict:
    """L-BFGS on the free parameters through the smooth (sigmoid) model.

    Works in unit-box coordinates of the full bounds and clips to them at the end.
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
    # (the support grows with sigma and the tail's length, and with an aspect ratio away from 1)
    kern = [i for i, k in enumerate(space.names) if any(p.name == k for kt in model.kernels for p in kt.params)]
    for temp in temperatures:
        opt = torch.optim.LBFGS([u], lr=1.0, max_iter=iters, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            with torch.no_grad():  # stay where the evaluator's padding holds the kernel
                u.clamp_(-0.5, 1.5)
                for i in kern:
                    u[i].clamp_(0.0, 1.0)
            loss = objective.smooth(theta_of(u), temp)[0]
            loss.backward()
            return loss

        opt.step(closure)
    g = np.clip(u.detach().cpu().numpy().astype(float), 0, 1)
    return {k: float(v[0]) for k, v in space.decode(g).items()}


# ------------------------------------------------------------------------ one fit


@dataclass
class Fit:
    values: dict
    objective: float  # hard objective on the check grid
    objective_ga: float  # the GA best on the check grid
    refined: bool  # refinement kept
    history: list
    factors: dict  # decimation factors used: ga, refine, check


def fit_params(space: Space, model, obj, f_ga: int, f_ref: int | None, f_check: int, device, seed: int, s: dict,
               population: int, generations: int, init=(), desc="GA", history=True) -> Fit:
    """GA on every ``f_ga``-th pixel, then the refinement on every ``f_ref``-th pixel
    (None: no refinement), kept if it lowers the hard objective on every
    ``f_check``-th pixel. ``obj(f)`` gives the objective at factor f.

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
    values, f, kept = best, f_best, False
    factors = dict(ga=f_ga, check=min(f_check, band_factor(sim, model, best, f_check)))
    if f_ref is not None:
        f_ref = band_factor(sim, model, best, f_ref)
        factors["refine"] = f_ref
        cand = refine(Space(space.params), obj(f_ref), model, best, device, s["temperatures"], s["refine_iters"])
        f_cand = float(check.hard(model.theta(cand, device))[0])
        if f_cand < f_best:  # the refinement is kept only if the hard objective improves
            values, f, kept = cand, f_cand, True
    return Fit(values, f, f_best, kept, hist if history else [], factors)


# ---------------------------------------------------------------------- calibrate


def calibrate(prints_dirs, out_dir, model: str = _D.model, seed: int = _D.seed, **settings) -> Params:
    """Calibrate ``model`` on registered prints; write params.yaml and the diagnostics.

    ``prints_dirs``: registration outputs (``<id>.png``, ``qc.tsv``, ``batch.yaml``);
    prints with status ok or empty are used, failed ones never. ``settings`` override
    ``DEFAULTS`` (GA size, bounds, free_c0, refinement, folds, bootstrap, ...).

    Writes under ``out_dir``: params.yaml, history.tsv (GA per generation), cv.tsv
    (held-out metrics per print), bootstrap.tsv (refit parameters), residuals/<id>.png
    (red: measured but not simulated, blue: simulated but not measured) and fit.png.
    Returns the fitted Params. Raises InputError (naming the file or folder) for bad or
    uninformative input; a fit on a bound is flagged in params.yaml and warned about.
    ``out_dir`` is a new folder or an earlier calibration, replaced when the fit is done.
    """
    unknown = sorted(set(settings) - set(DEFAULTS))
    if unknown:
        raise TypeError(f"unknown calibration setting(s) {unknown}; known: {sorted(DEFAULTS)}")
    checked = {k: CALIBRATION.check(k, v) for k, v in dict(settings, model=model, seed=seed).items()
               if k in CALIBRATION.settings and not (k == "threads" and v is None)}
    s = {**DEFAULTS, **settings, **checked}
    if s["objective"] not in OBJECTIVES:
        raise ValueError(f"unknown objective {s['objective']!r}; known: {sorted(OBJECTIVES)}")
    inputs = [prints_dirs] if isinstance(prints_dirs, (str, Path)) else list(prints_dirs)
    before = torch.get_num_threads()
    with output_dir(out_dir, command="calibrate", inputs=inputs) as tmp:
        if s["threads"]:
            torch.set_num_threads(int(s["threads"]))
        try:
            params = _calibrate(prints_dirs, tmp, model, seed, s)
        finally:
            torch.set_num_threads(before)
    return params


def _calibrate(prints_dirs, out_dir, model: str, seed: int, s: dict) -> Params:
    out_dir = Path(out_dir)
    t_start = time.perf_counter()
    device = torch.device(s["device"]) if s["device"] else default_device()
    data = load_prints(prints_dirs)
    m = get_model(model)
    params = default_params(model, free_c0=s["free_c0"], bounds=s["bounds"], pixel_size_um=data.pixel_size_um)
    space = Space(params)
    support = m.support_px({k: hi for k, (lo, hi) in params.bounds.items()})  # pad for the widest kernel allowed
    B, H, W = data.masks.shape
    f_ga = grid_factor((H, W), s["ga_size"])
    f_ref = grid_factor((H, W), s["refine_size"])
    f_refit = grid_factor((H, W), s["refit_size"])
    log.info("calibrating %s on %d prints (%dx%d): GA on a %dx%d grid", model, B, H, W, H // f_ga, W // f_ga)

    sim = FixedMasks(m, masks_to_tensor(data.masks, device), support_px=support)
    objs: dict[int, Objective] = {}
    def obj(f):
        if f not in objs:
            objs[f] = build_objective(sim, data.prints, f, s["objective"], s["area_floor"])
        return objs[f]

    full = obj(1)
    run_warnings: list[str] = []
    if B < 8:
        run_warnings.append(f"only {B} usable prints: the fit and its uncertainty rest on little data")

    # -- the fit ---------------------------------------------------------------
    t0 = time.perf_counter()
    fit = fit_params(space, m, obj, f_ga, f_ref if s["refine"] else None, 1, device, seed, s,
                     s["population"], s["generations"], desc="calibration GA")
    t_fit = time.perf_counter() - t0
    values = fit.values

    # -- fits on a bound --------------------------------------------------------
    on_bound = {}
    for k in space.names:
        lo, hi = params.bounds[k]
        tol = 5e-3 * (hi - lo)
        if values[k] <= lo + tol:
            on_bound[k] = "lower"
        elif values[k] >= hi - tol:
            on_bound[k] = "upper"
    for k, side in on_bound.items():
        msg = (f"{k} = {values[k]:.4g} is on its {side} bound {params.bounds[k]}: the bounds likely exclude the data's "
               f"optimum; widen them (setting 'bounds') and recalibrate")
        run_warnings.append(msg)

    # -- validation and uncertainty ---------------------------------------------
    sims = _simulated(m, full, values, device)
    per_print = [dict(id=lab, iou=metrics.iou(sm, p), pixel_error=metrics.pixel_error(sm, p), mismatch=float(np.mean(sm != p)))
                 for lab, sm, p in zip(data.labels, sims, data.prints)]
    refit = dict(space=space, model=m, obj=obj, f_ga=band_factor(full.sim, m, values, f_ga, GA_BAND_TOL),
                 f_ref=band_factor(full.sim, m, values, f_refit), device=device, s=s, values=values)
    t0 = time.perf_counter()
    cv_rows, cv_summary = cross_validate(data, full, refit, seed, s["folds"], per_print)
    t_cv = time.perf_counter() - t0
    t0 = time.perf_counter()
    boot_rows, unc = bootstrap(data, refit, seed, s["bootstrap"])
    t_boot = time.perf_counter() - t0
    if unc.get("note"):
        run_warnings.append(unc["note"])
    for w in run_warnings:
        warnings.warn(w, stacklevel=2)
        log.warning(w)

    # -- outputs -----------------------------------------------------------------
    fitted = params.with_values(**values)
    entries = {}
    for k in m.names:
        e = {}
        if k in unc.get("parameters", {}):
            e.update(unc["parameters"][k])
        if k in on_bound:
            e["on_bound"] = on_bound[k]
        entries[k] = e
    fitted.info = dict(
        parameter_extras={k: e for k, e in entries.items() if e},
        objective=dict(name=s["objective"], definition=OBJECTIVES[s["objective"]], area_floor=s["area_floor"], value=fit.objective, ga=fit.objective_ga, refinement_kept=fit.refined,
                       in_sample_iou_mean=float(np.mean([r["iou"] for r in per_print]))),
        data=dict(prints_dirs=[str(Path(d).resolve()) for d in data.prints_dirs], design_size=[H, W], prints=len(data),
                  ids=data.labels, empty=[lab for lab, st in zip(data.labels, data.status) if st == "empty"],
                  excluded_failed=data.failed),
        fit=dict(seed=seed, method="DEAP GA, then L-BFGS on the sigmoid model (kept if it lowers the hard objective)",
                 sampling=dict(note="every f-th pixel of the exact dose and the measured print (unbiased subsample)",
                               **{f"{k}_every": v for k, v in fit.factors.items()}),
                 population=s["population"], generations=s["generations"], on_bound=sorted(on_bound),
                 seconds=round(t_fit, 2),
                 settings={k: (list(v) if isinstance(v, tuple) else v) for k, v in s.items() if k not in ("progress", "device")}),
        validation=dict(cv_summary, seconds=round(t_cv, 2)),
        uncertainty=dict({k: v for k, v in unc.items() if k != "parameters"}, seconds=round(t_boot, 2)),
        warnings=run_warnings,
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    save_params(out_dir / "params.yaml", fitted)
    hist_cols = ["generation", "nevals", "best", "mean", "std"] + space.names
    write_tsv(out_dir / "history.tsv", fit.history, hist_cols)
    write_tsv(out_dir / "cv.tsv", cv_rows, ["fold", "id", "n_train", "iou", "pixel_error", "mismatch", "in_sample_iou"])
    if boot_rows:
        write_tsv(out_dir / "bootstrap.tsv", boot_rows, ["replicate", "prints", "objective"] + space.names)
    if s["residual_maps"]:
        for lab, meas, sim in zip(data.labels, data.prints, sims):
            write_rgb(out_dir / "residuals" / f"{lab.replace('/', '__')}.png", residual_rgb(meas, sim))
    if s["figure"]:
        fit_figure(out_dir / "fit.png", data, sims, per_print, model=model)
    log.info("calibration done in %.1f s (fit %.1f s, cv %.1f s, bootstrap %.1f s)", time.perf_counter() - t_start, t_fit, t_cv, t_boot)
    from .model import load_params

    return load_params(out_dir / "params.yaml")


def _simulated(m, full: Objective, values, device) -> np.ndarray:
    with torch.no_grad():
        return full.sim.prints(m.theta(values, device))[0].cpu().numpy()


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


def cross_validate(data: PrintSet, full: Objective, refit: dict, seed: int, folds: int, per_print: list):
    """k-fold over prints: refit without a fold, score the fold's prints (IoU, pixel error)."""
    B = len(data)
    folds = int(folds or 0)
    if folds < 2 or B < 2:
        return [], dict(folds=0, note="cross-validation off" if folds < 2 else "too few prints for cross-validation")
    k = min(folds, B)
    perm = np.random.default_rng([seed, 7]).permutation(B)
    m, device = refit["model"], refit["device"]
    rows = []
    for i, test in enumerate(np.array_split(perm, k)):
        train = np.setdiff1d(np.arange(B), test)
        fit = _refit(refit, train, None, seed + 1000 + i, f"cv fold {i}")
        with torch.no_grad():
            sims = full.subset(test).sim.prints(m.theta(fit.values, device))[0].cpu().numpy()
        for j, sim in zip(test, sims):
            p = data.prints[j]
            rows.append(dict(fold=i, id=data.labels[j], n_train=len(train), iou=metrics.iou(sim, p), pixel_error=metrics.pixel_error(sim, p),
                             mismatch=float(np.mean(sim != p)), in_sample_iou=per_print[j]["iou"]))
    pe = [r["pixel_error"] for r in rows if np.isfinite(r["pixel_error"])]
    summary = dict(folds=k, heldout_iou_mean=float(np.mean([r["iou"] for r in rows])),
                   heldout_iou_median=float(np.median([r["iou"] for r in rows])),
                   heldout_pixel_error_mean=float(np.mean(pe)) if pe else None,
                   heldout_mismatch_mean=float(np.mean([r["mismatch"] for r in rows])),
                   in_sample_iou_mean=float(np.mean([r["iou"] for r in per_print])))
    return rows, summary


def bootstrap(data: PrintSet, refit: dict, seed: int, replicates: int):
    """Refit on prints resampled with replacement; spread of each free parameter."""
    n = int(replicates or 0)
    names = refit["space"].names
    if n < 1:
        return [], dict(method="none", replicates=0)
    B = len(data)
    rng = np.random.default_rng([seed, 11])
    rows, skipped = [], 0
    for r in range(n):
        counts = rng.multinomial(B, np.full(B, 1.0 / B))
        idx = np.nonzero(counts)[0]
        pr = data.prints[idx]
        if not pr.any() or pr.all():  # a resample without edges identifies nothing
            skipped += 1
            continue
        fit = _refit(refit, idx, counts[idx], seed + 2000 + r, f"bootstrap {r}")
        rows.append(dict(replicate=r, prints=len(idx), objective=fit.objective, **{k: fit.values[k] for k in names}))
    out = dict(method="bootstrap over prints (refits: small GA around the full-data optimum + refinement)", replicates=n,
               used=len(rows), parameters={})
    if skipped:
        out["note"] = f"{skipped} of {n} bootstrap resamples had no edges (all empty or all solid) and were skipped"
    if len(rows) >= 2:
        for k in names:
            v = np.array([row[k] for row in rows])
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


def fit_figure(path, data: PrintSet, sims: np.ndarray, per_print: list, n: int = 6, model: str = "eq1") -> None:
    """Rows of prints: mask, measured, simulated, residual (matplotlib, Agg)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    B = len(data)
    pick = np.unique(np.linspace(0, B - 1, min(n, B)).round().astype(int))
    fig = Figure(figsize=(10, 2.6 * len(pick)))
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(pick), 4, squeeze=False)
    for row, j in zip(axes, pick):
        panels = [(data.masks[j], "mask", "gray"), (data.prints[j], "measured print", "gray"), (sims[j], f"simulated ({model})", "gray"),
                  (residual_rgb(data.prints[j], sims[j]), f"residual, IoU {per_print[j]['iou']:.3f}", None)]
        for ax, (img, title, cmap) in zip(row, panels):
            ax.imshow(img, cmap=cmap, vmin=0 if cmap else None, vmax=(255 if img.dtype == np.uint8 else 1) if cmap else None)
            ax.set_title(f"{data.labels[j]}: {title}" if title == "mask" else title, fontsize=8)
            ax.set_axis_off()
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)


def simulate_dir(params_path, mask_dir, out_dir, device=None) -> list[Path]:
    """Simulated binary prints (0/255) of every mask PNG in ``mask_dir`` as ``<id>.png``
    (``out_dir``: a new folder or an earlier output of this function)."""
    from .io import list_pngs, write_png
    from .model import load_params, simulate

    params = load_params(params_path)
    masks = list_pngs(mask_dir)
    if not masks:
        raise InputError(mask_dir, "no .png masks")
    with output_dir(out_dir, command="simulate", inputs=[params_path, mask_dir]) as tmp:
        for mid, p in masks.items():
            write_png(tmp / f"{mid}.png", simulate(params, read_mask(p), device=device))
    return [Path(out_dir) / f"{mid}.png" for mid in masks]


__all__ = ["calibrate", "load_prints", "PrintSet", "Objective", "OBJECTIVES", "print_weights", "build_objective", "per_print_error", "Space", "run_ga", "refine", "fit_params", "cross_validate",
           "bootstrap", "residual_rgb", "fit_figure", "simulate_dir", "grid_factor", "band_factor"]
