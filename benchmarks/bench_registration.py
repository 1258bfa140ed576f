"""Registration accuracy and speed against the virtual lab's truth.

One lab (the default lab, or the default with a lab config's overrides), trial masks:

    python benchmarks/bench_registration.py [--count 32] [--seed 3] [--out benchmarks/out/registration] [--lab-config FILE]

prints per-print transform error (RMS over the mask field, mask pixels), IoU of the
registered print vs the lab's noise-free print, the mean over non-empty prints, and the
wall time of registering the batch. The IoU a perfect registration would reach (the
true transform, same thresholding) is printed beside it.

Randomised labs, test patterns:

    python benchmarks/bench_registration.py --labs N [--prints 32] [--seed S] [--out benchmarks/out/registration_labs]

draws N labs with ``unscatter.lab.random_lab`` (optics, camera, export, printer and
microscope effects over wide ranges), prints ``--prints`` test masks on each (all test
patterns of ``unscatter.masks.TEST_PATTERNS``, the paper's families included), registers
each batch as the workflow does (skipping failed prints) and scores every print against
the lab's truth. ``--masks pool`` or ``--masks marked`` prints the trial-mask design's
candidates instead (``unscatter.design.candidate_pool``), without or with their
registration marks, and ``--masks paper`` or ``--masks paper-marked`` the paper's random
trial masks (``unscatter.masks.trial_masks``) without or with them: the same labs and
masks for the same seed, so the two runs measure what the marks do. Without ``--seed`` each run draws new labs; the seed it drew is printed
and ``--seed S`` repeats the run. Labs run one after another (registration itself uses
the two cores). Writes ``prints.tsv`` (one row per print), ``labs.yaml`` (each lab's
config overrides), ``summary.txt`` (what is printed) and ``worst.png`` (the overlays of
the worst prints) under ``--out``.

One lab of a ``--labs`` run again, with some of its physics changed (an ablation):

    python benchmarks/bench_registration.py --reprint benchmarks/out/registration_labs/lab_07 \
        --set printer.kernel.heavy_tail.fraction=0 [--set KEY=VALUE ...] [--out DIR]

prints the lab's masks again with its own full config (``batch.truth/lab_config.yaml``,
its seed included, so that everything not changed, noise too, is the same bit for bit),
registers the new batch and lists, print by print, the verdicts and pose errors before
and after: which of a lab's effects makes a print fail or go silently wrong.

Two ``--labs`` runs of the same labs against each other (the same seed on another machine,
or with another arithmetic, e.g. ``OPENBLAS_CORETYPE=Haswell``):

    python benchmarks/bench_registration.py --against DIR_A DIR_B [--out DIR]

lists the prints whose verdict differs, the distance between the two registrations of
each print (mask px, RMS over the field), the silently wrong prints of each, and, per
lab, the batch templates' numbers that differ most between the two (relative to the
larger). Writes ``against.tsv`` and ``against.txt`` under ``--out`` (default DIR_B).

With ``--perturb-template REL [--perturb-seed K]`` a ``--labs`` run moves the start of
each of the batch template's fits by a relative amount drawn at REL (1e-9 moves it in
its last bits, as another machine's arithmetic would): a probe, patched in here and not
an option of the registration, that shows on one machine how far the template's fit,
and the poses with it, rest on such bits. ``--against`` then compares it with a plain
run of the same seed.

A print is *silently wrong* when registration reports it ``ok`` with a pose error above
1.5 mask px, or ``empty`` although the lab's noise-free print has more than 0.05 % of
the field solid (131 mask px, a dot of 13 px across; registration's own empty test
counts 30 px). A ``failed`` print is not silently wrong: QC said so. The summary also
splits the failed prints by their true pose error (QC too cautious, or right) and sets
the ok prints' true error against the spreads QC judged them by (``qc_lines``).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import tifffile
import yaml

from unscatter.imaging import Settings, correct_image, threshold_print, transform_rms_px
from unscatter.io import InputError, benchmark_output_dir, read_print, read_tsv, read_yaml, write_png, write_tsv, write_yaml
from unscatter.metrics import iou

SILENT_POSE_PX = 1.5  # an 'ok' print whose pose is off by more is silently wrong
SILENT_EMPTY_SOLID = 0.0005  # an 'empty' print whose truth has more solid is silently wrong
TARGETS = dict(silently_wrong=0, failed_pct=1.0, median_pose_px=0.5, iou_gap=0.01, seconds_per_32=30.0)


def _matrix(row: dict, prefix: str = "m"):
    """The 2x3 design->image matrix of a qc.tsv or transforms.tsv row, or None."""
    try:
        return np.array([[float(row[f"{prefix}{a}{b}"]) for b in range(3)] for a in range(2)])
    except (KeyError, TypeError, ValueError):
        return None


def _float(v, default=float("nan")) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return default


def evaluate(reg_dir: Path, truth_dir: Path, size: int = 512) -> list[dict]:
    """Per print: status, QC reason, transform error (wherever qc.tsv has a matrix, failed
    prints included), IoU as registered (ok and empty prints), and IoU with the true
    transform (a perfect registration of the same image, same flat field, stain and threshold)."""
    qc = {r["id"]: r for r in read_tsv(reg_dir / "qc.tsv")}
    meta = read_yaml(reg_dir / "batch.yaml")
    offset = float(meta.get("camera_offset_adu", 0) or 0)
    refs = meta.get("dense_reference") or []
    truth = {r["id"]: r for r in read_tsv(truth_dir / "transforms.tsv")}
    out = []
    for mid, t in truth.items():
        if mid in refs:  # a dense reference: the registration measures it, it registers no print of it
            continue
        q = qc[mid]
        tp = read_print(truth_dir / "prints" / f"{mid}.png")
        row = dict(id=mid, status=q["status"], reason=q.get("reason", ""), truth_solid=float(tp.mean()),
                   true_rotation_deg=_float(t["rotation_deg"]), true_scale=_float(t["scale"]),
                   rotation_deg=_float(q.get("rotation_deg")), scale=_float(q.get("scale")), score=_float(q.get("score")),
                   pose_sd=_float(q.get("pose_sd")), size_sd=_float(q.get("size_sd")),
                   model_sd=_float(q.get("model_sd")))
        Mt, Me = _matrix(t), _matrix(q)
        if Me is not None:
            row["rms_px"] = transform_rms_px(Me, Mt, size)
        thr = _float(q.get("threshold"))
        if np.isfinite(thr):
            k = correct_image(mid, Path(q["image"]), offset, Settings(), q["flatfield"])
            stain = reg_dir / "stain" / f"{mid}.tif"  # what the registration divided the print's image by (its stain),
            c = k.c  # on the design grid at the pose it found: into the image by that pose, out of it by the true one
            if stain.exists() and Me is not None:
                c = c / cv2.warpAffine(tifffile.imread(stain), Me.astype(np.float64), c.shape[::-1], flags=cv2.INTER_LINEAR,
                                       borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)
            row["iou_perfect"] = iou(threshold_print(c, Mt, thr, size)[1], tp)
        if q["status"] in ("ok", "empty"):
            row["iou"] = iou(read_print(reg_dir / f"{mid}.png"), tp)
        out.append(row)
    return out


def silently_wrong(r: dict) -> bool:
    if r["status"] == "ok":
        return r.get("rms_px", np.inf) > SILENT_POSE_PX
    return r["status"] == "empty" and r["truth_solid"] > SILENT_EMPTY_SOLID


# ------------------------------------------------------------------ one lab


def single_lab(a) -> None:
    from unscatter.imaging import register_batch
    from unscatter.lab import print_batch
    from unscatter.masks import write_trial_masks

    seed = 3 if a.seed is None else a.seed
    out = a.out or Path("benchmarks/out/registration")
    write_trial_masks(out / "masks", a.count, seed=seed)
    print_batch(out / "masks", out / "batch", lab_config=a.lab_config, seed=seed, progress=False)
    t0 = time.perf_counter()
    register_batch(out / "batch", out / "reg", skip_failed=True, threads=a.threads)
    dt = time.perf_counter() - t0
    rows = evaluate(out / "reg", out / "batch.truth")
    for r in rows:
        print(f"{r['id']}  {r['status']:6s}  rms {r.get('rms_px', float('nan')):6.3f} px  IoU {r.get('iou', float('nan')):.4f}"
              f" (perfect registration {r.get('iou_perfect', float('nan')):.4f})  solid {r['truth_solid']:.3f}")
    ok = [r for r in rows if r["status"] == "ok"]
    ne = [r for r in rows if r["truth_solid"] > 0 and "iou" in r]
    print(f"registered {len(rows)} images in {dt:.1f} s ({dt / len(rows):.2f} s each)")
    print(f"transform RMS over the mask field: mean {np.mean([r['rms_px'] for r in ok]):.3f} px, max {np.max([r['rms_px'] for r in ok]):.3f} px")
    print(f"IoU vs the lab's noise-free print (non-empty prints): mean {np.mean([r['iou'] for r in ne]):.4f}, min {np.min([r['iou'] for r in ne]):.4f}")
    perf = [r["iou_perfect"] for r in ne if "iou_perfect" in r]
    print(f"IoU with the true transform (same images, same threshold): mean {np.mean(perf):.4f}")
    print(f"empty: {sum(r['status'] == 'empty' for r in rows)} (truth empty: {sum(r['truth_solid'] == 0 for r in rows)})")
    print(f"failed: {sum(r['status'] == 'failed' for r in rows)}")


# ------------------------------------------------------------ randomised labs


def _substream(seed: int, lab: int, what: int) -> int:
    """An independent integer seed for one purpose (masks, lab noise) of one lab."""
    return int(np.random.SeedSequence([seed, lab, what]).generate_state(1)[0])


def mask_pattern(kind: str, mid: str) -> str:
    """The pattern a print's mask is of: its test pattern, its family among the paper's
    trial masks (``unscatter.masks.trial_masks`` takes the families in turn), or its
    design candidate's kind."""
    from unscatter.masks import TRIAL_FAMILIES, test_pattern_of

    if kind == "test":
        return test_pattern_of(mid)
    if kind in ("paper", "paper-marked"):
        return TRIAL_FAMILIES[int(mid.rsplit("_", 1)[1]) % len(TRIAL_FAMILIES)]
    return mid.rsplit("_", 1)[0]


def lab_masks(kind: str, count: int, seed: int) -> dict:
    """id -> mask: test patterns (``unscatter.masks.test_pattern_masks``), the paper's random
    trial masks (``unscatter.masks.trial_masks``) without ("paper") or with the registration
    marks ("paper-marked", ``trial_masks.paper_fiducials``), or candidates of the trial-mask
    design's pool (``unscatter.design.candidate_pool``) without ("pool") or with them ("marked")."""
    if kind == "test":
        from unscatter.masks import test_pattern_masks

        return test_pattern_masks(count, seed=seed)
    if kind in ("paper", "paper-marked"):
        from unscatter.masks import trial_masks, with_fiducials

        masks = trial_masks(count, seed=seed)
        return {k: with_fiducials(m) for k, m in masks.items()} if kind == "paper-marked" else masks
    from unscatter.design import candidate_pool

    return candidate_pool(count, seed=seed, fiducials=kind == "marked")


def run_lab(i: int, seed: int, prints: int, root: Path, threads: int = 2, masks: str = "test") -> tuple[dict, list[dict]]:
    """Draw lab ``i``, print ``masks`` (``lab_masks``) on it, register, score. Returns (lab,
    print rows)."""
    from unscatter.imaging import register_batch
    from unscatter.lab import print_batch, random_lab

    over = random_lab(np.random.default_rng([seed, i, 0]))
    d = root / f"lab_{i:02d}"  # root is emptied for the run (benchmark_output_dir)
    for mid, m in lab_masks(masks, prints, _substream(seed, i, 1)).items():
        write_png(d / "masks" / f"{mid}.png", m)
    t0 = time.perf_counter()
    print_batch(d / "masks", d / "batch", overrides=over, seed=_substream(seed, i, 2), progress=False)
    t_print = time.perf_counter() - t0
    t0 = time.perf_counter()
    register_batch(d / "batch", d / "reg", skip_failed=True, progress=False, threads=threads)
    t_reg = time.perf_counter() - t0
    rows = evaluate(d / "reg", d / "batch.truth")
    for r in rows:
        r.update(lab=i, pattern=mask_pattern(masks, r["id"]),
                 silently_wrong=int(silently_wrong(r)))
    lab = dict(index=i, overrides=over, register_s=t_reg, print_s=t_print, n=len(rows),
               image_size=tuple(over["microscope"]["image_size"]))
    return lab, rows


def _fmt(v, spec=".3f") -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, spec)


def _median(v):
    return float(np.median(v)) if len(v) else float("nan")


def lab_line(lab: dict, rows: list[dict]) -> str:
    from unscatter.lab import describe_lab

    err = [r["rms_px"] for r in rows if r["status"] == "ok"]
    scored = [r for r in rows if "iou" in r and r["truth_solid"] > 0]
    H, W = lab["image_size"]
    return (f"lab {lab['index']}: {describe_lab(lab['overrides'])}\n"
            f"    failed {sum(r['status'] == 'failed' for r in rows)}/{len(rows)}, "
            f"empty {sum(r['status'] == 'empty' for r in rows)}, "
            f"silently wrong {sum(r['silently_wrong'] for r in rows)}, "
            f"pose error median {_fmt(_median(err))} max {_fmt(max(err) if err else float('nan'))} px, "
            f"IoU {_fmt(np.mean([r['iou'] for r in scored]) if scored else float('nan'), '.4f')} "
            f"(perfect {_fmt(np.mean([r['iou_perfect'] for r in scored if 'iou_perfect' in r]) if scored else float('nan'), '.4f')}), "
            f"registration {lab['register_s']:.1f} s for {lab['n']} prints of {H}x{W}")


def summarize(seed: int, labs: list[dict], rows: list[dict], cmd: str) -> str:
    n = len(rows)
    failed = [r for r in rows if r["status"] == "failed"]
    silent = [r for r in rows if r["silently_wrong"]]
    ok_err = np.array([r["rms_px"] for r in rows if r["status"] == "ok"])
    scored = [r for r in rows if "iou" in r and r["truth_solid"] > 0]
    mean_iou = float(np.mean([r["iou"] for r in scored])) if scored else float("nan")
    mean_perf = float(np.mean([r["iou_perfect"] for r in scored if "iou_perfect" in r])) if scored else float("nan")
    per32 = np.array([lab["register_s"] * 32 / lab["n"] for lab in labs])
    mpx = np.array([lab["image_size"][0] * lab["image_size"][1] for lab in labs]) / 720**2
    med_err = _median(ok_err)
    L = [f"seed {seed}: {len(labs)} random labs x {n // max(len(labs), 1)} test prints  ({cmd})", ""]
    L += [lab_line(lab, [r for r in rows if r["lab"] == lab["index"]]) for lab in labs]
    L += ["", f"  {'totals':30s}{'measured':32s}{'target':24s}"]

    def line(name, measured, target, met):
        L.append(f"  {name:30s}{measured:32s}{target:24s}{'met' if met else 'NOT MET'}")

    line("silently wrong", f"{len(silent)} of {n}", f"{TARGETS['silently_wrong']}", len(silent) <= TARGETS["silently_wrong"])
    line("failed", f"{len(failed)} of {n} ({100 * len(failed) / n:.1f} %)", f"<= {TARGETS['failed_pct']:g} %",
         100 * len(failed) / n <= TARGETS["failed_pct"])
    line("pose error of ok prints", f"median {_fmt(med_err)}, p95 {_fmt(float(np.quantile(ok_err, 0.95)) if len(ok_err) else float('nan'))} px",
         f"median <= {TARGETS['median_pose_px']:g} px", med_err <= TARGETS["median_pose_px"])
    line("mean IoU (perfect reg.)", f"{mean_iou:.4f} ({mean_perf:.4f})", f"gap <= {TARGETS['iou_gap']:g}",
         mean_perf - mean_iou <= TARGETS["iou_gap"])
    line("registration s / 32 prints", f"median {np.median(per32):.1f}, max {per32.max():.1f}",
         f"<= {TARGETS['seconds_per_32']:g} (720x720)", float(np.max(per32 / mpx)) <= TARGETS["seconds_per_32"])
    L.append(f"  (images of {', '.join(f'{h}x{w}' for h, w in (lab['image_size'] for lab in labs))}; judged on the time "
             f"scaled to 720x720 by pixel count: median {np.median(per32 / mpx):.1f} s, max {np.max(per32 / mpx):.1f} s)")
    L.append(f"  mean IoU over the {len(scored)} ok or empty prints whose truth is not empty; failed prints have no print")
    L += qc_lines(rows)
    L += reason_lines(rows)
    L += magnification_lines(labs, rows)
    L += metadata_lines(labs, rows)
    L += offset_lines(labs, rows)
    L += tail_lines(labs, rows)
    L += ["", f"silently wrong ({len(silent)}): ok with pose error > {SILENT_POSE_PX} px, or empty with truth solid > {SILENT_EMPTY_SOLID}"]
    for r in sorted(silent, key=lambda r: -r.get("rms_px", 0)):
        L.append(f"  lab {r['lab']}  {r['id']:22s} {r['pattern']:15s} {r['status']:6s} pose error {_fmt(r.get('rms_px'), '.2f')} px  "
                 f"IoU {_fmt(r.get('iou'), '.3f')} (perfect {_fmt(r.get('iou_perfect'), '.3f')})  truth solid {r['truth_solid']:.4f}")
    L += ["", f"failed ({len(failed)}):"]
    for r in failed:
        L.append(f"  lab {r['lab']}  {r['id']:22s} {r['pattern']:15s} pose error {_fmt(r.get('rms_px'), '.2f')} px  {r['reason']}")
    L += ["", f"  {'per pattern':15s} {'n':>3s} {'failed':>7s} {'empty':>6s} {'silently wrong':>15s} {'median pose error (ok)':>26s}  mean IoU (perfect)"]
    for pat in sorted({r["pattern"] for r in rows}):
        rr = [r for r in rows if r["pattern"] == pat]
        e = [r["rms_px"] for r in rr if r["status"] == "ok"]
        sc = [r for r in rr if "iou" in r and r["truth_solid"] > 0]
        perf = [r["iou_perfect"] for r in sc if "iou_perfect" in r]
        L.append(f"  {pat:15s} {len(rr):3d} {sum(r['status'] == 'failed' for r in rr):7d} {sum(r['status'] == 'empty' for r in rr):6d}"
                 f" {sum(r['silently_wrong'] for r in rr):15d} {_fmt(_median(e)):>23s} px"
                 f"  {_fmt(float(np.mean([r['iou'] for r in sc])) if sc else float('nan'), '.4f')}"
                 f" ({_fmt(float(np.mean(perf)) if perf else float('nan'), '.4f')})")
    return "\n".join(L)


def stated_kind(over: dict) -> str:
    """How a drawn lab states its camera pixel size (``lab.random``): none, calibrated
    (within its stated tolerance), nominal (no tolerance stated) or stale (off by more
    than the tolerance it states)."""
    md = over["microscope"].get("pixel_size_metadata")
    if not md:
        return "none"
    if not md.get("tolerance"):
        return "nominal"
    return "calibrated" if abs(md["error"]) <= md["tolerance"] else "stale"


def _by_kind(title: str, kind_of, kinds: tuple, labs: list[dict], rows: list[dict]) -> list[str]:
    """Failures and silent errors of the prints grouped by a kind of their lab
    (``kind_of``: the lab's overrides -> one of ``kinds``)."""
    kind = {lab["index"]: kind_of(lab["overrides"]) for lab in labs}
    parts = []
    for k in kinds:
        rr = [r for r in rows if kind[r["lab"]] == k]
        if rr:
            parts.append(f"{k} ({sum(v == k for v in kind.values())} labs) {sum(r['status'] == 'failed' for r in rr)} failed, "
                         f"{sum(r['silently_wrong'] for r in rr)} silently wrong of {len(rr)}")
    return [f"  by {title}: " + "; ".join(parts)]


def magnification_kind(over: dict) -> str:
    """How a drawn lab's magnification varies between images (``lab.random``): one
    objective (only refocusing changes it, 0.4 % at most), a zoom set by hand per image
    (a narrow range) or the whole range."""
    from unscatter.lab.random import RANGES

    lo, hi = over["microscope"]["scale"]
    if hi / lo < 1.005:
        return "one objective"
    return "whole range" if (lo, hi) == tuple(RANGES["scale"]) else "zoom per image"


def magnification_lines(labs: list[dict], rows: list[dict]) -> list[str]:
    """Failures and silent errors by how the lab's magnification varies by image."""
    return _by_kind("the lab's magnification", magnification_kind, ("one objective", "zoom per image", "whole range"),
                    labs, rows)


def metadata_lines(labs: list[dict], rows: list[dict]) -> list[str]:
    """Failures and silent errors by how the lab states its camera pixel size."""
    return _by_kind("the camera pixel size the lab states", stated_kind, ("none", "nominal", "calibrated", "stale"), labs, rows)


def offset_kind(over: dict) -> str:
    """How a drawn lab states its camera's dark offset (``lab.random``): declared with
    16-bit or 8-bit images, or not declared (the registration then takes 0)."""
    m = over["microscope"]
    if not m.get("declare_offset", True):
        return "undeclared"
    return f"declared, {m.get('format', 'tif16')}"


def offset_lines(labs: list[dict], rows: list[dict]) -> list[str]:
    """Failures and silent errors by how the lab states its camera offset: an offset the
    registration does not subtract makes polymer read brighter in a dimmer image, in
    units of its background (docs/registration.md, "Camera offsets")."""
    return _by_kind("the camera offset the lab states", offset_kind, ("declared, tif16", "declared, png8", "undeclared"),
                    labs, rows)


def tail_lines(labs: list[dict], rows: list[dict]) -> list[str]:
    """Failures, silent errors and the ok prints' pose error by the share of the lab's
    scattering kernel in its heavy tail: the print template's tail is the part of it
    that a batch's prints pin down least (docs/registration.md)."""
    share = {lab["index"]: float(((lab["overrides"].get("printer", {}).get("kernel") or {}).get("heavy_tail") or {})
                                 .get("fraction", 0.0)) for lab in labs}
    parts = []
    for lo, hi in ((0.0, 0.1), (0.1, 0.25), (0.25, np.inf)):
        idx = [k for k, v in share.items() if lo <= v < hi]
        rr = [r for r in rows if r["lab"] in idx]
        if rr:
            err = [r["rms_px"] for r in rr if r["status"] == "ok" and np.isfinite(r.get("rms_px", np.nan))]
            parts.append(f"{f'{lo:g} to {hi:g}' if np.isfinite(hi) else f'{lo:g} and above'} ({len(idx)} labs) {sum(r['status'] == 'failed' for r in rr)} failed, "
                         f"{sum(r['silently_wrong'] for r in rr)} silently wrong of {len(rr)}, ok median {_fmt(_median(err))} px")
    return ["  by the lab's heavy-tail share of scattered light: " + "; ".join(parts)]


def qc_lines(rows: list[dict]) -> list[str]:
    """Whether QC's verdicts match the truth: the failed prints split by their true pose
    error (a failure with the pose in fact within SILENT_POSE_PX is QC too cautious; one
    further off, QC catching a wrong pose; no pose: nothing to register, or no pose
    refined), and the ok prints' true error against the spreads QC judged them by
    (``pose_sd``: noise and template misfit; ``size_sd``: feature sizes, alone and in
    quadrature with ``model_sd``, the scatter kernel's shape, as QC weighs them)."""
    failed = [r for r in rows if r["status"] == "failed"]
    err = np.array([r.get("rms_px", np.nan) for r in failed], float)
    good, off = int(np.sum(err <= SILENT_POSE_PX)), int(np.sum(err > SILENT_POSE_PX))
    L = [f"  failed prints by their true pose error: {good} within {SILENT_POSE_PX} px (QC too cautious), {off} further "
         f"off (QC right), {len(failed) - good - off} without a pose"]
    ok = [r for r in rows if r["status"] == "ok" and np.isfinite(r.get("rms_px", np.nan))]
    e = np.array([r["rms_px"] for r in ok])
    spreads = {name: np.array([r.get(name, np.nan) for r in ok], float) for name in ("pose_sd", "size_sd")}
    # the kernel's move is a sensitivity, not a spread of its own: QC weighs it with size_sd
    spreads["size_sd with model_sd"] = np.hypot(spreads["size_sd"], np.nan_to_num(np.array([r.get("model_sd", 0.0) for r in ok], float)))
    for name, sd in spreads.items():
        keep = np.isfinite(sd) & (sd > 0)
        if keep.any():
            z = e[keep] / sd[keep]
            L.append(f"  ok prints' true pose error / {name}: median {np.median(z):.2f}, p90 {np.quantile(z, 0.9):.2f}, "
                     f"above 3: {int(np.sum(z > 3))} of {int(keep.sum())} (if the spread held the error: a median near 1, "
                     f"few above 3)")
    return L


REASON_KINDS = (  # qc.tsv reason prefixes, in the order reason_lines reports them
    ("faint", ("faint",)),
    ("above only the stain's threshold", ("not registered:",)),
    ("scale rests on a feature's size", ("pose not determined by the print: its scale rests",)),
    ("scale held, pose rests on sizes", ("pose not determined by the print: its scale held",)),
    ("pose rests on the kernel's shape", ("pose not determined by the print: it rests on the shape",)),
    ("pose rests on edges off the batch's", ("pose rests on edges off",)),
    ("pose rests on the lamp's field", ("pose rests on the lamp's field",)),
    ("pose uncertain or free", ("pose not determined by the print: uncertain", "pose not determined by the print: free")),
    ("ambiguous: the mask's symmetry", ("ambiguous: the mask maps",)),
    ("ambiguous: a rival pose", ("ambiguous: a pose",)),
    ("near the threshold", ("near the threshold",)),
    ("does not match its mask", ("does not match",)),
    ("did not converge", ("pose refinement did not converge",)),
    ("scale or rotation off", ("scale ", "rotation ")),
    ("score, coverage, not a print image", ("registration score", "print extends", "not a print image", "polymer in the image")),
)


def reason_kinds(reason: str) -> set:
    """The kinds (REASON_KINDS) of a failed print's QC reasons."""
    parts = reason.split("; ")
    return {name for name, prefixes in REASON_KINDS if any(p.startswith(prefixes) for p in parts)}


def reason_lines(rows: list[dict]) -> list[str]:
    """The failed prints by the kind of their QC reasons (a print may give several), each
    split by its true pose error as ``qc_lines`` splits them, and for the faint ones
    whether the lab printed anything there (truth solid above SILENT_EMPTY_SOLID)."""
    failed = [r for r in rows if r["status"] == "failed"]
    L = [f"  failed prints by the kind of their reasons (a print may give several): within {SILENT_POSE_PX} px / "
         f"further off / no pose"]
    for name, _ in REASON_KINDS:
        rr = [r for r in failed if name in reason_kinds(r["reason"])]
        if not rr:
            continue
        err = np.array([r.get("rms_px", np.nan) for r in rr], float)
        good, off = int(np.sum(err <= SILENT_POSE_PX)), int(np.sum(err > SILENT_POSE_PX))
        extra = ""
        if name == "faint":
            printed = sum(r["truth_solid"] > SILENT_EMPTY_SOLID for r in rr)
            extra = f"  (the lab printed {printed} of them; the rest cured nothing or under {SILENT_EMPTY_SOLID} of the field)"
        L.append(f"    {name:34s} {len(rr):4d}: {good:3d} / {off:3d} / {len(rr) - good - off:3d}{extra}")
    return L


def worst_sheet(rows: list[dict], root: Path, out_path: Path, count: int = 24, thumb: int = 256, cols: int = 6) -> None:
    """The overlays of the worst prints, labelled: silently wrong first, then failed, then
    the largest pose errors (red: registered mask contour, green: thresholded print).
    Each kind gets at least a share of the sheet when there are more of the others."""
    from PIL import Image, ImageDraw

    def cat(r):
        return 0 if r["silently_wrong"] else 1 if r["status"] == "failed" else 2

    def rank(r):
        return cat(r), -r.get("rms_px", -1.0)

    ranked = [r for r in sorted(rows, key=rank) if (root / f"lab_{r['lab']:02d}" / "reg" / "overlays" / f"{r['id']}.png").is_file()]
    quota = {0: count // 2, 1: count // 4, 2: count - count // 2 - count // 4}
    first = [r for c in (0, 1, 2) for r in [r for r in ranked if cat(r) == c][: quota[c]]]
    rest = [r for r in ranked if not any(r is f for f in first)]
    pick = sorted(first + rest[: count - len(first)], key=rank)
    head = 40
    ncols = min(cols, max(len(pick), 1))
    nrows = max(1, (len(pick) + ncols - 1) // ncols)
    sheet = Image.new("RGB", (ncols * thumb, nrows * (thumb + head)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for k, r in enumerate(pick):
        x, y = (k % ncols) * thumb, (k // ncols) * (thumb + head)
        with Image.open(root / f"lab_{r['lab']:02d}" / "reg" / "overlays" / f"{r['id']}.png") as im:
            sheet.paste(im.convert("RGB").resize((thumb, thumb)), (x, y + head))
        tag = "SILENTLY WRONG" if r["silently_wrong"] else r["status"]
        colour = (200, 0, 0) if r["silently_wrong"] else (200, 110, 0) if r["status"] == "failed" else (0, 0, 0)
        draw.text((x + 2, y + 1), f"lab {r['lab']} {r['id']}", fill=(0, 0, 0))
        draw.text((x + 2, y + 13), f"{tag}  pose {_fmt(r.get('rms_px'), '.2f')} px  IoU {_fmt(r.get('iou'), '.2f')}", fill=colour)
        draw.text((x + 2, y + 25), (r.get("reason") or "")[:42], fill=(90, 90, 90))
    out_path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out_path)


def perturb_template(rel: float, seed: int) -> None:
    """``--perturb-template``: every fit of a batch's print template that the registration
    calls (``unscatter.imaging.batch.fit_template``; the refits inside ``fit_hot_spot``
    are not moved) starts from its numbers times 1 + ``rel`` N(0, 1), the draws the same
    for every fit of a run (``seed``)."""
    import unscatter.imaging.batch as batch

    fit = batch.fit_template

    def moved(tmpl, pairs, x, *args, **kw):
        x = np.asarray(x, float)
        return fit(tmpl, pairs, x * (1.0 + rel * np.random.default_rng(seed).standard_normal(x.shape)), *args, **kw)

    batch.fit_template = moved


def random_labs(a) -> None:
    seed = a.seed if a.seed is not None else int(np.random.SeedSequence().generate_state(1)[0])
    if a.perturb_template:
        perturb_template(a.perturb_template, a.perturb_seed)
    try:
        out = benchmark_output_dir(a.out or Path("benchmarks/out/registration_labs"), script="benchmarks/bench_registration.py")
    except InputError as exc:
        sys.exit(f"error: {exc}")
    cmd = (f"python benchmarks/bench_registration.py --labs {a.labs} --prints {a.prints} --seed {seed} --threads {a.threads}"
           + (f" --masks {a.masks}" if a.masks != "test" else "")
           + (f" --perturb-template {a.perturb_template:g} --perturb-seed {a.perturb_seed}" if a.perturb_template else ""))
    print(f"seed {seed} (repeat with: {cmd})", flush=True)
    logging.getLogger("unscatter.imaging").setLevel(logging.ERROR)  # failures are in the tables below
    labs, rows = [], []
    for i in range(a.labs):
        lab, rr = run_lab(i, seed, a.prints, out, a.threads, a.masks)
        labs.append(lab)
        rows += rr
        print(lab_line(lab, rr) + f" (printing {lab['print_s']:.1f} s)", flush=True)
    cols = ["lab", "id", "pattern", "status", "reason", "rms_px", "iou", "iou_perfect", "truth_solid", "silently_wrong",
            "score", "rotation_deg", "true_rotation_deg", "scale", "true_scale", "pose_sd", "size_sd", "model_sd"]
    write_tsv(out / "prints.tsv", rows, cols)
    write_yaml(out / "labs.yaml", dict(seed=seed, labs={f"lab_{lab['index']:02d}": lab["overrides"] for lab in labs}))
    text = summarize(seed, labs, rows, cmd)
    (out / "summary.txt").write_text(text + "\n")
    worst_sheet(rows, out, out / "worst.png")
    print()
    print(text)
    print(f"\nwrote {out / 'prints.tsv'}, {out / 'summary.txt'}, {out / 'labs.yaml'}, {out / 'worst.png'}")


def _set(cfg: dict, assignment: str) -> str:
    """Apply KEY=VALUE (dotted KEY, VALUE in YAML) to ``cfg``; returns the assignment."""
    key, sep, value = assignment.partition("=")
    if not sep or not key:
        sys.exit(f"error: --set {assignment!r}: expected KEY=VALUE, e.g. printer.kernel.heavy_tail.fraction=0")
    node, parts = cfg, key.split(".")
    for k in parts[:-1]:
        if not isinstance(node.get(k), dict):
            sys.exit(f"error: --set {assignment!r}: the lab config has no section {k!r} on the way to {key!r}")
        node = node[k]
    if parts[-1] not in node:
        sys.exit(f"error: --set {assignment!r}: the lab config has no {key!r}")
    node[parts[-1]] = yaml.safe_load(value)
    return assignment


def reprint(a) -> None:
    """``--reprint``: the ablation of one lab's physics (see the module's docstring)."""
    from unscatter.imaging import register_batch
    from unscatter.lab import print_batch

    src = a.reprint
    truth = src / "batch.truth"
    for need in (src / "masks", src / "reg" / "qc.tsv", truth / "lab_config.yaml", truth / "transforms.tsv"):
        if not need.exists():
            sys.exit(f"error: --reprint {src}: {need} is missing (a lab folder of a bench_registration.py --labs run)")
    cfg = read_yaml(truth / "lab_config.yaml")
    changes = [_set(cfg, kv) for kv in a.set or []]
    out = Path(a.out or "benchmarks/out/registration_reprint")
    if out.resolve() == src.resolve() or out.resolve() in src.resolve().parents:
        sys.exit(f"error: --out {out} holds the lab it would reprint ({src}); it is emptied for a new run: choose another")
    try:
        out = benchmark_output_dir(out, script="benchmarks/bench_registration.py")
    except InputError as exc:
        sys.exit(f"error: {exc}")
    write_yaml(out / "lab_config.yaml", cfg)
    exposures = {r["id"]: float(r["exposure"]) for r in read_tsv(truth / "transforms.tsv")}
    print_batch(src / "masks", out / "batch", lab_config=out / "lab_config.yaml", seed=cfg.get("seed"), progress=False,
                exposures=exposures)
    logging.getLogger("unscatter.imaging").setLevel(logging.ERROR)
    t0 = time.perf_counter()
    register_batch(out / "batch", out / "reg", skip_failed=True, threads=a.threads, progress=False)
    dt = time.perf_counter() - t0
    before = {r["id"]: r for r in evaluate(src / "reg", truth)}
    after = {r["id"]: r for r in evaluate(out / "reg", out / "batch.truth")}

    def verdict(r):
        return "SILENTLY WRONG" if silently_wrong(r) else r["status"]

    L = [f"{src} reprinted with {', '.join(changes) or 'no change'}; registration {dt:.1f} s", "",
         f"  {'id':22s} {'before':>14s} {'pose error':>10s}   {'after':>14s} {'pose error':>10s}"]
    for mid in sorted(before):
        b, c = before[mid], after[mid]
        L.append(f"  {mid:22s} {verdict(b):>14s} {_fmt(b.get('rms_px'), '.2f'):>10s}   {verdict(c):>14s} {_fmt(c.get('rms_px'), '.2f'):>10s}")
    for name, rr in (("before", before), ("after", after)):
        ok = [r["rms_px"] for r in rr.values() if r["status"] == "ok"]
        L.append(f"  {name}: {sum(r['status'] == 'failed' for r in rr.values())} failed, {sum(silently_wrong(r) for r in rr.values())} "
                 f"silently wrong of {len(rr)}, pose error of ok prints median {_fmt(_median(ok))} px")
    text = "\n".join(L)
    (out / "summary.txt").write_text(text + "\n")
    print(text)
    print(f"\nwrote {out / 'summary.txt'}, {out / 'reg'}")


def against(a) -> None:
    """Two runs of the same labs compared print by print (``--against A B``)."""
    dirs = [Path(d) for d in a.against]
    runs = []
    for d in dirs:
        try:
            runs.append(({(int(r["lab"]), r["id"]): r for r in read_tsv(d / "prints.tsv")}, read_yaml(d / "labs.yaml")))
        except (InputError, OSError) as exc:
            sys.exit(f"error: {d}: not the output of a --labs run ({exc})")
    (ra, la), (rb, lb) = runs
    if la.get("seed") != lb.get("seed") or set(ra) != set(rb):
        sys.exit(f"error: {dirs[0]} and {dirs[1]} are not runs of the same labs (seeds {la.get('seed')} and "
                 f"{lb.get('seed')}, {len(ra)} and {len(rb)} prints)")
    labs = sorted({k[0] for k in ra})
    poses = [{(lab, r["id"]): _matrix(r) for lab in labs for r in read_tsv(d / f"lab_{lab:02d}" / "reg" / "qc.tsv")}
             for d in dirs]  # the registered design->image matrices of each run (None: no pose)
    rows, lines = [], []
    for key in sorted(ra):
        A, B = ra[key], rb[key]
        Ma, Mb = (p.get(key) for p in poses)
        rows.append(dict(lab=key[0], id=key[1], pattern=A["pattern"], status_a=A["status"], status_b=B["status"],
                         rms_px_a=A["rms_px"], rms_px_b=B["rms_px"], silently_wrong_a=A["silently_wrong"],
                         silently_wrong_b=B["silently_wrong"],
                         apart_px=transform_rms_px(Ma, Mb, 512) if Ma is not None and Mb is not None else float("nan")))
    apart = np.array([r["apart_px"] for r in rows], float)
    apart = apart[np.isfinite(apart)]

    def wrong(r, k):
        return str(r[f"silently_wrong_{k}"]) in ("1", "True")

    flips = [r for r in rows if r["status_a"] != r["status_b"]]
    silent = [[r for r in rows if wrong(r, k)] for k in "ab"]
    lines.append(f"{len(rows)} prints of {len({r['lab'] for r in rows})} labs (seed {la.get('seed')}): A = {dirs[0]}, "
                 f"B = {dirs[1]}")
    lines.append(f"verdict differs: {len(flips)}; silently wrong: A {len(silent[0])}, B {len(silent[1])}")
    if apart.size:
        lines.append(f"registrations apart (mask px, RMS over the field): median {np.median(apart):.3f}, "
                     f"90th percentile {np.percentile(apart, 90):.3f}, largest {apart.max():.3f}; "
                     f"over 0.5 px: {int((apart > 0.5).sum())}, over 1.5 px: {int((apart > 1.5).sum())}")
    for lab in sorted({r["lab"] for r in rows}):
        ta, tb = (read_yaml(d / f"lab_{lab:02d}" / "reg" / "registration.yaml").get("print_template") or {} for d in dirs)
        diff = sorted(((abs(float(ta[k]) - float(tb[k])) / max(abs(float(ta[k])), abs(float(tb[k])), 0.05), k)
                       for k in ta if k in tb), reverse=True)[:4]
        sub = [r["apart_px"] for r in rows if r["lab"] == lab and np.isfinite(r["apart_px"])]
        lines.append(f"lab {lab}: prints apart median {_fmt(_median(sub))} px; template numbers that differ most: "
                     + ", ".join(f"{k} {float(ta[k]):.3g} / {float(tb[k]):.3g}" for _, k in diff))
    lines.append("prints whose verdict differs or that are silently wrong in either (lab, id, A, B, apart px):")
    for r in rows:
        if r["status_a"] != r["status_b"] or wrong(r, "a") or wrong(r, "b"):
            def v(k):
                return f"{r['status_' + k]} {_fmt(_float(r['rms_px_' + k]), '.2f')} px" + (" SILENTLY WRONG" if wrong(r, k) else "")
            lines.append(f"  {r['lab']} {r['id']:<22} {v('a'):<30} {v('b'):<30} {_fmt(r['apart_px'], '.2f')}")
    text = "\n".join(lines)
    out = a.out or dirs[1]
    out.mkdir(parents=True, exist_ok=True)
    write_tsv(out / "against.tsv", rows, list(rows[0]))
    (out / "against.txt").write_text(text + "\n")
    print(text)
    print(f"\nwrote {out / 'against.tsv'}, {out / 'against.txt'}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--count", type=int, default=32, help="trial masks (one lab)")
    ap.add_argument("--seed", type=int, default=None, help="one lab: 3 if not given; random labs: drawn and printed if not given")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--lab-config", type=Path, help="overrides of the default lab (one lab)")
    ap.add_argument("--labs", type=int, default=0, help="number of random labs (0: one lab)")
    ap.add_argument("--prints", type=int, default=32, help="test prints per random lab")
    ap.add_argument("--masks", choices=("test", "paper", "paper-marked", "pool", "marked"), default="test",
                    help="random labs: test patterns; the paper's random trial masks without (paper) or with "
                         "(paper-marked) the registration marks; or the trial-mask design's candidates without (pool) "
                         "or with (marked) them")
    ap.add_argument("--threads", type=int, default=2, help="registration threads (the workflow uses 2)")
    ap.add_argument("--reprint", type=Path, help="a lab folder of a --labs run: print it again with --set changes")
    ap.add_argument("--set", action="append", metavar="KEY=VALUE",
                    help="with --reprint: a change to the lab's config (dotted key, YAML value); repeatable")
    ap.add_argument("--perturb-template", type=float, default=0.0, metavar="REL",
                    help="random labs: move the start of each template fit by this relative amount (a probe of how "
                         "far the results rest on the arithmetic's last bits)")
    ap.add_argument("--perturb-seed", type=int, default=1, help="with --perturb-template: the draw")
    ap.add_argument("--against", type=Path, nargs=2, metavar=("DIR_A", "DIR_B"),
                    help="two --labs runs of the same labs (another machine or arithmetic): compared print by print")
    a = ap.parse_args()
    if a.perturb_template and not a.labs:
        ap.error("--perturb-template needs --labs")
    if a.set and not a.reprint:
        ap.error("--set needs --reprint")
    if a.against:
        against(a)
    elif a.reprint:
        reprint(a)
    elif a.labs:
        random_labs(a)
    else:
        single_lab(a)


if __name__ == "__main__":
    main()
