"""Benchmark of the candidate fits (not a test): does a fit of Eq. 1 plus one library
effect reach the optimum of its family, and are its parameters recovered within the
spread it reports (issue #12, deliverable 1)?

    python benchmarks/bench_fit_recovery.py [--labs N] [--seed S] [--size 256] [--count 32]
        [--effects heavy_tail,...] [--quick] [--noise 0.03]

Each "lab" is the library's own model (``unscatter.model``: Eq. 1 plus one effect) at
random parameters: sigma 1.5 to 5 px, T 0.35 to 0.65, the quadratic field terms within
+-0.08, and the effect drawn over the part of its range where it matters (tail share
0.1 to 0.45 over 6 to 30 px, an aspect ratio 1.25 to 1.8 or its inverse at any angle,
gamma 0.6 to 0.85 or 1.25 to 1.8, each quartic field term within +-0.15, an edge offset
of 0.5 to 2.5 px either way). It prints ``count`` paper trial masks through a multiplicative
dose noise correlated over 2 px (``simulate(dose_noise=...)``, as cells give). Then the
workflow's chain: ``calibrate`` Eq. 1 (defaults, no CV) and ``diagnose`` with that one
candidate (defaults, or ``--quick``). Scored on 16 held-out paper masks and 16 test
patterns, printed with fresh noise:

- ``ratio``: held-out mismatch of the fitted model over that of the true parameters
  (target: at most 1.02; Eq. 1's ratio beside it says how much the effect matters);
- each free parameter's error over the spread the diagnosis reports for it (``std`` in
  model.yaml: the grouped jackknife over its fold fits): ``|z|``; an aspect ratio below
  1 is compared as its inverse at the angle turned by 90 deg, angles modulo 180 deg;
- ``train_ratio``: the selected model's mismatch on the trial prints it was fitted to over
  the true parameters' there. The truth is a point of the fitted family, so above 1 the
  fit stopped short of its objective's optimum (the optimiser's failure); the held-out
  ratios add the estimate's noise (what 32 prints cannot pin down);
- ``cv_ratio``: the candidate's k-fold held-out mismatch in the diagnosis (its ranking row,
  whether accepted or not) over the true parameters' mismatch on the same trial prints:
  the fit judged apart from the acceptance test (target: at most 1.02);
- whether the diagnosis accepted the effect at all (a strong effect it does not accept
  is a miss of the fit or of the test).

``--set key=value`` (repeatable; YAML values) passes a setting to both ``calibrate`` and
``diagnose`` where it is theirs (e.g. ``--set "temperatures=[0.1, 0.03]"``), to compare
fitting settings on the same draws.

Every run draws a new seed (printed; ``--seed`` reproduces it with the same ``--labs``
and ``--effects``). ``--summarize DIR [DIR ...]`` reprints the summary of saved runs
together. Tables and a figure: ``benchmarks/out/fit_recovery/seed<S>/``
(``cases.tsv``, ``params.tsv``, ``summary.txt``, ``recovery.png``).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_diagnosis import _write_batch  # noqa: E402

import yaml  # noqa: E402

from unscatter.calibration import DEFAULTS as CAL_DEFAULTS  # noqa: E402
from unscatter.calibration import calibrate  # noqa: E402
from unscatter.diagnosis import DEFAULTS as DIAG_DEFAULTS  # noqa: E402
from unscatter.diagnosis import diagnose  # noqa: E402
from unscatter.io import read_tsv, write_tsv, write_yaml  # noqa: E402
from unscatter.masks import test_pattern_masks, trial_masks  # noqa: E402
from unscatter.model import EFFECTS, canonical, default_params, extend_params, load_params, simulate  # noqa: E402

PX_UM = 5.0  # design pixel size written to the batch (the fits work in design px)


def draw_truth(rng: np.random.Generator, effect: str) -> dict:
    """Eq. 1 plus ``effect`` at random parameters (see the module docstring)."""
    v = dict(sigma_px=float(rng.uniform(1.5, 5.0)), T=float(rng.uniform(0.35, 0.65)),
             **{f"c{i}": float(rng.uniform(-0.08, 0.08)) for i in range(1, 5)})
    sign = 1.0 if rng.random() < 0.5 else -1.0
    if effect == "heavy_tail":
        v.update(tail_fraction=float(rng.uniform(0.1, 0.45)), tail_length_px=float(rng.uniform(6.0, 30.0)))
    elif effect == "anisotropy":
        r = float(np.exp(rng.uniform(np.log(1.25), np.log(1.8))))
        v.update(aniso_ratio=r if sign > 0 else 1.0 / r, aniso_angle_deg=float(rng.uniform(-45.0, 45.0)))
    elif effect == "dose_nonlinearity":
        v.update(dose_gamma=float(rng.uniform(1.25, 1.8) if sign > 0 else rng.uniform(0.6, 0.85)))
    elif effect == "illumination_field":
        v.update({k: float(rng.uniform(-0.15, 0.15)) for k in ("ill_xy", "ill_xr2", "ill_yr2", "ill_r4")})
    elif effect == "edge_offset":
        v.update(edge_offset_px=sign * float(rng.uniform(0.5, 2.5)))
    else:
        raise ValueError(f"unknown effect {effect!r}; known: {list(EFFECTS)}")
    return v


def param_error(name: str, fit: float, true: float) -> float:
    d = fit - true
    return (d + 90.0) % 180.0 - 90.0 if name == "aniso_angle_deg" else d


def mismatch(params, masks: np.ndarray, prints: np.ndarray) -> float:
    return float(np.mean(simulate(params, masks) != prints))


def overrides(items) -> dict:
    """``key=value`` strings as a dict of YAML values."""
    out = {}
    for it in items or []:
        k, sep, v = it.partition("=")
        if not sep:
            raise SystemExit(f"--set {it!r}: expected key=value")
        val = yaml.safe_load(v)
        out[k.strip()] = tuple(val) if isinstance(val, list) else val
    bad = sorted(k for k in out if k not in CAL_DEFAULTS and k not in DIAG_DEFAULTS)
    if bad:
        raise SystemExit(f"--set: unknown setting(s) {bad}")
    return out


def run(args) -> None:
    sets = overrides(args.set)
    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(4), "little") % 1_000_000_000
    effects = args.effects.split(",") if args.effects else list(EFFECTS)
    tag = "".join(f"_{k}={v}" for k, v in sets.items()).replace(" ", "").replace("(", "").replace(")", "").replace(",", "-")
    root = Path(args.out or "benchmarks/out/fit_recovery") / f"seed{seed}{'_quick' if args.quick else ''}{tag}"
    root.mkdir(parents=True, exist_ok=True)
    cmd = (f"python benchmarks/bench_fit_recovery.py --labs {args.labs} --seed {seed} --size {args.size} --count {args.count}"
           + (f" --effects {args.effects}" if args.effects else "") + (" --quick" if args.quick else "")
           + (f" --noise {args.noise}" if args.noise != 0.03 else "") + "".join(f" --set '{x}'" for x in args.set or []))
    print(f"seed {seed} (reproduce: {cmd}); {args.count} trial prints + 16 paper + 16 test-pattern held-out masks of "
          f"{args.size}x{args.size}, dose noise {args.noise}; outputs in {root}", flush=True)
    rng = np.random.default_rng(seed)
    trial = trial_masks(args.count, seed=0, size=args.size)
    held = {f"paper_{k}": v for k, v in trial_masks(16, seed=seed % 100_000 + 1, size=args.size).items()}
    held.update(test_pattern_masks(16, seed=seed, size=args.size))
    H = np.stack(list(held.values()))
    T = np.stack(list(trial.values()))
    base = default_params("eq1", pixel_size_um=PX_UM)
    cases, prows = [], []
    head = (f"{'case':<5}{'effect':<20}{'truth (effect)':<34}{'accepted':<9}{'ratio':>7}{'cv':>7}{'train':>7}{'eq1':>7}{'max |z|':>9}"
            f"{'sigma z':>8}{'T z':>7}{'cal':>6}{'diag':>6}")
    print(head, flush=True)
    lines = [head]
    ci = 0
    for lab in range(args.labs):
        for effect in effects:
            case_seed = int(rng.integers(1 << 31))
            crng = np.random.default_rng(case_seed)
            truth = draw_truth(crng, effect)
            p_true = extend_params(base, [effect]).with_values(**truth)
            prints = simulate(p_true, T, dose_noise=args.noise, rng=crng)
            held_prints = simulate(p_true, H, dose_noise=args.noise, rng=crng)
            d = root / f"case{ci:03d}_{effect}"
            batch = _write_batch(d / "prints", trial, dict(zip(trial, prints)), PX_UM)
            write_yaml(d / "truth.yaml", dict(seed=case_seed, effect=effect, values=truth))
            t0 = time.perf_counter()
            calibrate([batch], d / "cal", seed=0, folds=0, bootstrap=0, residual_maps=False, figure=False, progress=False,
                      **{k: v for k, v in sets.items() if k in CAL_DEFAULTS})
            t_cal = time.perf_counter() - t0
            t0 = time.perf_counter()
            r = diagnose([batch], d / "cal" / "params.yaml", d / "diag", quick=args.quick, seed=0, progress=False,
                         figures=False, candidates=[effect], **{k: v for k, v in sets.items() if k in DIAG_DEFAULTS})
            t_diag = time.perf_counter() - t0
            eq1 = load_params(d / "cal" / "params.yaml")
            sel = load_params(d / "diag" / "model.yaml")
            accepted = effect in r["effects"]
            # the effect's fit, whether accepted or not: the ranking's fold mean is all the diagnosis keeps of a
            # rejected candidate, so a rejected effect is scored as the model the diagnosis returns (Eq. 1)
            e_true = mismatch(p_true, H, held_prints)
            e_fit = mismatch(sel, H, held_prints)
            e_eq1 = mismatch(eq1, H, held_prints)
            # the candidate's k-fold held-out error in the diagnosis against the truth's error on the same prints
            cand = [x for x in r["rounds"] if x["round"] == 1 and x["candidate"] == effect]
            e_true_trial = mismatch(p_true, T, prints)
            # the optimiser's own test: the fitted model's objective on the prints it was fitted to, against the
            # truth's (a feasible point of the same family): above 1, the fit stopped short of the optimum
            train_ratio = mismatch(sel, T, prints) / e_true_trial
            cv_ratio = cand[0]["heldout_mismatch"] / e_true_trial if cand else np.nan
            tv, fv = canonical(truth), canonical(sel.values)
            extras = (sel.info or {}).get("parameter_extras", {})
            zs = {}
            for k in tv:
                if k not in fv:
                    continue
                sd = float(extras.get(k, {}).get("std", np.nan)) if accepted else np.nan
                err = param_error(k, fv[k], tv[k])
                z = abs(err) / sd if sd > 0 else np.nan
                zs[k] = z
                prows.append(dict(case=ci, effect=effect, accepted=accepted, param=k, true=tv[k], fit=fv[k], error=err,
                                  spread=sd, abs_z=z, of_effect=k not in base.values))
            fx = [sp.name for sp in EFFECTS[effect].params]
            zmax = max((zs.get(k, np.nan) for k in fx), default=np.nan) if accepted else np.nan
            desc = ", ".join(f"{k}={tv[k]:.3g}" for k in fx)
            row = dict(case=ci, case_seed=case_seed, effect=effect, truth=desc, accepted=accepted, named=",".join(r["effects"]),
                       ratio=e_fit / e_true, cv_ratio=cv_ratio, train_ratio=train_ratio, ratio_eq1=e_eq1 / e_true, mismatch_true=e_true, max_abs_z_effect=zmax,
                       sigma_abs_z=zs.get("sigma_px", np.nan), T_abs_z=zs.get("T", np.nan), cal_s=round(t_cal, 1),
                       diag_s=round(t_diag, 1))
            cases.append(row)
            line = (f"{ci:<5}{effect:<20}{desc[:33]:<34}{'yes' if accepted else 'NO':<9}{row['ratio']:7.3f}{cv_ratio:7.3f}{train_ratio:7.3f}{row['ratio_eq1']:7.3f}"
                    f"{zmax:9.2f}{row['sigma_abs_z']:8.2f}{row['T_abs_z']:7.2f}{t_cal:5.0f}s{t_diag:5.0f}s")
            print(line, flush=True)
            lines.append(line)
            write_tsv(root / "cases.tsv", cases, list(cases[0]))
            write_tsv(root / "params.tsv", prows, list(prows[0]))
            ci += 1
    text = "\n".join(lines) + "\n\n" + summary(cases, prows)
    (root / "summary.txt").write_text(text)
    print("\n" + summary(cases, prows))
    figure(root / "recovery.png", cases, prows, effects)


T3_95 = 3.18  # Student t(3)'s two-sided 95 % point: a jackknife over 4 folds puts 5 % of the errors beyond it


def summary(cases: list, prows: list) -> str:
    out = []
    effects = list(dict.fromkeys(c["effect"] for c in cases))
    out.append(f"{'effect':<20}{'cases':>6}{'accepted':>9}{'ratio median':>13}{'max':>7}{'<=1.02':>8}{'cv median':>10}{'max':>7}"
               f"{'<=1.02':>8}{'train max':>10}{'<=1.01':>8}"
               f"{'effect |z| median':>18}{'<=1':>6}{'<=2':>6}{'all |z| <=2':>12}{'> 3.18':>10}")
    for e in effects + ["all"]:
        cs = [c for c in cases if e in ("all", c["effect"])]
        ps = [p for p in prows if e in ("all", p["effect"]) and p["accepted"]]
        ratios = np.array([c["ratio"] for c in cs])
        cv = np.array([c.get("cv_ratio", np.nan) for c in cs])
        trn = np.array([c.get("train_ratio", np.nan) for c in cs if c["accepted"]] or [np.nan])  # else it is Eq. 1's
        zf = np.array([p["abs_z"] for p in ps if p["of_effect"] and np.isfinite(p["abs_z"])])
        za = np.array([p["abs_z"] for p in ps if np.isfinite(p["abs_z"])])
        out.append(f"{e:<20}{len(cs):6d}{sum(c['accepted'] for c in cs):9d}{np.median(ratios):13.3f}{ratios.max():7.3f}"
                   f"{int(np.sum(ratios <= 1.02)):8d}{np.median(cv):10.3f}{cv.max():7.3f}{int(np.sum(cv <= 1.02)):8d}"
                   f"{np.max(trn):10.3f}{int(np.sum(trn <= 1.01)):8d}"
                   f"{(np.median(zf) if len(zf) else np.nan):18.2f}"
                   f"{(np.mean(zf <= 1) if len(zf) else np.nan):6.0%}{(np.mean(zf <= 2) if len(zf) else np.nan):6.0%}"
                   f"{(np.mean(za <= 2) if len(za) else np.nan):12.0%}{f'{int(np.sum(za > T3_95))} of {len(za)}':>10}")
    out.append("ratio: held-out mismatch of the selected model over the true parameters' (target <= 1.02); cv: the "
               "candidate's k-fold held-out mismatch in the diagnosis over the truth's on the trial prints; train (accepted "
               "effects): the fit's mismatch on its own prints over the truth's (above 1: short of the optimum); |z|: parameter error over "
               "the reported spread (a grouped jackknife over k = 4 folds has k - 1 = 3 degrees of freedom: a Student t(3) gives "
               "61 % within 1, 86 % within 2, 95 % within 3.18; '> 3.18': all parameters beyond it, of those scored)")
    t = np.array([c["diag_s"] for c in cases])
    out.append(f"diagnosis (one candidate) median {np.median(t):.0f} s, max {t.max():.0f} s")
    return "\n".join(out)


def figure(path: Path, cases: list, prows: list, effects: list) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for i, e in enumerate(effects):
        cs = [c for c in cases if c["effect"] == e]
        ax[0].scatter([i] * len(cs), [c["ratio"] for c in cs], c=["C0" if c["accepted"] else "C3" for c in cs])
        ax[0].scatter([i + 0.2] * len(cs), [c["ratio_eq1"] for c in cs], marker="x", c="grey")
        ps = [p for p in prows if p["effect"] == e and p["accepted"] and np.isfinite(p["abs_z"])]
        ax[1].scatter([i + (0.15 if p["of_effect"] else -0.15) for p in ps], [p["abs_z"] for p in ps],
                      c=["C1" if p["of_effect"] else "C0" for p in ps], s=12)
    for a in ax:
        a.set_xticks(range(len(effects)), effects, rotation=20)
    ax[0].axhline(1.02, ls="--", c="k", lw=0.8)
    ax[0].set_yscale("log")
    ax[0].set_ylabel("held-out mismatch / true parameters'")
    ax[0].set_title("fit (blue; red: not accepted) and Eq. 1 (x)")
    ax[1].axhline(1, ls=":", c="k", lw=0.8)
    ax[1].axhline(2, ls="--", c="k", lw=0.8)
    ax[1].set_yscale("symlog", linthresh=1)
    ax[1].set_ylabel("|fit - true| / reported spread")
    ax[1].set_title("parameters (orange: the effect's, blue: Eq. 1's)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _typed(row: dict) -> dict:
    out = {}
    for k, v in row.items():
        if v in ("True", "False"):
            out[k] = v == "True"
        else:
            try:
                out[k] = float(v) if v not in ("", "nan") else np.nan
            except ValueError:
                out[k] = v
    return out


def summarize(dirs: list) -> None:
    """The summary of several runs' tables together (their cases.tsv and params.tsv)."""
    cases, prows = [], []
    for i, d in enumerate(dirs):
        cs = [_typed(r) for r in read_tsv(Path(d) / "cases.tsv")]
        for c in cs:
            c["case"] = f"{i}:{int(c['case'])}"
        ps = [_typed(r) for r in read_tsv(Path(d) / "params.tsv")]
        for q in ps:
            q["case"] = f"{i}:{int(q['case'])}"
        cases += cs
        prows += ps
    print(f"{len(cases)} cases from {len(dirs)} run(s)\n" + summary(cases, prows))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--labs", type=int, default=2, help="random parameter draws per effect")
    ap.add_argument("--seed", type=int, default=None, help="the seed (default: a new one, printed)")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--count", type=int, default=32, help="trial prints")
    ap.add_argument("--effects", default=None, help=f"comma-separated (default: {','.join(EFFECTS)})")
    ap.add_argument("--quick", action="store_true", help="diagnose(quick=True)")
    ap.add_argument("--noise", type=float, default=0.03, help="dose noise (sd of the multiplicative field)")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE", help="a calibrate/diagnose setting (repeatable)")
    ap.add_argument("--out", default=None, help="output root (default benchmarks/out/fit_recovery)")
    ap.add_argument("--summarize", nargs="+", metavar="RUN_DIR", help="reprint the summary of these runs' tables together")
    args = ap.parse_args()
    summarize(args.summarize) if args.summarize else run(args)


if __name__ == "__main__":
    main()
