"""Benchmark of the compensation (not a test): time per design and print quality.

    python benchmarks/bench_compensation.py [--params P] [--train-dir D] [--lab] [--quick]

Prints
1. the time of ILT (plain and dose-robust), of the nn mask and of nn+ilt for every test
   design at 512 x 512, with 1 and 2 torch threads (best of --repeats; wall and CPU
   seconds), and the first call of a fresh process (torch and FFT set-up);
2. IoU, EPE and PV band of every method against the identical mask at 100/75/70/50 %
   grey, printed by the simulator (the calibrated model: the optimisation's own model,
   so this is the best case);
3. a sweep over ILT schedules (steps at 1/4, 1/2 and full resolution): time vs quality;
4. with --lab, the same benchmark printed by the virtual lab and measured through
   registration (the lab has effects Eq. 1 lacks: the honest number), the masks carrying
   the registration marks where their designs leave room, as the print job has them.

Without --params it uses a plausible printer (sigma 5 px, T 0.5, a small field tilt).
Without --train-dir it trains a seconds-long 'ci' network: enough to time nn+ilt, not
a compensation by itself (its nn row says so). Outputs: benchmarks/out/compensation/.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the CLI does: idle threads sleep on a shared machine

import numpy as np  # noqa: E402
import torch  # noqa: E402

from unscatter import metrics  # noqa: E402
from unscatter.benchmark import IDENTICAL, run_benchmark, simulator_printer  # noqa: E402
from unscatter.lab.jobs import virtual_lab_printer  # noqa: E402
from unscatter.compensation import ILT_DEFAULTS, NN_ILT_DEFAULTS, compensate, load_printer, optimise_mask  # noqa: E402
from unscatter.io import list_pngs, read_mask, write_png, write_tsv  # noqa: E402
from unscatter.model import default_params, save_params, simulate  # noqa: E402

PLAUSIBLE = dict(c1=-0.06, c2=-0.04, c3=0.03, c4=-0.02, sigma_px=5.0, T=0.5)


def timed(fn, *a, **k):
    t, c = time.perf_counter(), os.times()
    out = fn(*a, **k)
    e = os.times()
    return out, time.perf_counter() - t, (e.user - c.user) + (e.system - c.system)


def best_of(n, fn, *a, **k):
    runs = [timed(fn, *a, **k) for _ in range(n)]
    wall = min(r[1] for r in runs)
    cpu = min(r[2] for r in runs)
    return runs[-1][0], wall, cpu


def tiny_net(params_path: Path, root: Path) -> Path:
    from unscatter.augment import augment
    from unscatter.training import train

    augment(params_path, root / "aug.zarr", count=40, seed=1, size=512, progress=False)
    train(root / "aug.zarr", root / "train", preset="ci", settings=dict(epochs=3), threads=1, progress=False)
    return root / "train"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--params", type=Path, help="params.yaml or a calibration folder (default: a plausible printer)")
    ap.add_argument("--train-dir", type=Path, help="training folder with master.pt (default: a tiny ci net)")
    ap.add_argument("--designs", type=Path, default=Path("data/designs"))
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/compensation"))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--lab", action="store_true", help="also print the benchmark on the virtual lab (~2 min)")
    ap.add_argument("--quick", action="store_true", help="one repeat, two designs, a short sweep")
    a = ap.parse_args()
    out = a.out
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix="bench_compensation_"))
    if a.params is None:
        save_params(tmp / "params.yaml", default_params(pixel_size_um=2.96).with_values(**PLAUSIBLE))
        a.params = tmp / "params.yaml"
    params = load_printer(a.params)
    params_path = a.params / "params.yaml" if a.params.is_dir() else a.params
    px = params.pixel_size_um or 2.96
    tiny = a.train_dir is None
    train_dir = a.train_dir or tiny_net(params_path, tmp)
    designs = {k: read_mask(p) != 0 for k, p in list_pngs(a.designs).items()}
    if a.quick:
        designs = dict(list(designs.items())[:2])
        a.repeats = 1
    print(f"printer: {params.model} {', '.join(f'{k}={v:.4g}' for k, v in params.values.items())}")
    print(f"network: {train_dir}{' (tiny ci net: timing only)' if tiny else ''}")
    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs visible, load average {os.getloadavg()[0]:.1f}")

    # 1. time per design ----------------------------------------------------------
    first = next(iter(designs.values()))
    _, cold, _ = timed(optimise_mask, first, params, threads=1)
    print(f"\n1. time per 512 x 512 design (best of {a.repeats}); first ILT call of this process: {cold:.2f} s")
    print(f"   ILT schedule {ILT_DEFAULTS['schedule']}, nn+ilt schedule {NN_ILT_DEFAULTS['schedule']}")
    rows = []
    masks = {m: {} for m in ("nn", "ilt", "ilt_robust", "nn+ilt")}
    for th in a.threads:
        print(f"   threads={th}: design         ilt (wall/cpu)   ilt robust      nn              nn+ilt (incl. nn)")
        for name, d in designs.items():
            r = dict(threads=th, design=name)
            (m, info), r["ilt_s"], r["ilt_cpu_s"] = best_of(a.repeats, optimise_mask, d, params, threads=th)
            masks["ilt"][name] = m
            m, r["robust_s"], r["robust_cpu_s"] = best_of(a.repeats, compensate, d, "ilt", params_path=params, robust=True, threads=th)
            masks["ilt_robust"][name] = m
            m, r["nn_s"], r["nn_cpu_s"] = best_of(a.repeats, compensate, d, "nn", train_dir=train_dir, threads=th)
            masks["nn"][name] = m
            m, r["nn_ilt_s"], r["nn_ilt_cpu_s"] = best_of(a.repeats, compensate, d, "nn+ilt", params_path=params,
                                                          train_dir=train_dir, threads=th)
            masks["nn+ilt"][name] = m
            rows.append(r)
            print(f"             {name:14s} {r['ilt_s']:5.2f}/{r['ilt_cpu_s']:5.2f} s   {r['robust_s']:5.2f}/{r['robust_cpu_s']:5.2f} s"
                  f"   {r['nn_s']:5.2f}/{r['nn_cpu_s']:5.2f} s   {r['nn_ilt_s']:5.2f}/{r['nn_ilt_cpu_s']:5.2f} s")
        sub = [r for r in rows if r["threads"] == th]
        print(f"             {'mean':14s} {np.mean([r['ilt_s'] for r in sub]):5.2f} s         "
              f"{np.mean([r['robust_s'] for r in sub]):5.2f} s         {np.mean([r['nn_s'] for r in sub]):5.2f} s"
              f"         {np.mean([r['nn_ilt_s'] for r in sub]):5.2f} s")
    write_tsv(out / "timings.tsv", rows)

    # 2. quality on the simulator ---------------------------------------------------
    ddir = tmp / "designs"
    for name, d in designs.items():
        write_png(ddir / f"{name}.png", d)
    res = run_benchmark(ddir, masks, out / "simulator", px, simulator_printer(params))
    print("\n2. printed by the simulator (the optimisation's own model): per design IoU / EPE (um) / PV band (um)")
    _table(res, designs, tiny)

    # 3. schedule sweep ------------------------------------------------------------
    sweep = [((4, 20), (2, 10), (1, 4)), ((4, 40), (2, 20), (1, 8)), ILT_DEFAULTS["schedule"], ((4, 100), (2, 60), (1, 30)),
             ((2, 60), (1, 20)), ((1, 120),)]
    if a.quick:
        sweep = sweep[:3]
    print("\n3. ILT schedules (1 thread): mean time, IoU and EPE over the designs (simulator)")
    srows = []
    for sched in sweep:
        ts, ious, epes = [], [], []
        for name, d in designs.items():
            (m, info), t, _ = timed(optimise_mask, d, params, schedule=sched, threads=1)
            p = simulate(params, m)
            ts.append(t)
            ious.append(metrics.iou(p, d))
            epes.append(metrics.epe_um(p, d, px))
        srows.append(dict(schedule=str(sched), seconds=np.mean(ts), iou=np.mean(ious), epe_um=np.mean(epes)))
        print(f"   {str(sched):34s} {np.mean(ts):5.2f} s  IoU {np.mean(ious):.4f}  EPE {np.mean(epes):.3f} um")
    write_tsv(out / "schedules.tsv", srows)

    # 4. the virtual lab ---------------------------------------------------------------
    if a.lab:
        t = time.perf_counter()
        res = run_benchmark(ddir, masks, out / "lab", px, virtual_lab_printer(tmp / "lab", seed=7),
                            fiducials=True)
        print(f"\n4. printed by the virtual lab, measured through registration ({time.perf_counter() - t:.0f} s)")
        _table(res, designs, tiny)
    print(f"\noutputs: {out}")


def _table(rows, designs, tiny):
    cols = []
    for r in rows:
        c = (r["method"], r["mask_dose"], r["variant"])
        if c not in cols:
            cols.append(c)
    by = {(r["design"], r["method"], r["mask_dose"]): r for r in rows}
    print("   " + f"{'design':14s}" + "".join(f"{c[2] + (' (tiny)' if tiny and c[0] == 'nn' else ''):>22s}" for c in cols))
    for name in designs:
        cells = []
        for method, dose, _ in cols:
            r = by[(name, method, dose)]
            cells.append(f"{r['iou']:.3f}/{r['epe_um']:5.2f}/{r['pv_band_um']:5.2f}" if r["status"] == "ok" else "no print")
        print("   " + f"{name:14s}" + "".join(f"{c:>22s}" for c in cells))
    means = []
    for method, dose, _ in cols:
        ok = [by[(n, method, dose)] for n in designs if by[(n, method, dose)]["status"] == "ok"]
        means.append(f"{np.mean([r['iou'] for r in ok]):.3f}/{np.nanmean([r['epe_um'] for r in ok]):5.2f}/"
                     f"{np.nanmean([r['pv_band_um'] for r in ok]):5.2f}")
    print("   " + f"{'mean':14s}" + "".join(f"{c:>22s}" for c in means))
    best = max((c for c in cols if c[0] != IDENTICAL), key=lambda c: np.mean([by[(n, c[0], c[1])]["iou"] for n in designs]))
    ident = np.mean([by[(n, IDENTICAL, 1.0)]["iou"] for n in designs])
    print(f"   best method by mean IoU: {best[2]} ({np.mean([by[(n, best[0], best[1])]['iou'] for n in designs]):.4f}) "
          f"vs identical 100 % ({ident:.4f})")


if __name__ == "__main__":
    main()
