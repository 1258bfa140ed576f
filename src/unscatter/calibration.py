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

The objective, the search, the refinement, the folds and the bootstrap live in
``unscatter.fitting``, which the diagnosis shares, and the prints are read by
``unscatter.prints``; this module runs them for Eq. 1 and writes the calibration's
outputs.

The measured prints are thresholded microscope images, not the cure. Prints whose
``registration.yaml`` records its measurement can be fitted through a measurement stage
(``unscatter.measurement``: the density from Eq. 1's dose, blurred by the microscope, at
the registration's level). The setting ``measurement``: "none" fits the prints as if
they were the cure (the paper's way); "auto" (the default) does so too, but where the
fitted sigma is no larger than the measurement's own blur (``_resolution``: the prints
do not resolve the scattering) it fits them again through the stage, the microscope's
blur held as batch.yaml states it (``microscope_blur_um``) or else as the registration's
print template measured it; "registration" always fits through the stage, holding a
stated blur, else fitting it by a profile after the GA (``_profile_blur``). The fitted
parameters are Eq. 1's alone; params.yaml records the stage under ``measurement``.

Inputs are registration outputs (``<id>.png`` prints in mask coordinates, ``qc.tsv``,
``batch.yaml``); prints with status ok or empty are used, failed ones never.
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from . import metrics
from .fitting import (
    AREA_FLOOR,
    GA_BAND_TOL,
    OBJECTIVES,
    REFINE_TOL,
    SEARCH,
    Objective,
    Refits,
    Space,
    band_factor,
    bootstrap,
    build_objective,
    cross_validate,
    default_workers,
    fit_params,
    grid_factor,
    hard_scores,
    on_bounds,
    refine,
    residual_rgb,
)
from .io import InputError, output_dir, read_mask, read_yaml, write_rgb, write_tsv
from .measurement import BLUR, MeasuredMasks, MeasuredModel, Measurement, from_registration
from .prints import PrintSet, load_prints
from .settings import CALIBRATION
from .model import (
    FixedMasks,
    Params,
    default_device,
    keep_freed_memory,
    default_params,
    get_model,
    masks_to_tensor,
    periods,
    save_params,
)

log = logging.getLogger(__name__)

# The user-facing settings (population, generations, folds, bootstrap, free_c0, refine,
# threads, workers) take their defaults and bounds from unscatter.settings.CALIBRATION.
_D = CALIBRATION.default
DEFAULTS = dict(
    free_c0=_D.free_c0,  # the gauge: fix c0 = 1 (see unscatter.model)
    bounds=None,  # {name: (lower, upper)} over the model's defaults
    ga_size=128,  # the GA samples every f-th pixel, f leaving about this many a side
    population=_D.population,
    generations=_D.generations,
    **SEARCH,  # the GA's operators (fitting.SEARCH)
    refine=_D.refine,
    refine_size=256,  # the refinement's sampling (None: every pixel); the final check uses every pixel
    # smooth threshold, as a fraction of T, coarse to fine; the end of the temperature whose hard objective is lowest
    # is kept (fitting.fit_params): 0.03 smooths the edge more than the prints' own noise does, so its optimum is
    # not the hard objective's (bench_fit_recovery: with (0.1, 0.03) and a fixed 10-20 iterations, 5 of 10 fits
    # ended 1-3 % above the true parameters' objective on their own prints)
    temperatures=(0.1, 0.03, 0.01),
    refine_iters=100,  # L-BFGS iterations per temperature (at most) ...
    refine_tol=REFINE_TOL,  # ... stopping earlier once the objective changes by less than this share (fitting.refine)
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
    # the refits of the folds and the bootstrap run in this many processes at once, each on one torch thread (None: one
    # per CPU core, fitting.default_workers; 1 on a GPU); with threads 1 the results do not depend on it
    workers=_D.workers,
    # what the fit minimises (OBJECTIVES): "mismatch", the paper's mean squared distance,
    # weighs each print by its area; "dice" (1 - Dice per print, IoU's twin) and
    # "pixel_error" weigh each print as the scores of prints (IoU, pixel error) do
    objective=_D.objective,
    area_floor=AREA_FLOOR,  # dice, pixel_error: a print's area counts as at least about this share of the field
    # the measurement stage between the simulated cure and the measured print (unscatter.measurement):
    # "registration" (what registration.yaml records; none for prints without it), "none", or a Measurement
    measurement=_D.measurement,
)

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
               if k in CALIBRATION.settings and not (k == "threads" and v is None) and not isinstance(v, Measurement)}
    s = {**DEFAULTS, **settings, **checked}
    if s["objective"] not in OBJECTIVES:
        raise ValueError(f"unknown objective {s['objective']!r}; known: {sorted(OBJECTIVES)}")
    inputs = [prints_dirs] if isinstance(prints_dirs, (str, Path)) else list(prints_dirs)
    before = torch.get_num_threads()
    keep_freed_memory()  # the fits' temporaries (``model.keep_freed_memory``)
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

    printer_params, printer_model = params, m

    def through(meas):
        """The model, its simulator, objectives, parameters and search space, fitted
        through the measurement ``meas`` (or without one)."""
        m, sim, obj = _objectives(model, data.masks, data.prints, support, meas, device, s)
        p = printer_params
        if meas is not None:
            # the measured print is the density blurred at the registration's level: fit it so, the
            # microscope's blur (unless given) along with the printer's parameters
            log.info("fitting through the measurement: %s", meas.as_dict())
            # the search holds the blur (at the registration's estimate, or as stated); the profile below fits it
            b0 = float(np.clip(meas.blur_px, *meas.blur_bounds)) if meas.fit_blur else float(meas.blur_px)
            p = Params(p.model, {**p.values, BLUR: b0},
                       {**p.bounds, BLUR: (min(meas.blur_bounds[0], b0), max(meas.blur_bounds[1], b0))},
                       (*p.fixed, BLUR), p.pixel_size_um)
        return m, sim, obj, p, Space(p)

    meas = _measurement(s["measurement"], data)
    m, sim, obj, params, space = through(meas)
    run_warnings: list[str] = []
    if B < 8:
        run_warnings.append(f"only {B} usable prints: the fit and its uncertainty rest on little data")

    # -- the fit ---------------------------------------------------------------
    t0 = time.perf_counter()
    fit = fit_params(space, m, obj, f_ga, f_ref if s["refine"] else None, 1, device, seed, s,
                     s["population"], s["generations"], desc="calibration GA")
    values = fit.values
    switched = None
    if meas is None and s["measurement"] == "auto" and "sigma_px" in space.names:
        # prints that do not resolve the scattering (its sigma within the measurement's own blur) are fitted
        # again through the measurement, its blur held: as stated, else as the registration's template measured it
        first = _resolution(values, data, None)
        try:
            held = _measurement("registration", data) if first and not first["resolved"] else None
        except InputError:  # folders that record it differently: no one measurement to fit through
            held = None
        if held is not None:
            meas, stated = replace(held, fit_blur=False), not held.fit_blur
            switched = dict(first_sigma_px=round(float(values["sigma_px"]), 4), first_objective=float(fit.objective),
                            measurement_blur_px=first["measurement_blur_px"],
                            blur=("stated (batch.yaml microscope_blur_um)" if stated else "the registration's print template's"))
            log.info("sigma_px = %.3g is within the measurement's own blur (%.3g px): fitted again through the measurement "
                     "stage, the microscope's blur held at %.3g px", values["sigma_px"], first["measurement_blur_px"], meas.blur_px)
            m, sim, obj, params, space = through(meas)
            fit = fit_params(space, m, obj, f_ga, f_ref if s["refine"] else None, 1, device, seed, s,
                             s["population"], s["generations"], desc="calibration GA, through the measurement")
            values = fit.values
    full = obj(1)
    t_fit = time.perf_counter() - t0
    profile = []
    if meas is not None and meas.fit_blur:
        values, profile = _profile_blur(params, m, obj, fit, f_ref if s["refine"] else None, device, s, meas)
        params = params.with_values(**{BLUR: values[BLUR]})
        space = Space(params)
        fit.objective = profile_best = min(r["objective"] for r in profile)
        log.info("measurement blur %.3f px (profile objective %.6g)", values[BLUR], profile_best)

    # -- fits on a bound --------------------------------------------------------
    on_bound = on_bounds([values], params.bounds, space.names, periods(params))
    for k, side in on_bound.items():
        msg = (f"{k} = {values[k]:.4g} is on its {side} bound {params.bounds[k]}: the bounds likely exclude the data's "
               f"optimum; widen them (setting 'bounds') and recalibrate")
        run_warnings.append(msg)

    # -- validation and uncertainty ---------------------------------------------
    sims = _simulated(m, full, values, device)
    per_print = [dict(id=lab, iou=metrics.iou(sm, p), pixel_error=metrics.pixel_error(sm, p), mismatch=float(np.mean(sm != p)))
                 for lab, sm, p in zip(data.labels, sims, data.prints)]
    f_ga_refit, f_ref_refit = band_factor(full.sim, m, values, f_ga, GA_BAND_TOL), band_factor(full.sim, m, values, f_refit)
    refit = dict(space=space, model=m, obj=obj, f_ga=f_ga_refit, f_ref=f_ref_refit, device=device, s=s, values=values)
    workers = 1 if device.type != "cpu" else (s["workers"] if s["workers"] is not None else default_workers(device))
    n_refits = (s["folds"] if (s["folds"] or 0) >= 2 else 0) + (s["bootstrap"] or 0)
    context = (model, data.masks, data.prints, support, meas, device, s, space, values, f_ga_refit, f_ref_refit)
    with Refits(refit, min(workers, max(n_refits, 1)), _refit_context, context) as runner:
        t0 = time.perf_counter()
        cv_rows, cv_summary = cross_validate(data, full, refit, seed, s["folds"], per_print, runner)
        t_cv = time.perf_counter() - t0
        t0 = time.perf_counter()
        boot_rows, unc = bootstrap(data, refit, seed, s["bootstrap"], runner)
        t_boot = time.perf_counter() - t0
    if unc.get("note"):
        run_warnings.append(unc["note"])
    run_warnings += _against_mask(model, cv_summary, s["objective"])
    resolution = _resolution(values, data, meas) if "sigma_px" in space.names else None  # a fitted sigma only
    if switched:
        resolution = dict(first, switched=True)
        run_warnings.append(
            f"the first fit's sigma_px = {switched['first_sigma_px']:.3g} was no larger than the measurement's own blur "
            f"({switched['measurement_blur_px']:.3g} design px): these prints do not resolve the scattering, so the "
            f"calibration fitted them again through the measurement stage, the microscope's blur held at "
            f"{meas.blur_px:.3g} px ({switched['blur']}); sigma_px is now {values['sigma_px']:.3g}. "
            + ("" if stated else "Stating the microscope's blur (batch.yaml "
               "microscope_blur_um, measured on beads) makes this surer. ") + "See docs/calibration.md, 'A stated microscope blur'")
    if resolution and not resolution["resolved"] and not switched:
        run_warnings.append(
            f"sigma_px = {values['sigma_px']:.3g} is no larger than the measurement's own blur "
            f"({resolution['measurement_blur_px']:.3g} design px: the microscope's blur as the registration's print "
            f"template measured it, with the registration's smoothing): these prints do not resolve the scattering, and the fit "
            f"takes the microscope's blur for it. Against the real cure such a model can predict worse than the mask "
            f"itself; image the prints at a higher magnification (docs/calibration.md, 'Scattering the microscope does not resolve')")
    for w in run_warnings:
        warnings.warn(w, stacklevel=2)
        log.warning(w)

    # -- outputs -----------------------------------------------------------------
    if meas is not None and BLUR in values:
        meas = meas.with_blur(values[BLUR])
    fitted = printer_params.with_values(**{k: v for k, v in values.items() if k != BLUR})
    entries = {}
    for k in printer_model.names:
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
                 settings={k: (list(v) if isinstance(v, tuple) else v.as_dict() if isinstance(v, Measurement) else v)
                           for k, v in s.items() if k not in ("progress", "device")}),
        validation=dict(cv_summary, seconds=round(t_cv, 2), **({"resolution": resolution} if resolution else {})),
        uncertainty=dict({k: v for k, v in unc.items() if k != "parameters"}, seconds=round(t_boot, 2)),
        warnings=run_warnings,
    )
    if meas is not None:
        fitted.info["measurement"] = dict(
            meas.as_dict(), profile=[{k: round(v, 6) for k, v in r.items()} for r in profile],
            **({"switched": dict(switched, note="measurement 'auto': the prints did not resolve the scattering")}
               if switched else {}),
            note="fitted through this measurement stage (unscatter.measurement): the measured print is the density, "
                 "blurred, at the level; the parameters are the printer's, without it")
    out_dir.mkdir(parents=True, exist_ok=True)
    save_params(out_dir / "params.yaml", fitted)
    hist_cols = ["generation", "nevals", "best", "mean", "std"] + space.names
    write_tsv(out_dir / "history.tsv", fit.history, hist_cols)
    write_tsv(out_dir / "cv.tsv", cv_rows, ["fold", "id", "n_train", "iou", "pixel_error", "mismatch", "in_sample_iou", "error",
                                            "mask_threshold", "mask_iou", "mask_error"])
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


def _resolution(values: dict, data: PrintSet, meas: Measurement | None) -> dict | None:
    """Does the fitted scattering exceed what the measurement itself blurs? The prints'
    registrations record the microscope's blur as their print template measured it and
    their own smoothing; where the fitted sigma is no larger than the two together, the
    prints cannot tell scattering from the microscope. The template's blur, not a blur
    batch.yaml states: the registered prints are blurred by more than the optics (the
    camera's pixels, the warps' interpolation), which the template's blur holds and a
    stated PSF does not (on the sharp random labs the stated blur was 0.3 to 0.8 of the
    template's; docs/calibration.md, 'A stated microscope blur'). None where nothing is recorded, the
    model has no sigma, or the fit went through the measurement stage; the caller asks
    only where sigma was fitted."""
    if meas is not None or "sigma_px" not in values:
        return None
    recs = _recorded(data)
    if any(r is None or r.get("blur_px") is None for r in recs):
        return None  # some folders record none: nothing one number can say
    b = float(np.hypot(np.mean([float(r["blur_px"]) for r in recs]), np.mean([float(r.get("smoothing_px", 0.0)) for r in recs])))
    return dict(measurement_blur_px=round(b, 4), sigma_px=float(values["sigma_px"]),
                resolved=bool(values["sigma_px"] > RESOLVED_RATIO * b),
                note="the fitted sigma against the microscope's blur as the registration's print template measured it "
                     "(registration.yaml) and the registration's smoothing, in quadrature: at or below it the prints do "
                     "not resolve the scattering")


RESOLVED_RATIO = 1.0  # a fitted sigma at most this times the measurement's own blur is not resolved
IOU_DISAGREE_P = 0.05  # the mask's held-out IoU above the model's, print by print, this surely: the objective is wrong


def _against_mask(model: str, cv: dict, objective: str) -> list[str]:
    """Warnings where the calibrated model predicts the held-out prints no better than the
    mask itself (``fitting.cross_validate``'s baseline): by the objective (the model's
    form misses what shapes the prints), or by held-out IoU, print by print (a paired
    t-test, p < IOU_DISAGREE_P), where the objective prefers the model (the objective and
    the score disagree)."""
    mb = cv.get("mask_baseline")
    if not mb:
        return []
    ts = "/".join(map(str, mb["thresholds"]))
    scores = (f"held-out {objective} {cv['heldout_error']:.5g} against {mb['heldout_error']:.5g}, IoU {cv['heldout_iou_mean']:.4f} "
              f"against {mb['heldout_iou_mean']:.4f} (pooled {cv['heldout_iou_pooled']:.4f} against {mb['heldout_iou_pooled']:.4f})")
    if not cv["beats_mask"]:
        return [f"{model} as calibrated predicts the held-out prints no better than the mask itself (printed where its grey "
                f"level >= {ts}): {scores}. The model's form misses what shapes these prints: run the diagnosis, and do not "
                f"compensate with this model (docs/calibration.md, 'The mask itself as the baseline')"]
    if mb.get("iou_better_p", 1.0) < IOU_DISAGREE_P:
        return [f"{model} as calibrated beats the mask itself (printed where its grey level >= {ts}) by the objective "
                f"but the mask scores better by held-out IoU (paired t-test over prints, p {mb['iou_better_p']:.2g}): "
                f"{scores}. The objective and the score disagree: '{objective}' "
                f"{'weighs each print by its area' if objective == 'mismatch' else 'does not rank as IoU does'}; "
                f"see docs/calibration.md, 'The mask itself as the baseline'"]
    return []


def _profile_blur(params: Params, m, obj, fit, f_ref, device, s: dict, meas: Measurement, step: float = 1.0):
    """The measurement's blur by its profile: for blurs on a grid over its bounds, the
    printer's parameters refined from the search's optimum, the scattering sigma moved
    along sqrt(sigma^2 + blur^2), which the two trade along, and scored by the hard
    objective on every pixel; then at the vertex of a parabola through the best and its
    neighbours. The profile's differences are small (a few 1e-3 of the objective), so
    each point is a full refinement (both temperatures) on the refinement's grid: on the
    search's coarser grid the density's aliasing, and with one temperature the
    refinement's own error, move its minimum.

    A search over both at once fails here: blur and sigma trade along a long, narrow
    valley (the measured width is about their quadrature sum) that the GA does not
    follow. Returns (values, profile rows)."""
    check = obj(1)
    lo, hi = meas.blur_bounds
    b0 = float(fit.values[BLUR])
    width2 = float(fit.values["sigma_px"]) ** 2 + b0**2
    sig_lo = params.bounds["sigma_px"][0]

    def at(b, f, temperatures):
        start = dict(fit.values, **{BLUR: float(b), "sigma_px": float(np.sqrt(max(width2 - b * b, sig_lo**2)))})
        p_b = params.with_values(**{BLUR: float(b)})
        tried = [start]
        if f is not None:
            tried += refine(Space(p_b), obj(band_factor(obj(1).sim, m, start, f)), m, start, device, temperatures,
                            s["refine_iters"], tol=s["refine_tol"], endpoints=True)
        scores = hard_scores(check, m, tried, device)
        i = int(np.argmin(scores))  # the start, or the temperature's end with the lowest hard objective
        return tried[i], float(scores[i])

    grid = np.arange(lo, hi + 1e-9, step)
    # the search's own fit (at the recorded blur) stays a candidate
    searched = dict(blur_px=b0, objective=float(check.hard(m.theta(fit.values, device))[0]),
                    sigma_px=float(fit.values["sigma_px"]), T=float(fit.values["T"]))
    rows, best = [], (fit.values, searched["objective"])
    for b in grid:
        v, f = at(b, f_ref, tuple(s["temperatures"]))
        rows.append(dict(blur_px=float(b), objective=f, sigma_px=float(v["sigma_px"]), T=float(v["T"])))
        if f < best[1]:
            best = (v, f)
    i = int(np.argmin([r["objective"] for r in rows]))
    if 0 < i < len(rows) - 1:  # the parabola's vertex through the best and its neighbours
        y0, y1, y2 = (rows[j]["objective"] for j in (i - 1, i, i + 1))
        den = y0 - 2 * y1 + y2
        if den > 0:
            b = float(np.clip(grid[i] + 0.5 * step * (y0 - y2) / den, grid[i - 1], grid[i + 1]))
            v, f = at(b, f_ref, tuple(s["temperatures"]))
            rows.append(dict(blur_px=b, objective=f, sigma_px=float(v["sigma_px"]), T=float(v["T"])))
            if f < best[1]:
                best = (v, f)
    return best[0], rows + [searched]


def _objectives(model: str, masks: np.ndarray, prints: np.ndarray, support: float, meas: Measurement | None, device,
                s: dict):
    """The model fitted, its simulator of the masks and ``obj(f)``, the objective on every
    f-th pixel (built once per f): Eq. 1's, or through the measurement stage ``meas``."""
    m = get_model(model)
    sim = FixedMasks(m, masks_to_tensor(masks, device), support_px=support)
    if meas is not None:
        sim, m = MeasuredMasks(sim, meas), MeasuredModel(m, meas)
    objs: dict[int, Objective] = {}

    def obj(f):
        if f not in objs:
            objs[f] = build_objective(sim, prints, f, s["objective"], s["area_floor"])
        return objs[f]

    return m, sim, obj


def _refit_context(model: str, masks, prints, support: float, meas, device, s: dict, space: Space, values: dict,
                   f_ga: int, f_ref: int) -> dict:
    """What a refit of the folds and the bootstrap needs (``fitting._refit``), built from
    inputs that pickle: in a worker process (``fitting.Refits``) it is built from them as
    the calibration built its own."""
    m, _, obj = _objectives(model, masks, prints, support, meas, device, s)
    return dict(space=space, model=m, obj=obj, f_ga=f_ga, f_ref=f_ref, device=device, s=s, values=values)


def _recorded(data: PrintSet) -> list:
    """Each prints folder's measurement record (registration.yaml ``measurement``), None
    where it has none."""
    out = []
    for d in data.prints_dirs:
        f = Path(d) / "registration.yaml"
        rec = (read_yaml(f) or {}).get("measurement") if f.is_file() else None
        out.append(rec if isinstance(rec, dict) else None)
    return out


def _measurement(setting, data: PrintSet) -> Measurement | None:
    """The measurement stage of a calibration (setting ``measurement``): a Measurement as
    given, none, or what the prints' registrations record (registration.yaml; several
    registrations: their mean numbers, one level). None where no registration recorded one."""
    if setting is None or setting in ("none", "auto"):  # auto: the first fit without it (``_calibrate`` may switch)
        return None
    if isinstance(setting, Measurement):
        return setting
    if setting != "registration":
        raise ValueError(f"measurement must be 'auto', 'registration', 'none' or a Measurement, got {setting!r}")
    found, missing = [], []
    for d, rec in zip(data.prints_dirs, _recorded(data)):
        mm = from_registration({"measurement": rec})
        (found if mm is not None else missing).append(mm if mm is not None else d)
    if not found:
        return None
    if missing:
        raise InputError(Path(missing[0]), "records no measurement (registration.yaml) while the other prints folders do; "
                         "calibrate them apart, or set the calibration's measurement to 'none'")
    if len({m.level for m in found}) > 1:
        raise InputError(Path(data.prints_dirs[0]), "the registrations thresholded at different levels; calibrate them apart")
    if len({m.fit_blur for m in found}) > 1:
        raise InputError(Path(data.prints_dirs[[m.fit_blur for m in found].index(True)]) / "registration.yaml",
                         "records no microscope blur stated by its batch (batch.yaml microscope_blur_um) while the other "
                         "prints folders do; state it for every batch, or for none")
    mean = {k: float(np.mean([getattr(m, k) for m in found])) for k in ("blur_px", "smoothing_px", "gel_share")}
    return Measurement(level=found[0].level, fit_blur=found[0].fit_blur, **mean)


def _simulated(m, full: Objective, values, device) -> np.ndarray:
    with torch.no_grad():
        return full.sim.prints(m.theta(values, device))[0].cpu().numpy()


# -------------------------------------------------------------------------- figures


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


__all__ = ["calibrate", "load_prints", "PrintSet", "fit_figure", "simulate_dir"]
