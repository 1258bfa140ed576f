"""Calibration bias on random labs: Eq. 1 calibrated through the measurement chain
against the lab's own parameters and prints (not a test).

    python benchmarks/bench_calibration_bias.py --labs N [--seed S] [--size 256] [--out DIR]

For each of N labs drawn with ``unscatter.lab.random_lab`` (optics, camera, printer over
wide ranges; a new seed each run, printed, ``--seed`` repeats it), with the printer's
effects beyond Eq. 1 switched off (no heavy tail, anisotropy, hotspot, quartic field,
dose nonlinearity or edge offset: paper physics, so the lab's sigma and T are Eq. 1's):

1. 32 random paper trial masks are printed and imaged on the lab and registered as the
   workflow does (failed prints skipped);
2. Eq. 1 is calibrated on the registered prints ("chain"), and, for the decomposition,
   on the lab's true prints of the same masks in mask coordinates ("truth": no
   microscope, no registration);
3. held-out masks (test patterns and paper masks) are printed by the lab (mask
   coordinates, ``bench_diagnosis.TRUTH_DRAWS`` noisy prints each); each calibrated
   model, the lab's own Eq. 1 parameters ("lab eq1") and the floor (the per-pixel
   majority of ``bench_diagnosis.FLOOR_VOTES`` other noisy prints of the lab: the best its
   own printer predicts one print) are scored by IoU against them, the mean over the
   prints of each mask (``bench_diagnosis.held_out_truth``; before 2026-12-06 one print a
   mask and a floor of 7 votes).

Gauge: the lab's dose is 1 at full grey at the field centre over a large area, its
field's centre value is 1 and its print is where the density reaches half of saturation,
that is where the dose reaches its cure threshold; Eq. 1 with c0 = 1 (the default) has the
same units, so the fitted T compares with the lab's cure threshold directly.

The measurement's own bias is reported per lab: the registered prints against the lab's
true prints of the trial masks, as (registered area - true area) / true edge length
(px per edge px, positive: registered larger), and the share of true thin features
(line width <= 3 px) lost by the registration.

``--declare-dense`` writes the lab's fully cured polymer level over its background
(1 / the microscope's background) into batch.yaml as ``dense_level``, as a lab that
measured it would: the registration then thresholds at that level instead of its estimate.
``--dense-reference`` prints a dense reference in each batch instead (``masks.dense_reference_mask``
at 4 times the exposure, named in batch.yaml as ``dense_reference``), as a lab that prints one
would: the registration measures the level on it. The registration's dense level against
the lab's is reported per lab (``dense_err``) either way.
``--declare-blur`` writes the lab's microscope blur at the sample (``lab.run.psf_sigma_um``)
as ``microscope_blur_um``: the chain's calibration then holds it instead of fitting it.

Writes ``bias.tsv`` (a row per lab), ``labs.yaml`` and ``summary.txt`` under ``--out``.
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

# the printer's effects beyond Eq. 1, off (microscope effects stay as drawn: they are the chain)
EQ1_PRINTER = {"kernel": {"heavy_tail": {"fraction": 0.0, "length_um": 60.0}, "anisotropy": {"ratio": 1.0, "angle_deg": 0.0}},
               "illumination": {"quartic": 0.0, "hotspot": None}, "dose_gamma": 1.0, "edge_offset_um": 0.0,
               "kernel_dose_growth": 0.0, "oxygen_inhibition": None}


def _substream(seed: int, lab: int, what: int) -> int:
    return int(np.random.default_rng([seed, lab, what]).integers(2**31))


def thin_lost(true: np.ndarray, reg: np.ndarray, width: float = 3.0) -> tuple[int, int]:
    """Pixels of thin true features (local width <= ``width`` px: the medial axis where
    the distance to the background is at most width / 2) and how many of them the
    registered print misses."""
    from skimage.morphology import medial_axis

    t = np.asarray(true, bool)
    if not t.any():
        return 0, 0
    skel, dist = medial_axis(t, return_distance=True)
    thin = skel & (dist <= width / 2)
    return int(thin.sum()), int((thin & ~np.asarray(reg, bool)).sum())


def run_lab(i: int, seed: int, a, root: Path) -> dict:
    from unscatter.calibration import calibrate
    from unscatter.imaging import register_batch
    from unscatter.io import read_print, read_tsv, read_yaml, write_png, write_yaml
    from unscatter.lab import Printer, load_config, random_lab
    from unscatter.lab.random import describe_lab
    from unscatter.lab.run import psf_sigma_um
    from unscatter.masks import test_pattern_masks, trial_masks
    from unscatter.metrics import area_bias_px
    from unscatter.model import default_params, simulate

    d = root / f"lab{i:02d}"
    over = random_lab(np.random.default_rng(_substream(seed, i, 0)))
    over["printer"] = {**over["printer"], **EQ1_PRINTER, "kernel": {**over["printer"]["kernel"], **EQ1_PRINTER["kernel"]},
                       "illumination": {**over["printer"]["illumination"], **EQ1_PRINTER["illumination"]}}
    cfg = load_config(overrides=over)
    px = float(cfg["batch"]["pixel_size_um"])
    level = float(cfg["microscope"]["level"])
    pc, il = cfg["printer"], cfg["printer"]["illumination"]
    lab_vals = dict(sigma_px=pc["kernel"]["sigma_um"] / px, T=pc["cure"]["threshold"], c0=il["c0"], c1=il["cx2"], c2=il["cy2"],
                    c3=il["cx"], c4=il["cy"])

    trial = {f"trial_{k}": m for k, m in trial_masks(32, seed=_substream(seed, i, 2), size=a.size).items()}
    for mid, m in trial.items():
        if not a.reuse:
            write_png(d / "masks" / f"{mid}.png", m)
    t0 = time.perf_counter()
    reuse = a.reuse and (d / "reg" / "qc.tsv").is_file()
    if not reuse:
        from bench_diagnosis import print_lab_batch  # with --dense-reference, a large block cured through

        print_lab_batch(d / "masks", d / "batch", over, _substream(seed, i, 5), a.size, a.dense_reference)
        if a.declare_dense:  # the lab's fully cured polymer over its background (the microscope's units)
            meta = read_yaml(d / "batch" / "batch.yaml")
            write_yaml(d / "batch" / "batch.yaml", {**meta, "dense_level": round(1.0 / float(cfg["microscope"]["background"]), 4)})
        if a.declare_blur:  # the lab's microscope blur at the sample, as a lab that imaged beads would state it
            meta = read_yaml(d / "batch" / "batch.yaml")
            write_yaml(d / "batch" / "batch.yaml", {**meta, "microscope_blur_um": psf_sigma_um(cfg["microscope"], px)})
    t_print = time.perf_counter() - t0
    t0 = time.perf_counter()
    qc = read_tsv(d / "reg" / "qc.tsv") if reuse else register_batch(d / "batch", d / "reg", skip_failed=True, progress=False, threads=1)
    t_reg = time.perf_counter() - t0
    failed = sorted(r["id"] for r in qc if r["status"] == "failed")

    # the measurement's bias on the trial prints: registered against true, mask coordinates
    truth = {mid: read_print(d / "batch.truth" / "prints" / f"{mid}.png") for mid in trial}
    bias_px, thin_n, thin_miss = [], 0, 0
    for r in read_tsv(d / "reg" / "qc.tsv"):
        if r["status"] != "ok":
            continue
        reg, t = read_print(d / "reg" / f"{r['id']}.png"), truth[r["id"]]
        if np.isfinite(b := area_bias_px(reg, t)):
            bias_px.append(b)
        n, miss = thin_lost(t, reg)
        thin_n += n
        thin_miss += miss
    from bench_diagnosis import _write_batch, held_out_truth, scored  # prints in mask coordinates, held-out scores

    _write_batch(d / "truth_prints", trial, truth, px)

    # held-out masks, printed by the lab in mask coordinates (several prints each), and the floor
    held = {f"pat_{k}": m for k, m in test_pattern_masks(a.heldout, seed=_substream(seed, i, 3), size=a.size).items()}
    held |= {f"paper_{k}": m for k, m in trial_masks(a.heldout // 2, seed=_substream(seed, i, 4), size=a.size).items()}
    printer = Printer(cfg["printer"], a.size, px)
    ho_true, ho_floor = held_out_truth(printer, level, held, _substream(seed, i, 6))
    H = np.stack(list(held.values()))
    ids = list(held)

    def score(sim):
        v = [m["sim"] for m in scored({"sim": sim}, ho_true, ids)[0].values()]
        pat = [x for x, mid in zip(v, ids) if mid.startswith("pat_")]
        return float(np.nanmean(v)), float(np.nanmean(pat))

    lab_params = default_params("eq1", pixel_size_um=px).with_values(**lab_vals)
    row = dict(lab=i, failed=len(failed), lab_sigma_px=round(lab_vals["sigma_px"], 3), lab_T=lab_vals["T"],
               edge_bias_px=float(np.median(bias_px)) if bias_px else float("nan"),
               thin_lost=thin_miss / thin_n if thin_n else float("nan"), print_s=round(t_print, 1), register_s=round(t_reg, 1),
               dense_err=float(read_yaml(d / "reg" / "registration.yaml")["dense_level"] * float(cfg["microscope"]["background"]) - 1))
    row["iou_floor"], row["pat_floor"] = score([ho_floor[mid] for mid in ids])
    row["iou_lab_eq1"], row["pat_lab_eq1"] = score(simulate(lab_params, H))
    fit = dict(population=a.population, generations=a.generations, folds=0, bootstrap=0)
    for name, src, meas in (("chain", d / "reg", "registration"), ("plain", d / "reg", "none"), ("truth", d / "truth_prints", "none")):
        if name == "plain" and not a.plain:
            continue
        t0 = time.perf_counter()
        try:
            p = calibrate(src, d / f"cal_{name}", seed=_substream(seed, i, 7), progress=False, residual_maps=False, figure=False,
                          threads=1, measurement=meas, **fit)
        except Exception as exc:  # noqa: BLE001 (a calibration that cannot be made is a result)
            row[f"{name}_error"] = " ".join(str(exc).split())[:120]
            continue
        row[f"{name}_sigma_rel"] = float(p.values["sigma_px"] / lab_vals["sigma_px"] - 1)
        row[f"{name}_T_rel"] = float(p.values["T"] / lab_vals["T"] - 1)
        row[f"iou_{name}"], row[f"pat_{name}"] = score(simulate(p, H))
        row[f"{name}_s"] = round(time.perf_counter() - t0, 1)
        if (p.info.get("measurement") or {}).get("blur_px") is not None:
            row[f"{name}_blur_px"] = float(p.info["measurement"]["blur_px"])
    lab = dict(lab=i, describe=describe_lab(over), overrides=over, failed=failed, lab_values=lab_vals)
    print(f"lab {i}: {lab['describe']}\n  " + "  ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                                  for k, v in row.items()), flush=True)
    if not a.keep:
        shutil.rmtree(d)
    return lab, row


def summarize(seed, rows, cmd) -> str:
    L = [f"calibration bias: {cmd}", f"seed {seed}, {len(rows)} labs", "",
         "IoU: held-out, against the lab's prints; sig, T: fitted / lab's - 1; chain: registered prints through the "
         "measurement stage, plain: the same prints as if they were the cure, truth: the lab's true prints", "",
         f"{'lab':>4}{'sigma':>7}{'T':>6}{'edge px':>8}{'thin lost':>10}{'floor':>8}{'lab eq1':>8}"
         f"{'chain':>8}{'plain':>8}{'truth':>8}{'sig chain':>10}{'plain':>7}{'truth':>7}{'T chain':>8}{'plain':>7}{'truth':>7}"
         f"{'blur':>6}{'failed':>7}"]
    for r in rows:
        L.append(f"{r['lab']:>4}{r['lab_sigma_px']:>7.2f}{r['lab_T']:>6.3f}{r['edge_bias_px']:>+8.3f}{r['thin_lost']:>10.3f}"
                 f"{r['iou_floor']:>8.4f}{r['iou_lab_eq1']:>8.4f}{r.get('iou_chain', np.nan):>8.4f}{r.get('iou_plain', np.nan):>8.4f}"
                 f"{r.get('iou_truth', np.nan):>8.4f}"
                 f"{r.get('chain_sigma_rel', np.nan):>+10.3f}{r.get('plain_sigma_rel', np.nan):>+7.3f}{r.get('truth_sigma_rel', np.nan):>+7.3f}"
                 f"{r.get('chain_T_rel', np.nan):>+8.3f}{r.get('plain_T_rel', np.nan):>+7.3f}{r.get('truth_T_rel', np.nan):>+7.3f}"
                 f"{r.get('chain_blur_px', np.nan):>6.2f}{r['failed']:>7}")
    L.append("")

    def dist(key, absval=False):
        v = np.array([r[key] for r in rows if key in r and np.isfinite(r[key])])
        if absval:
            v = np.abs(v)
        return f"median {np.median(v):.4f}, worst {(v.max() if absval else v.min()):.4f}" if v.size else "-"

    for name in ("chain", "plain", "truth"):
        if not any(f"iou_{name}" in r or f"{name}_error" in r for r in rows):
            continue
        gaps = [r["iou_floor"] - r[f"iou_{name}"] for r in rows if f"iou_{name}" in r]
        n_sig = sum(abs(r.get(f"{name}_sigma_rel", np.inf)) > 0.05 for r in rows)
        n_T = sum(abs(r.get(f"{name}_T_rel", np.inf)) > 0.05 for r in rows)
        n_iou = sum(g > 0.01 for g in gaps) + sum(f"iou_{name}" not in r for r in rows)
        L.append(f"{name}: |sigma err| {dist(f'{name}_sigma_rel', True)}; |T err| {dist(f'{name}_T_rel', True)}; "
                 f"IoU gap to floor median {np.median(gaps) if gaps else np.nan:.4f}, worst {max(gaps) if gaps else np.nan:.4f}; "
                 f"failing (|sigma| > 5 %: {n_sig}, |T| > 5 %: {n_T}, IoU gap > 0.01: {n_iou}) of {len(rows)}")
    L.append(f"edge bias of the registered prints (px per edge px): {dist('edge_bias_px')}; thin features lost: {dist('thin_lost')}")
    L.append(f"the registration's dense level against the lab's (relative): |error| {dist('dense_err', True)}")
    return "\n".join(L)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--labs", type=int, default=6)
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--size", type=int, default=256, help="mask size (px)")
    ap.add_argument("--heldout", type=int, default=16)
    ap.add_argument("--population", type=int, default=24)
    ap.add_argument("--generations", type=int, default=12)
    ap.add_argument("--no-plain", dest="plain", action="store_false",
                    help="leave out the calibration without the measurement stage")
    ap.add_argument("--reuse", action="store_true", help="reuse the prints and registrations a --keep run left in --out "
                    "(same --seed): only the calibrations run again")
    ap.add_argument("--declare-dense", action="store_true", help="write the lab's dense level (fully cured polymer over "
                    "its background) into batch.yaml as dense_level, as a lab that measured it would")
    ap.add_argument("--dense-reference", action="store_true", help="print a dense reference in each batch "
                    "(masks.dense_reference_mask at 4 times the exposure) and name it in batch.yaml as dense_reference, "
                    "as a lab that prints one would: the registration measures the dense level on it")
    ap.add_argument("--declare-blur", action="store_true", help="write the lab's microscope blur at the sample into "
                    "batch.yaml as microscope_blur_um (lab.run.psf_sigma_um), as a lab that imaged beads would: the "
                    "chain's calibration then holds it instead of fitting it")
    ap.add_argument("--keep", action="store_true", help="keep each lab's batch, registration and calibrations")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "calibration_bias")
    a = ap.parse_args(argv)
    if a.dense_reference and a.declare_dense:
        ap.error("--dense-reference measures the dense level that --declare-dense states: give one of them")
    logging.basicConfig(level=logging.ERROR)
    import warnings

    import torch

    warnings.simplefilter("ignore")
    torch.set_num_threads(1)
    seed = a.seed if a.seed is not None else int(np.random.default_rng().integers(2**31))
    cmd = " ".join(["python benchmarks/bench_calibration_bias.py", *(argv if argv is not None else sys.argv[1:])])
    print(f"seed {seed} (repeat with --seed {seed})", flush=True)
    from unscatter.io import InputError, benchmark_output_dir, write_tsv, write_yaml

    try:
        a.out = benchmark_output_dir(a.out, script="benchmarks/bench_calibration_bias.py", keep=a.reuse)
    except InputError as exc:
        ap.error(str(exc))

    labs, rows = [], []
    for i in range(a.labs):
        lab, row = run_lab(i, seed, a, a.out)
        labs.append(lab)
        rows.append(row)
        write_tsv(a.out / "bias.tsv", rows, sorted({k for r in rows for k in r}, key=lambda k: list(rows[0]).index(k) if k in rows[0] else 99))
        write_yaml(a.out / "labs.yaml", dict(seed=seed, labs=labs))
    text = summarize(seed, rows, cmd)
    (a.out / "summary.txt").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
