"""Print budget: how many trial prints a calibration needs, random paper masks against
designed ones (not a test).

    python benchmarks/bench_print_budget.py --labs N [--counts 4,8,16,32] [--seed S] [--full]

For each of N labs drawn with ``unscatter.lab.random_lab`` (optics, camera, printer and
its effects over wide ranges; a new seed each run, printed, ``--seed`` repeats it):

1. 32 random paper trial masks (``masks.trial_masks``) and 32 designed ones
   (``design.design_masks``: greedy, so its first n are the n-mask design; designed
   without knowing the lab), and held-out masks (test patterns and paper masks), are
   printed and imaged on the lab in one batch and registered as the workflow does
   (failed prints are skipped: a print lost to QC is a print paid for and lost); the
   registration is scored against the lab's true transforms: prints used although
   silently wrong, and failed prints that were in fact within 1.5 px. With
   ``--paper-fiducials`` the paper's masks carry the designed masks' registration marks
   too (``masks.with_fiducials``), so that the two kinds lose prints to registration alike;
2. for each kind and each n of ``--counts``, Eq. 1 is calibrated on the prints of the
   first n masks (``--full``: the workflow's GA 48 x 30; default: GA 24 x 10, no CV);
3. the calibrated model prints the held-out masks; its IoU against the lab's true
   prints (mask coordinates: the batch's truth and ``bench_diagnosis.TRUTH_DRAWS`` - 1
   more prints of each mask by the lab's printer, the mean over them; one print before
   2026-12-06) is the score, with the fitted sigma against the lab's own.

With ``--effects`` (for instance ``none,heavy_tail,anisotropy,dose_nonlinearity,
illumination_field,edge_offset,outside``) each lab has one effect beyond Eq. 1 (or none,
or physics outside the library), drawn as the diagnosis benchmark draws them
(``bench_diagnosis.random_effect_lab``, with this lab's random optics), every effect once
per round. With ``--diagnose`` the residual diagnosis (quick settings) follows each
calibration on the same prints: the effect it names against the lab's (right, wrong,
missed, false alarm: ``bench_diagnosis.verdict``) and the selected model's held-out IoU,
against n, for both kinds of trial masks.

With ``--sequential`` (needs ``--diagnose``) a third kind, ``sequential``, is measured:
the first count's designed prints, then at each next count the masks that
``design.design_masks`` proposes from the last diagnosis (its fit and spread as the
prior, the prints made so far adding their information, the effects it could not decide
on weighted; ``unscatter masks design --model DIAG --prints REG``), printed on the same
lab as a new batch (new noise, new poses), registered, and calibrated and diagnosed with
the earlier prints.

Writes ``budget.tsv`` (a row per lab, kind, n), ``labs.yaml``, ``summary.txt`` and
``budget.png`` (held-out IoU against n) under ``--out``.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
import bench_diagnosis  # noqa: E402 (the one-effect labs and the verdicts of the diagnosis benchmark)
import bench_registration  # noqa: E402 (the registration scored against the lab's true transforms)


def _substream(seed: int, lab: int, what: int) -> int:
    return int(np.random.default_rng([seed, lab, what]).integers(2**31))


class LabRun(NamedTuple):
    """One lab of the run: where its files go, its printer and effect, the held-out masks
    and the lab's true prints of them."""

    i: int
    seed: int
    d: Path
    over: dict
    effect: str | None
    held_masks: np.ndarray
    truth: list
    lab_sigma_px: float

    def sub(self, what: int) -> int:
        return _substream(self.seed, self.i, what)


def _subset(reg: Path, ids: list, out: Path) -> int:
    """A registration folder holding only the prints of ``ids`` (failed ones stay out)."""
    from unscatter.io import read_tsv, write_tsv

    out.mkdir(parents=True)
    shutil.copy(reg / "batch.yaml", out / "batch.yaml")
    rows = []
    for r in read_tsv(reg / "qc.tsv"):
        if r["id"] in ids and r["status"] != "failed":
            m = Path(r["mask"])
            r["mask"] = str(m if m.is_absolute() else (reg / m).resolve())
            shutil.copy(reg / f"{r['id']}.png", out / f"{r['id']}.png")
            rows.append(r)
    write_tsv(out / "qc.tsv", rows)
    return len(rows)


def run_lab(i: int, seed: int, a, root: Path) -> tuple[dict, list[dict]]:
    from unscatter.design import design_masks
    from unscatter.imaging import register_batch
    from unscatter.io import read_print, write_png
    from unscatter.lab import Printer, load_config, print_batch, random_lab
    from unscatter.lab.random import describe_lab
    from unscatter.masks import test_pattern_masks, trial_masks, with_fiducials

    d = root / f"lab{i:02d}"
    over = random_lab(np.random.default_rng(_substream(seed, i, 0)))
    effect, magnitude = None, None
    if a.effects:
        effect = a.order[i]
        # the same draw as random_lab's above: its optics, the printer with this one effect
        fx, magnitude = bench_diagnosis.random_effect_lab(np.random.default_rng(_substream(seed, i, 0)), effect, a.strength)
        over = dict(over, printer=fx["printer"])
    top = max(a.counts)
    t0 = time.perf_counter()
    design = design_masks(top, pool=a.pool, draws=a.draws, seed=_substream(seed, i, 1), fiducials=a.fiducials,
                          criterion=a.criterion, progress=False, compare=False)
    t_design = time.perf_counter() - t0
    kinds = {
        "paper": [with_fiducials(m) if a.paper_fiducials else m for m in trial_masks(top, seed=_substream(seed, i, 2)).values()],
        "designed": list(design["masks"].values()),
    }
    held = list(test_pattern_masks(a.heldout, seed=_substream(seed, i, 3)).values())
    held += list(trial_masks(a.heldout // 2, seed=_substream(seed, i, 4)).values())
    ids = {k: [f"{k}_{j:03d}" for j in range(len(v))] for k, v in kinds.items()}
    ids["held"] = [f"held_{j:03d}" for j in range(len(held))]
    for k, v in [*kinds.items(), ("held", held)]:
        for mid, m in zip(ids[k], v):
            write_png(d / "masks" / f"{mid}.png", m)
    print_batch(d / "masks", d / "batch", overrides=over, seed=_substream(seed, i, 5), progress=False)
    t1 = time.perf_counter()
    qc = register_batch(d / "batch", d / "reg", skip_failed=True, progress=False)
    t_reg = time.perf_counter() - t1
    failed = {r["id"] for r in qc if r["status"] == "failed"}
    silent, close = registration_truth(d / "reg", d / "batch.truth")
    held_masks = np.stack(held)
    cfg = load_config(overrides=over)
    # the batch's print of each held-out mask and more prints of it (``held_out_iou``)
    more, _ = bench_diagnosis.held_out_truth(Printer(cfg["printer"], held_masks.shape[-1], float(cfg["batch"]["pixel_size_um"])),
                                             float(cfg["microscope"]["level"]), dict(zip(ids["held"], held)),
                                             _substream(seed, i, 8), votes=0)
    truth = [[read_print(d / "batch.truth" / "prints" / f"{mid}.png"), *more[mid][1:]] for mid in ids["held"]]
    lab_sigma_px = cfg["printer"]["kernel"]["sigma_um"] / float(cfg["batch"]["pixel_size_um"])
    lab = dict(lab=i, describe=describe_lab(over), effect=effect, magnitude=magnitude, overrides=over, failed=sorted(failed),
               design_s=round(t_design, 1), register_s=round(t_reg, 1), lab_sigma_px=lab_sigma_px,
               silently_wrong=silent, failed_within_1_5px=close)
    run = LabRun(i, seed, d, over, effect, held_masks, truth, lab_sigma_px)
    rows = []
    for kind in kinds:
        for n in a.counts:
            sub = d / f"{kind}_{n:02d}"
            used = _subset(d / "reg", ids[kind][:n], sub)
            row = dict(lab=i, kind=kind, n=n, prints_used=used)
            if used:
                row.update(_fit_and_score(run, a, sub, kind, n))
            rows.append(_report(run, row))
    if a.sequential:
        rows += _sequential(run, a)
    return lab, rows


def _report(run: LabRun, row: dict) -> dict:
    i, lab_sigma_px = run.i, run.lab_sigma_px
    print(f"  lab {i} {row['kind']:10s} n={row['n']:2d} used {row['prints_used']:2d}  IoU {row.get('heldout_iou', float('nan')):.4f}  "
          f"sigma {row.get('sigma_px', float('nan')):.2f} (lab {lab_sigma_px:.2f})  {row.get('error', '')}"
          + (f"  named {row['named']} ({row['verdict']}), selected IoU {row['heldout_iou_selected']:.4f}"
             if "heldout_iou_selected" in row else ""), flush=True)
    return row


def _sequential(run: LabRun, a) -> list[dict]:
    """The sequential kind: the first count's designed prints (already diagnosed as
    ``diag_designed_NN``), then at each next count the masks the last diagnosis proposes,
    printed on the lab as a new batch, registered, and calibrated and diagnosed with the
    prints so far."""
    from unscatter.design import design_masks
    from unscatter.imaging import register_batch
    from unscatter.io import write_png
    from unscatter.lab import print_batch

    d, n0 = run.d, a.counts[0]
    folders = [d / f"designed_{n0:02d}"]
    diag, cal = d / f"diag_designed_{n0:02d}", d / f"cal_designed_{n0:02d}"
    have, rows = n0, []
    for step, n in enumerate(a.counts[1:], 1):
        row = dict(lab=run.i, kind="sequential", n=n)
        # from the diagnosis; where it could not be made (too few prints), from the calibration
        if (diag / "model.yaml").is_file():
            model, row["designed_from"] = diag, "diagnosis"
        elif (cal / "params.yaml").is_file():
            model, row["designed_from"] = cal / "params.yaml", "calibration"
        else:
            rows.append(_report(run, dict(row, prints_used=0, error="no calibration to design from")))
            break
        t0 = time.perf_counter()
        new = design_masks(n - have, model=model, prints=folders, pool=a.pool, draws=a.draws,
                           seed=run.sub(10 + step), fiducials=a.fiducials, criterion=a.criterion, progress=False,
                           compare=False)["masks"]
        t_design = time.perf_counter() - t0
        step_dir = d / f"sequential_{n:02d}"
        for j, m in enumerate(new.values()):
            write_png(step_dir / "masks" / f"seq{step}_{j:03d}.png", m)
        print_batch(step_dir / "masks", step_dir / "batch", overrides=run.over, seed=run.sub(20 + step), progress=False)
        qc = register_batch(step_dir / "batch", step_dir / "reg", skip_failed=True, progress=False)
        silent, _ = registration_truth(step_dir / "reg", step_dir / "batch.truth")
        row["silently_wrong_new"] = ",".join(silent)
        folders.append(step_dir / "reg")
        have = n
        used = _usable(folders)
        row.update(prints_used=used, failed_new=sum(r["status"] == "failed" for r in qc), design_s=round(t_design, 1))
        row.update(_fit_and_score(run, a, folders, "sequential", n))
        rows.append(_report(run, row))
        if "error" in row:
            break
        diag, cal = d / f"diag_sequential_{n:02d}", d / f"cal_sequential_{n:02d}"
    return rows


def _fit_and_score(run: LabRun, a, prints, kind: str, n: int) -> dict:
    """Eq. 1 calibrated on ``prints`` (``cal_KIND_NN``; ``--full``: the workflow's GA 48 x 30,
    default GA 24 x 10, no CV) and scored on the held-out masks; with ``--diagnose`` the
    diagnosis after it (``diag_KIND_NN``)."""
    from unscatter.calibration import calibrate
    from unscatter.model import simulate

    fit = dict(population=48, generations=30, folds=0, bootstrap=0) if a.full else \
        dict(population=24, generations=10, folds=0, bootstrap=0)
    t0 = time.perf_counter()
    cal = run.d / f"cal_{kind}_{n:02d}"
    try:
        p = calibrate(prints, cal, seed=run.sub(6), progress=False, residual_maps=False, figure=False,
                      threads=1, **fit)
    except Exception as exc:  # noqa: BLE001 (a calibration that cannot be made is a result)
        return dict(error=" ".join(str(exc).split())[:120])
    mean, pooled = held_out_iou(simulate(p, run.held_masks), run.truth)
    row = dict(heldout_iou=mean, heldout_iou_pooled=pooled, sigma_px=float(p.values["sigma_px"]),
               sigma_rel_err=float(p.values["sigma_px"] / run.lab_sigma_px - 1), T=float(p.values["T"]),
               calibrate_s=round(time.perf_counter() - t0, 1))
    if a.diagnose:
        row.update(_diagnosis(prints, cal / "params.yaml", run.d / f"diag_{kind}_{n:02d}", run.effect, run.held_masks,
                              run.truth, run.sub(7)))
    return row


def _usable(folders: list) -> int:
    """Prints not failed in registration folders."""
    from unscatter.io import read_tsv

    return sum(r["status"] != "failed" for f in folders for r in read_tsv(Path(f) / "qc.tsv"))


def registration_truth(reg: Path, truth: Path) -> tuple[list[str], int]:
    """The registration against the lab's true transforms (``bench_registration``): the
    prints that went into the budget silently wrong (ok with the pose more than 1.5 px
    off, or empty where the truth printed) and how many failed prints were in fact
    within 1.5 px (the budget QC cost without need)."""
    rows = bench_registration.evaluate(reg, truth)
    close = sum(r["status"] == "failed" and r.get("rms_px", np.inf) <= bench_registration.SILENT_POSE_PX for r in rows)
    return [r["id"] for r in rows if bench_registration.silently_wrong(r)], int(close)


def held_out_iou(sim, truth: list) -> tuple[float, float]:
    """A model's held-out prints against the lab's (``truth``: a list of the lab's prints
    for each mask): the mean of per-mask IoU and the IoU pooled over the masks
    (``metrics.pooled_iou``), each the mean over the lab's prints (``bench_diagnosis.scored``)."""
    ids = list(range(len(truth)))
    per_mask, pooled = bench_diagnosis.scored({"model": sim}, dict(zip(ids, truth, strict=True)), ids)
    return float(np.mean([v["model"] for v in per_mask.values()])), pooled["model"]


def _diagnosis(prints, params: Path, out: Path, effect, held_masks, truth: list, seed: int) -> dict:
    """The residual diagnosis (quick settings) on a calibration's prints: what it named, its
    verdict against the lab's effect (None: the lab's effects are many, no verdict) and the
    selected model's held-out IoU."""
    from unscatter.diagnosis import diagnose
    from unscatter.model import load_params, simulate

    t0 = time.perf_counter()
    try:
        r = diagnose([prints] if isinstance(prints, Path) else prints, params, out, quick=True, seed=seed, progress=False, figures=False, threads=1)
    except Exception as exc:  # noqa: BLE001 (a diagnosis that cannot be made is a result)
        return dict(named="error", verdict="error", diagnose_error=" ".join(str(exc).split())[:120])
    mean, pooled = held_out_iou(simulate(load_params(out / "model.yaml"), held_masks), truth)
    return dict(named=",".join(r["effects"]) or "-", unexplained=bool(r["unexplained_residual"]),
                verdict=bench_diagnosis.verdict(effect, r["effects"], r["unexplained_residual"]) if effect else "-",
                heldout_iou_selected=mean, heldout_iou_selected_pooled=pooled,
                diagnose_s=round(time.perf_counter() - t0, 1))


def _median(rows, kind, n, key) -> str:
    v = [r[key] for r in rows if r["kind"] == kind and r["n"] == n and key in r]
    return f"{np.median(v):.4f}" if v else "-"


def _kinds(rows) -> list[str]:
    return [k for k in ("paper", "designed", "sequential") if any(r["kind"] == k for r in rows)]


def detection_lines(labs, rows, counts) -> list[str]:
    """Verdicts of the diagnosis against n, per kind of trial masks."""
    verdicts = (*bench_diagnosis.VERDICTS, "error")
    kinds = _kinds(rows)
    L = ["", "effect named (diagnosis, quick settings) against the number of prints: "
         + "/".join(verdicts) + "; selected model's held-out IoU, median (pooled)",
         f"{'n':>4} " + " ".join(f"{k:>36}" for k in kinds)]
    for n in counts:
        cells = []
        for kind in kinds:
            rr = [r for r in rows if r["kind"] == kind and r["n"] == n and "verdict" in r]
            c = [sum(r["verdict"] == v for r in rr) for v in verdicts]
            cells.append(("/".join(map(str, c)) + f"  {_median(rows, kind, n, 'heldout_iou_selected')} "
                          f"({_median(rows, kind, n, 'heldout_iou_selected_pooled')})") if rr else "-")
        L.append(f"{n:>4} " + " ".join(f"{c:>36}" for c in cells))
    L.append("per lab (effect: named at each n, " + " | ".join(kinds) + "):")
    for lab in labs:
        parts = [" ".join(f"{r['n']}:{r.get('named', '?')}" for r in rows if r["lab"] == lab["lab"] and r["kind"] == kind)
                 for kind in kinds]
        L.append(f"  lab {lab['lab']} {lab.get('effect')} ({lab.get('magnitude')}): " + " | ".join(parts))
    return L


def summarize(seed, labs, rows, counts, cmd) -> str:
    kinds = _kinds(rows)
    L = [f"print budget: {cmd}", f"seed {seed}, {len(labs)} labs", ""]
    for lab in labs:
        L.append(f"lab {lab['lab']}: {lab['describe']}")
        L.append(f"   registration failed {len(lab['failed'])} ({lab['failed_within_1_5px']} of them within 1.5 px of the "
                 f"truth): {', '.join(lab['failed']) or '-'}; silently wrong (used as good) "
                 f"{len(lab['silently_wrong'])}: {', '.join(lab['silently_wrong']) or '-'}; "
                 f"design {lab['design_s']} s, registration {lab['register_s']} s")
    if labs:
        L.append(f"registration, all labs: failed {sum(len(x['failed']) for x in labs)} ("
                 f"{sum(x['failed_within_1_5px'] for x in labs)} within 1.5 px of the truth), silently wrong "
                 f"{sum(len(x['silently_wrong']) for x in labs)} (in the first batch; sequential batches: budget.tsv)")
    L += ["", "Eq. 1's held-out IoU against the lab's true prints: median over labs of the IoU pooled over the "
          "held-out masks (metrics.pooled_iou) [min, max], the median of the per-mask mean, |sigma error| median",
          f"{'n':>4} " + " ".join(f"{k + ' pooled':>26} {'mean':>7} {'|sig err|':>9}" for k in kinds)]
    for n in counts:
        cells = []
        for kind in kinds:
            v = [r["heldout_iou_pooled"] for r in rows if r["kind"] == kind and r["n"] == n and "heldout_iou_pooled" in r]
            e = [abs(r["sigma_rel_err"]) for r in rows if r["kind"] == kind and r["n"] == n and "sigma_rel_err" in r]
            cells.append(f"{np.median(v):.4f} [{min(v):.4f}, {max(v):.4f}]".rjust(26) if v else "-".rjust(26))
            cells.append(f"{_median(rows, kind, n, 'heldout_iou'):>7} {(f'{np.median(e):.3f}' if e else '-'):>9}")
        L.append(f"{n:>4} " + " ".join(cells))
    L.append("")
    for other in kinds[1:]:
        for n in counts:
            w = []
            for lab in labs:
                by = {r["kind"]: r["heldout_iou_pooled"] for r in rows
                      if r["lab"] == lab["lab"] and r["n"] == n and "heldout_iou_pooled" in r}
                if "paper" in by and other in by:
                    w.append(by[other] > by["paper"])
            if w:
                L.append(f"n={n}: {other} better than paper (pooled) in {sum(w)} of {len(w)} labs")
    top = max(counts)
    for other in kinds[1:]:
        for n in [m for m in counts[:-1] if any(r["kind"] == other and r["n"] == m for r in rows)]:
            L.append(f"{other} n={n} vs paper n={top} pooled: {_median(rows, other, n, 'heldout_iou_pooled')} "
                     f"vs {_median(rows, 'paper', top, 'heldout_iou_pooled')}; right named: "
                     f"{_right(rows, other, n)} vs {_right(rows, 'paper', top)}")
    if any("verdict" in r for r in rows):
        L += detection_lines(labs, rows, counts)
    return "\n".join(L)


def _right(rows, kind, n) -> str:
    rr = [r for r in rows if r["kind"] == kind and r["n"] == n and "verdict" in r]
    return f"{sum(r['verdict'] == 'right' for r in rr)} of {len(rr)}" if rr else "-"


def figure(rows, counts, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for kind, c in (("paper", "tab:gray"), ("designed", "tab:blue"), ("sequential", "tab:orange")):
        for lab in sorted({r["lab"] for r in rows}):
            pts = [(r["n"], r["heldout_iou_pooled"]) for r in rows
                   if r["kind"] == kind and r["lab"] == lab and "heldout_iou_pooled" in r]
            if pts:
                ax.plot(*zip(*pts), color=c, alpha=0.3, lw=0.8)
        med = []
        for n in counts:
            v = [r["heldout_iou_pooled"] for r in rows if r["kind"] == kind and r["n"] == n and "heldout_iou_pooled" in r]
            if v:
                med.append((n, np.median(v)))
        if med:
            ax.plot(*zip(*med), "o-", color=c, lw=2, label=f"{kind} (median)")
    ax.set_xscale("log", base=2)
    ax.set_xticks(counts, [str(n) for n in counts])
    ax.set_xlabel("trial prints")
    ax.set_ylabel("Eq. 1's held-out IoU vs the lab's prints (pooled)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--labs", type=int, default=3)
    ap.add_argument("--counts", default="4,8,16,32")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--pool", type=int, default=160)
    ap.add_argument("--draws", type=int, default=3)
    ap.add_argument("--criterion", choices=("d", "discrimination", "paired"), default="d",
                    help="the designed masks' criterion (design.design_masks; d, as the runs in docs/trial-masks.md before "
                         "2026-11-30 had it: unscatter's own default is paired)")
    ap.add_argument("--heldout", type=int, default=16)
    ap.add_argument("--full", action="store_true", help="the workflow's calibration (GA 48 x 30)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "print_budget")
    ap.add_argument("--effects", default=None, help="labs with one effect each, drawn from these (bench_diagnosis: "
                    f"{','.join(bench_diagnosis.RANDOM_EFFECTS)}); default: random_lab's labs, many effects at once")
    ap.add_argument("--strength", choices=("wide", "strong"), default="wide", help="with --effects: their magnitudes")
    ap.add_argument("--no-fiducials", dest="fiducials", action="store_false",
                    help="designed masks without their registration marks (unscatter.masks.fiducial_marks)")
    ap.add_argument("--paper-fiducials", action="store_true",
                    help="the paper's random masks with the registration marks too (trial_masks.paper_fiducials; "
                    "unscatter masks trial --fiducials), so that both kinds are registered alike")
    ap.add_argument("--diagnose", action="store_true", help="the residual diagnosis after each calibration")
    ap.add_argument("--sequential", action="store_true", help="with --diagnose: the next masks designed from the "
                    "last diagnosis, count by count, printed as new batches")
    a = ap.parse_args(argv)
    if a.sequential and not a.diagnose:
        ap.error("--sequential designs from the diagnosis: give --diagnose too")
    a.counts = sorted(int(x) for x in a.counts.split(","))
    logging.basicConfig(level=logging.WARNING)
    import torch

    torch.set_num_threads(1)
    seed = a.seed if a.seed is not None else int(np.random.default_rng().integers(2**31))
    if a.effects:
        effects = a.effects.split(",")
        unknown = [e for e in effects if e not in bench_diagnosis.RANDOM_EFFECTS and e not in bench_diagnosis.OUTSIDE]
        if unknown:
            ap.error(f"--effects: unknown {unknown}")
        rng = np.random.default_rng([seed, 99])
        a.order = []
        while len(a.order) < a.labs:  # every effect once per round, shuffled
            a.order += [effects[j] for j in rng.permutation(len(effects))]
    cmd = " ".join(["python benchmarks/bench_print_budget.py", *(argv if argv is not None else sys.argv[1:])])
    print(f"seed {seed} (repeat with --seed {seed})", flush=True)
    from unscatter.io import InputError, benchmark_output_dir, write_tsv, write_yaml

    try:
        a.out = benchmark_output_dir(a.out, script="benchmarks/bench_print_budget.py")
    except InputError as exc:
        ap.error(str(exc))
    labs, rows = [], []

    for i in range(a.labs):
        lab, r = run_lab(i, seed, a, a.out)
        labs.append(lab)
        rows += r
        write_tsv(a.out / "budget.tsv", rows, list(dict.fromkeys(k for r in rows for k in r)))
        write_yaml(a.out / "labs.yaml", dict(seed=seed, labs=labs))
    text = summarize(seed, labs, rows, a.counts, cmd)
    (a.out / "summary.txt").write_text(text + "\n")
    figure(rows, a.counts, a.out / "budget.png")
    print(text)


if __name__ == "__main__":
    main()
