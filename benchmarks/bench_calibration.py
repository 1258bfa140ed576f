"""Benchmark of the calibration (not a test): speed, and the effect of sampling.

    python benchmarks/bench_calibration.py [--prints DIR] [--quick]

Prints
1. objective evaluations per second (one evaluation = one parameter set over all prints)
   for the fast evaluator (precomputed spectra, batched population) at the GA's,
   the refinement's and full sampling, and for a plain per-mask spatial-domain
   implementation (scipy.ndimage.gaussian_filter per mask per individual);
2. the wall time of a full calibration (GA + refinement) on 32 prints at 512 x 512, the
   same extrapolated for the plain implementation, and the time of CV and bootstrap;
3. the sampling check: GA and refinement optima when the objective uses every 4th,
   every 2nd or every pixel.

Without --prints it makes 32 trial prints with the virtual lab, its effects beyond Eq. 1
switched off, so the true parameters are known.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

from unscatter.calibration import DEFAULTS, calibrate
from unscatter.prints import load_prints
from unscatter.fitting import Objective, Space, refine, run_ga
from unscatter.io import read_yaml, write_png, write_tsv, write_yaml
from unscatter.masks import trial_masks
from unscatter.model import FixedMasks, default_params, design_coords, eq1, masks_to_tensor

EQ1_LAB = {"printer": {"kernel": {"heavy_tail": None, "anisotropy": {"ratio": 1.0, "angle_deg": 0.0}},
                       "illumination": {"quartic": 0.0, "hotspot": None}, "dose_gamma": 1.0, "edge_offset_um": 0.0}}


def lab_prints(out: Path, count=32, size=512) -> dict:
    """Registration-output-like folder of virtual-lab prints; returns the true parameters."""
    from unscatter.lab import Printer, load_config

    cfg = load_config(overrides=EQ1_LAB)
    px = cfg["batch"]["pixel_size_um"]
    printer = Printer(cfg["printer"], size, px)
    rows = []
    for i, (mid, m) in enumerate(trial_masks(count, seed=0, size=size).items()):
        pr = printer.crop(printer.density(m, np.random.default_rng([1, i]))) >= cfg["microscope"]["level"]
        write_png(out / "masks" / f"{mid}.png", m)
        write_png(out / f"{mid}.png", pr)
        rows.append(dict(id=mid, status="ok" if pr.any() else "empty", reason="", mask=f"masks/{mid}.png"))
    write_tsv(out / "qc.tsv", rows, ["id", "status", "reason", "mask"])
    write_yaml(out / "batch.yaml", dict(pixel_size_um=px))
    il, pc = cfg["printer"]["illumination"], cfg["printer"]
    return dict(c0=1.0, c1=il["cx2"], c2=il["cy2"], c3=il["cx"], c4=il["cy"], sigma_px=pc["kernel"]["sigma_um"] / px,
                T=pc["cure"]["threshold"])


def plain_objective(masks: np.ndarray, prints: np.ndarray, v: dict) -> float:
    """Eq. 1 per mask in the spatial domain (the straightforward implementation)."""
    H, W = masks.shape[1:]
    X = design_coords(W).double().numpy()[None, :]
    Y = design_coords(H).double().numpy()[:, None]
    field = np.maximum(v["c0"] + v["c1"] * X**2 + v["c2"] * Y**2 + v["c3"] * X + v["c4"] * Y, 0)
    err = 0.0
    for m, p in zip(masks, prints):
        dose = ndimage.gaussian_filter(field * (m / 255.0), v["sigma_px"], mode="constant")
        err += np.mean((dose >= v["T"]) != p)
    return err / len(masks)


def timed(fn, *a, **k):
    t = time.perf_counter()
    c = os.times()
    out = fn(*a, **k)
    e = os.times()
    return out, time.perf_counter() - t, (e.user - c.user) + (e.system - c.system)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--prints", type=Path, help="a registration output folder (default: virtual-lab prints)")
    ap.add_argument("--quick", action="store_true", help="fewer repetitions and a shorter sampling check")
    args = ap.parse_args()
    torch.manual_seed(0)
    tmp = Path(tempfile.mkdtemp(prefix="bench_calibration_"))
    truth = None
    if args.prints:
        pdir = args.prints
    else:
        pdir = tmp / "prints"
        truth, dt, _ = timed(lab_prints, pdir)
        print(f"virtual lab: 32 trial prints at 512x512 in {dt:.1f} s; true Eq. 1 parameters: "
              + ", ".join(f"{k}={v:.4g}" for k, v in truth.items()))
    default_threads = torch.get_num_threads()
    torch.set_num_threads(DEFAULTS["threads"] or default_threads)  # as calibrate() runs
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s) (calibration default; torch's: {default_threads}), "
          f"{os.cpu_count()} CPUs; wall times on a shared machine vary")

    data = load_prints([pdir])
    B, H, W = data.masks.shape
    m = eq1()
    params = default_params()
    space = Space(params)
    support = m.support_px({k: hi for k, (lo, hi) in params.bounds.items()})
    sim, dt, _ = timed(FixedMasks, m, masks_to_tensor(data.masks, "cpu"), support)
    print(f"\nprecomputed spectra of {len(sim.basis_names)} basis images x {B} masks on a {sim.full_shape} grid in {dt:.2f} s")

    # -- 1. evaluations per second ----------------------------------------------------
    rng = np.random.default_rng(0)
    P = 48
    pop = space.decode(rng.random((P, len(space.names))))
    theta = m.theta(pop, "cpu")
    reps = 2 if args.quick else 4
    print(f"\n1. objective evaluations per second ({B} prints of {H}x{W}, population of {P}; best of {reps} passes,"
          " since other processes only ever slow a pass down)")
    rates = {}
    for f in (4, 2, 1):
        obj = Objective.build(sim, data.prints, f)
        obj.hard(theta)  # warm up
        dt, cpu = min(timed(obj.hard, theta)[1:] for _ in range(reps))
        rates[f] = P / dt
        nth = {1: "pixel   ", 2: "2nd pixel", 4: "4th pixel"}[f]
        print(f"   fast, every {nth} ({(H + f - 1) // f}x{(W + f - 1) // f} samples): "
              f"{rates[f]:8.1f} evals/s  ({1000 / rates[f]:.1f} ms/eval, CPU {1000 * cpu / P:.1f} ms/eval)")
    obj = Objective.build(sim, data.prints, 4)
    before = torch.get_num_threads()
    for n in sorted({1, default_threads}):
        torch.set_num_threads(n)
        dt, _ = min(timed(obj.hard, theta)[1:] for _ in range(reps))
        print(f"   fast, every 4th pixel, {n} thread{'s' if n > 1 else ''}: {P / dt:8.1f} evals/s")
    torch.set_num_threads(before)
    n_plain = 2 if args.quick else 3
    one = {k: v[0] for k, v in pop.items()}
    dt, cpu = min(timed(plain_objective, data.masks, data.prints, one)[1:] for _ in range(n_plain))
    rate_plain = 1 / dt
    print(f"   plain, scipy gaussian_filter per mask, every pixel:       {rate_plain:8.2f} evals/s  ({1000 / rate_plain:.0f} ms/eval)")
    print(f"   speed-up: {rates[1] / rate_plain:.1f}x at equal sampling, {rates[4] / rate_plain:.0f}x as the GA runs (every 4th pixel)")

    # -- 2. calibration wall time --------------------------------------------------------
    print("\n2. calibration wall time")
    out = tmp / "fit"
    p, dt, cpu = timed(calibrate, [pdir], out, seed=0, folds=0, bootstrap=0, progress=False)
    fit_s = p.info["fit"]["seconds"]
    hist = read_yaml(out / "params.yaml")
    nevals = sum(int(line.split("\t")[1]) for line in (out / "history.tsv").read_text().splitlines()[1:])
    print(f"   calibrate(): {dt:.1f} s in all (CPU {cpu:.1f} s); GA + refinement {fit_s:.1f} s, {nevals} GA evaluations"
          f" (population {DEFAULTS['population']}, {DEFAULTS['generations']} generations)")
    print(f"   plain implementation, same GA (extrapolated from its evals/s): {nevals / rate_plain:.0f} s "
          f"= {nevals / rate_plain / fit_s:.0f}x the fast GA + refinement")
    v = p.values
    line = ", ".join(f"{k}={v[k]:.4g}" for k in space.names)
    print(f"   fit: {line}; objective {hist['objective']['value']:.5f}")
    if truth:
        print(f"   recovery: sigma {100 * (v['sigma_px'] / truth['sigma_px'] - 1):+.2f} %, T {100 * (v['T'] / truth['T'] - 1):+.2f} %")
    out2 = tmp / "fit_cv"
    p2, dt, _ = timed(calibrate, [pdir], out2, seed=0, progress=False, residual_maps=False, figure=False)
    val, unc = p2.info["validation"], p2.info["uncertainty"]
    print(f"   with {val['folds']}-fold CV and {unc['replicates']} bootstrap replicates: {dt:.1f} s in all "
          f"(CV {val['seconds']:.1f} s, bootstrap {unc['seconds']:.1f} s); held-out IoU {val['heldout_iou_mean']:.4f}, "
          f"in-sample {val['in_sample_iou_mean']:.4f}")
    d2 = read_yaml(out2 / "params.yaml")["parameters"]
    print("   bootstrap std: " + ", ".join(f"{k} {d2[k]['std']:.3g}" for k in space.names))

    # -- 3. sampling check -----------------------------------------------------------------
    gens = DEFAULTS["generations"]
    ga_factors = (4, 2) if args.quick else (4, 2, 1)  # the GA on every pixel takes minutes
    print(f"\n3. sampling check: GA (seed 0, population {DEFAULTS['population']}, {gens} generations) and refinement "
          "with the objective on every f-th pixel; every objective value below is on every pixel")
    full = Objective.build(sim, data.prints, 1)
    ga_best = {}
    for f in ga_factors:
        obj = Objective.build(sim, data.prints, f)
        (best, _, _), dt, _ = timed(run_ga, space, obj, m, "cpu", 0, DEFAULTS["population"], gens, progress=False)
        ga_best[f] = best
        print(f"   GA, every {f}: {dt:6.1f} s  " + ", ".join(f"{k}={best[k]:.4g}" for k in space.names)
              + f"  objective {full.hard(m.theta(best, 'cpu'))[0]:.5f}")
    start = ga_best[4]
    ref = {}
    for f in (4, 2, 1):
        obj = Objective.build(sim, data.prints, f)
        r, dt, _ = timed(refine, space, obj, m, start, "cpu", DEFAULTS["temperatures"], DEFAULTS["refine_iters"])
        ref[f] = r
        print(f"   refinement from the every-4 GA optimum, every {f}: {dt:5.1f} s  "
              + ", ".join(f"{k}={r[k]:.4g}" for k in space.names) + f"  objective {full.hard(m.theta(r, 'cpu'))[0]:.5f}")
    for f in (4, 2):
        ds = 100 * (ref[f]["sigma_px"] / ref[1]["sigma_px"] - 1)
        dT = 100 * (ref[f]["T"] / ref[1]["T"] - 1)
        dc = max(abs(ref[f][k] - ref[1][k]) for k in ("c1", "c2", "c3", "c4"))
        print(f"   refined optimum, every {f} vs every pixel: sigma {ds:+.2f} %, T {dT:+.2f} %, max |dc| {dc:.4f}")
    print(f"\n(outputs kept in {tmp})")


if __name__ == "__main__":
    main()
