"""Print budget: how many trial prints a calibration needs, random paper masks against
designed ones (not a test).

    python benchmarks/bench_print_budget.py --labs N [--counts 4,8,16,32] [--seed S] [--full]

For each of N labs drawn with ``unscatter.lab.random_lab`` (optics, camera, printer and
its effects over wide ranges; a new seed each run, printed, ``--seed`` repeats it):

1. 32 random paper trial masks (``masks.trial_masks``) and 32 designed ones
   (``design.design_masks``: greedy, so its first n are the n-mask design; designed
   without knowing the lab), and held-out masks (test patterns and paper masks), are
   printed and imaged on the lab in one batch and registered as the workflow does
   (failed prints are skipped: a print lost to QC is a print paid for and lost);
2. for each kind and each n of ``--counts``, Eq. 1 is calibrated on the prints of the
   first n masks (``--full``: the workflow's GA 48 x 30; default: GA 24 x 10, no CV);
3. the calibrated model prints the held-out masks; its IoU against the lab's true
   prints (mask coordinates, from the lab's truth) is the score, with the fitted sigma
   against the lab's own.

With ``--effects`` (for instance ``none,heavy_tail,anisotropy,dose_nonlinearity,
illumination_field,edge_offset,outside``) each lab has one effect beyond Eq. 1 (or none,
or physics outside the library), drawn as the diagnosis benchmark draws them
(``bench_diagnosis.random_effect_lab``, with this lab's random optics), every effect once
per round. With ``--diagnose`` the residual diagnosis (quick settings) follows each
calibration on the same prints: the effect it names against the lab's (right, wrong,
missed, false alarm: ``bench_diagnosis.verdict``) and the selected model's held-out IoU,
against n, for both kinds of trial masks.

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

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
import bench_diagnosis  # noqa: E402 (the one-effect labs and the verdicts of the diagnosis benchmark)


def _substream(seed: int, lab: int, what: int) -> int:
    return int(np.random.default_rng([seed, lab, what]).integers(2**31))


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
    from unscatter.calibration import calibrate
    from unscatter.design import design_masks
    from unscatter.imaging import register_batch
    from unscatter.io import read_print, write_png
    from unscatter.lab import load_config, print_batch, random_lab
    from unscatter.lab.random import describe_lab
    from unscatter.masks import test_pattern_masks, trial_masks
    from unscatter.model import simulate

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
    design = design_masks(top, pool=a.pool, draws=a.draws, seed=_substream(seed, i, 1), progress=False, compare=False)
    t_design = time.perf_counter() - t0
    kinds = {
        "paper": list(trial_masks(top, seed=_substream(seed, i, 2)).values()),
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
    truth = [read_print(d / "batch.truth" / "prints" / f"{mid}.png") for mid in ids["held"]]
    held_masks = np.stack(held)
    cfg = load_config(overrides=over)
    lab_sigma_px = cfg["printer"]["kernel"]["sigma_um"] / float(cfg["batch"]["pixel_size_um"])
    lab = dict(lab=i, describe=describe_lab(over), effect=effect, magnitude=magnitude, overrides=over, failed=sorted(failed),
               design_s=round(t_design, 1), register_s=round(t_reg, 1), lab_sigma_px=lab_sigma_px)
    rows = []
    for kind in kinds:
        for n in a.counts:
            sub = d / f"{kind}_{n:02d}"
            used = _subset(d / "reg", ids[kind][:n], sub)
            row = dict(lab=i, kind=kind, n=n, prints_used=used)
            if used:
                t2 = time.perf_counter()
                fit = dict(population=48, generations=30, folds=0, bootstrap=0) if a.full else \
                    dict(population=24, generations=10, folds=0, bootstrap=0)
                try:
                    p = calibrate(sub, d / f"cal_{kind}_{n:02d}", seed=_substream(seed, i, 6), progress=False,
                                  residual_maps=False, figure=False, threads=1, **fit)
                except Exception as exc:  # noqa: BLE001 (a calibration that cannot be made is a result)
                    row.update(error=" ".join(str(exc).split())[:120])
                else:
                    mean, pooled = held_out_iou(simulate(p, held_masks), truth)
                    row.update(heldout_iou=mean, heldout_iou_pooled=pooled, sigma_px=float(p.values["sigma_px"]),
                               sigma_rel_err=float(p.values["sigma_px"] / lab_sigma_px - 1),
                               T=float(p.values["T"]), calibrate_s=round(time.perf_counter() - t2, 1))
                    if a.diagnose:
                        row.update(_diagnosis(sub, d / f"cal_{kind}_{n:02d}" / "params.yaml", d / f"diag_{kind}_{n:02d}",
                                              effect, held_masks, truth, _substream(seed, i, 7)))
            rows.append(row)
            print(f"  lab {i} {kind:8s} n={n:2d} used {used:2d}  IoU {row.get('heldout_iou', float('nan')):.4f}  "
                  f"sigma {row.get('sigma_px', float('nan')):.2f} (lab {lab_sigma_px:.2f})  {row.get('error', '')}"
                  + (f"  named {row['named']} ({row['verdict']}), selected IoU {row['heldout_iou_selected']:.4f}"
                     if "named" in row else ""), flush=True)
    return lab, rows


def held_out_iou(sim, truth: list) -> tuple[float, float]:
    """A model's held-out prints against the lab's: the mean of per-mask IoU and the IoU
    pooled over the masks (``metrics.pooled_iou``)."""
    from unscatter.metrics import iou, pooled_iou

    return float(np.nanmean([iou(s, t) for s, t in zip(sim, truth, strict=True)])), pooled_iou(sim, truth)


def _diagnosis(prints: Path, params: Path, out: Path, effect, held_masks, truth: list, seed: int) -> dict:
    """The residual diagnosis (quick settings) on a calibration's prints: what it named, its
    verdict against the lab's effect (None: the lab's effects are many, no verdict) and the
    selected model's held-out IoU."""
    from unscatter.diagnosis import diagnose
    from unscatter.model import load_params, simulate

    t0 = time.perf_counter()
    try:
        r = diagnose([prints], params, out, quick=True, seed=seed, progress=False, figures=False, threads=1)
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


def detection_lines(labs, rows, counts) -> list[str]:
    """Verdicts of the diagnosis against n, per kind of trial masks."""
    verdicts = (*bench_diagnosis.VERDICTS, "error")
    L = ["", "effect named (diagnosis, quick settings) against the number of prints: "
         + ", ".join(verdicts) + "; selected model's held-out IoU, median",
         f"{'n':>4} {'paper':>34} {'designed':>34}"]
    for n in counts:
        cells = []
        for kind in ("paper", "designed"):
            rr = [r for r in rows if r["kind"] == kind and r["n"] == n and "verdict" in r]
            c = [sum(r["verdict"] == v for r in rr) for v in verdicts]
            sel = [r["heldout_iou_selected"] for r in rr if "heldout_iou_selected" in r]
            cells.append("/".join(map(str, c)) + (f"  IoU {np.median(sel):.4f}" if sel else ""))
        L.append(f"{n:>4} {cells[0]:>34} {cells[1]:>34}   pooled: paper "
                 f"{_median(rows, 'paper', n, 'heldout_iou_selected_pooled')}, designed "
                 f"{_median(rows, 'designed', n, 'heldout_iou_selected_pooled')}")
    L.append("per lab (effect: named at each n, paper | designed):")
    for lab in labs:
        parts = []
        for kind in ("paper", "designed"):
            parts.append(" ".join(f"{r['n']}:{r.get('named', '?')}" for r in rows if r["lab"] == lab["lab"] and r["kind"] == kind))
        L.append(f"  lab {lab['lab']} {lab.get('effect')} ({lab.get('magnitude')}): {parts[0]} | {parts[1]}")
    return L


def summarize(seed, labs, rows, counts, cmd) -> str:
    L = [f"print budget: {cmd}", f"seed {seed}, {len(labs)} labs", ""]
    for lab in labs:
        L.append(f"lab {lab['lab']}: {lab['describe']}")
        L.append(f"   registration failed {len(lab['failed'])}: {', '.join(lab['failed']) or '-'}; "
                 f"design {lab['design_s']} s, registration {lab['register_s']} s")
    L += ["", "held-out IoU against the lab's true prints (median over labs [min, max]); |sigma error| median",
          f"{'n':>4} {'paper':>26} {'designed':>26} {'|sigma err| paper':>18} {'designed':>9}"]
    for n in counts:
        cells = []
        for kind in ("paper", "designed"):
            v = [r["heldout_iou"] for r in rows if r["kind"] == kind and r["n"] == n and "heldout_iou" in r]
            cells.append(f"{np.median(v):.4f} [{min(v):.4f}, {max(v):.4f}]" if v else "-")
        errs = []
        for kind in ("paper", "designed"):
            v = [abs(r["sigma_rel_err"]) for r in rows if r["kind"] == kind and r["n"] == n and "sigma_rel_err" in r]
            errs.append(f"{np.median(v):.3f}" if v else "-")
        L.append(f"{n:>4} {cells[0]:>26} {cells[1]:>26} {errs[0]:>18} {errs[1]:>9}")
    if any("heldout_iou_pooled" in r for r in rows):  # held-out IoU pooled over masks (metrics.pooled_iou)
        L.append("pooled over the held-out masks (median over labs): " + "; ".join(
            f"n={n} paper {_median(rows, 'paper', n, 'heldout_iou_pooled')}, designed "
            f"{_median(rows, 'designed', n, 'heldout_iou_pooled')}" for n in counts))
    wins = []
    for n in counts:
        for lab in labs:
            p = [r for r in rows if r["lab"] == lab["lab"] and r["n"] == n and "heldout_iou" in r]
            by = {r["kind"]: r["heldout_iou"] for r in p}
            if len(by) == 2:
                wins.append((n, by["designed"] > by["paper"]))
    L.append("")
    for n in counts:
        w = [x for m, x in wins if m == n]
        L.append(f"n={n}: designed better than paper in {sum(w)} of {len(w)} labs")
    top = max(counts)
    for n in counts:
        d = [r["heldout_iou"] for r in rows if r["kind"] == "designed" and r["n"] == n and "heldout_iou" in r]
        p = [r["heldout_iou"] for r in rows if r["kind"] == "paper" and r["n"] == top and "heldout_iou" in r]
        if d and p:
            L.append(f"designed n={n} vs paper n={top}: median IoU {np.median(d):.4f} vs {np.median(p):.4f}")
    if any("verdict" in r for r in rows):
        L += detection_lines(labs, rows, counts)
    return "\n".join(L)


def figure(rows, counts, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for kind, c in (("paper", "tab:gray"), ("designed", "tab:blue")):
        labs = sorted({r["lab"] for r in rows})
        for lab in labs:
            pts = [(r["n"], r["heldout_iou"]) for r in rows if r["kind"] == kind and r["lab"] == lab and "heldout_iou" in r]
            if pts:
                ax.plot(*zip(*pts), color=c, alpha=0.3, lw=0.8)
        med = [(n, np.median([r["heldout_iou"] for r in rows if r["kind"] == kind and r["n"] == n and "heldout_iou" in r]))
               for n in counts]
        med = [(n, v) for n, v in med if np.isfinite(v)]
        if med:
            ax.plot(*zip(*med), "o-", color=c, lw=2, label=f"{kind} (median)")
    ax.set_xscale("log", base=2)
    ax.set_xticks(counts, [str(n) for n in counts])
    ax.set_xlabel("trial prints")
    ax.set_ylabel("held-out IoU vs the lab's prints")
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
    ap.add_argument("--heldout", type=int, default=16)
    ap.add_argument("--full", action="store_true", help="the workflow's calibration (GA 48 x 30)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "print_budget")
    ap.add_argument("--effects", default=None, help="labs with one effect each, drawn from these (bench_diagnosis: "
                    f"{','.join(bench_diagnosis.RANDOM_EFFECTS)}); default: random_lab's labs, many effects at once")
    ap.add_argument("--strength", choices=("wide", "strong"), default="wide", help="with --effects: their magnitudes")
    ap.add_argument("--diagnose", action="store_true", help="the residual diagnosis after each calibration")
    a = ap.parse_args(argv)
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
    if a.out.exists():
        shutil.rmtree(a.out)
    a.out.mkdir(parents=True)
    labs, rows = [], []
    from unscatter.io import write_tsv, write_yaml

    for i in range(a.labs):
        lab, r = run_lab(i, seed, a, a.out)
        labs.append(lab)
        rows += r
        write_tsv(a.out / "budget.tsv", rows)
        write_yaml(a.out / "labs.yaml", dict(seed=seed, labs=labs))
    text = summarize(seed, labs, rows, a.counts, cmd)
    (a.out / "summary.txt").write_text(text + "\n")
    figure(rows, a.counts, a.out / "budget.png")
    print(text)


if __name__ == "__main__":
    main()
