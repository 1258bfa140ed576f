"""Benchmark of the residual diagnosis (not a test): does the loop name the lab's effect,
how much does it lower the held-out error, and how long does it take.

    python benchmarks/bench_diagnosis.py [--quick] [--scenarios a,b,...] [--size N] [--count N]
    python benchmarks/bench_diagnosis.py --random-labs N [--seed S] [--quick] [--objective dice] [--registered]
        [--trial designed [--criterion d|discrimination|paired] [--noise edge|pixel]] [--workers N] [--sigma-um LO,HI]
        [--declare-blur]

Random labs (``--random-labs N``, issue #12): every run draws a new seed (printed; ``--seed``
reproduces it, with the same N). Each lab is ``unscatter.lab.random_lab`` (cure, kernel, noise and field
over wide ranges) with every effect beyond Eq. 1 off but one, drawn in shuffled rounds
from none, heavy_tail, anisotropy, dose_nonlinearity (gamma 0.6-0.8 or 1.3-1.8),
illumination_field (quartic +-0.15..0.3), edge_offset (+-3..7 um) and a lamp hotspot
(outside the library: right when the residual is flagged unexplained). The lab prints
32 trial masks (its true prints in mask coordinates: microscope and registration left
out, so only calibration and diagnosis are judged; ``--registered``: printed and imaged
by the whole random lab, its microscope, camera and metadata included, and registered
as the workflow does, failed prints skipped, with the same labs for the same seed);
``calibrate`` (defaults, no CV or
bootstrap) then ``diagnose`` (defaults, or ``quick``) run on them. Scored on 16 held-out
paper masks and 16 test patterns (gratings, near-threshold, dots, ...) against the lab's
noisy prints (``TRUTH_DRAWS`` independent prints of each mask, every score the mean over
them): IoU of Eq. 1, of the selected model, of the lab's noise-free printer and of the
floor (the per-pixel majority of ``FLOOR_VOTES`` other prints of the lab at the quantiles
of its print-to-print dose factor: the best its own printer predicts one print;
``held_out_truth``), as the mean of per-print IoU and pooled over the lab's held-out prints
(``metrics.pooled_iou``: a mask the lab prints nothing of weighs its stray pixels, not an
IoU of 0 or 1). Before 2026-12-06 one print a mask and a majority of 11 prints at drawn
factors: a lab's gap to the floor was then a draw (sd up to 0.008 between prints of the
same masks) and the floor 0.001 to 0.011 below the lab's noise-free printer. Effect sizes are drawn log-uniformly from barely detectable to
strong (``--strength strong``: the upper part only); "outside" labs hold one or two of OUTSIDE_PHYSICS (a
lamp hot spot, oxygen inhibition at edges, a kernel that widens with grey level). The
summary adds the power study's tables: the confusion matrix, detection against the
effect's size and against what Eq. 1 leaves to explain, false alarms and outside
effects flagged (``--summarize labs.tsv`` reprints them). ``--trial designed`` prints as many
designed trial masks (``design.design_masks`` at the prior, one design for every lab,
with the registration marks the workflow prints on them) instead of the paper's, into a
folder of its own (``..._designed``; ``--tag`` tells variants apart): run it with the same
seed, N and effects as a paper run, and the labs and held-out masks are the same.
``--criterion`` and ``--noise`` choose the design's criterion and its model of the print
noise (``design.NOISE``).
"1-IoU fx" is the effect's size (the lab's noise-free held-out prints with vs without
it); "trial" is what the trial masks show of it (``trial_share`` in labs.tsv: Eq. 1
calibrated on the lab's noise-free trial prints leaves ``trial_visible`` of their pixels
wrong, the most any candidate can gain there, over Eq. 1's held-out mismatch on the
lab's prints; the diagnosis accepts a gain of 3 % or more). The mask itself is scored beside the models (``pooled_iou_mask`` in labs.tsv: the
mask printed where its grey level reaches the threshold that fits the trial prints best,
``fitting.mask_threshold``), with whether the diagnosis said that no model beats it
(``beats_mask_flag``); ``--sigma-um LO,HI`` draws the labs' scattering over that range
instead (a sharp printer, where the mask is a strong baseline). Tables: ``benchmarks/out/diagnosis/seed<S>.../labs.tsv``, ``prints.tsv``, ``summary.txt``.

Measured on 2 shared CPU cores (other jobs running: times are rough), 1 torch thread,
``--quick`` (256 x 256, 32 prints, quick diagnosis). BEFORE: main at de62901; AFTER: the
multi-start candidate fits (``diagnosis.DEFAULTS['starts']``) and the kernel clamp of the
refinement, objective unchanged (the paper's mismatch):

    seed    labs  detection right/wrong/missed/false alarm   IoU gap to floor, median [max]   Eq. 1 gap   diagnosis s, median [max]
                  before        after                        before           after                     before      after
    451170  8     7/0/1/0       7/0/1/0                      0.0028 [0.0226]  0.0022 [0.0226]  0.0171    24 [58]     44 [55]
    605389  8     8/0/0/0       8/0/0/0                      -0.0002 [0.0436] -0.0012 [0.0436] 0.0331    34 [164]    47 [145]
    482586  8     6/0/2/0       7/0/1/0                      -0.0002 [0.0591] -0.0010 [0.0591] 0.0279    18 [69]     50 [271]*

(482586 was the fresh seed, drawn by the AFTER run. * the AFTER run shared the cores with
a test run. Times are rough on shared cores, but the multi-start costs: the diagnosis
took about 1.5-2x as long AFTER at --quick. The labs drawn depend on the seed and on N:
reproduce with the same --random-labs N.) Both misses on 482586 BEFORE are heavy tails (0.16 x 45 um, 0.17 x
31 um): the candidate fit stayed at tail_fraction 0 (+0.1 %) and 0.15 (+1.3 %); AFTER it
reaches 0.15 x 12.8 px (+4.2 %, named) and 0.22 x 10.4 px (+9.7 %, but the bootstrap
interval of the improvement touches 0: missed on power, Eq. 1 is 0.001 below the floor there).

The miss on 451170 is a quartic field of +0.27 (beyond the library's +-0.25): Eq. 1 absorbs it in
c1, c2 and T to 0.003 of the floor. The largest gaps are the hotspots (outside the
library; flagged unexplained, 0.02-0.04 below the floor). The heavy-tail labs gain most
from the multi-start (selected IoU 0.9878 -> 0.9897, floor 0.9887; fitted sigma 0.95 ->
0.99 of the lab's). Fitted sigma of Eq. 1 on labs whose kernel is the lab's Gaussian:
median 1.00 (0.96-1.07 but for gamma and edge-offset labs, where Eq. 1 bends sigma to
mimic them): without the microscope the calibration is not biased; the 15 % of issue
#12 comes from the measurement chain. Candidate fits alone (prints of the library model at random parameters, 24 trial masks
of 128 x 128, cell-like dose noise; fitted from Eq. 1's fit as the diagnosis does):
the heavy tail's held-out mismatch was 75 % above the true parameters' before the
multi-start (the fit stayed at tail_fraction 0), +4 % and -0.3 % after; over all five
effects, two draws each, median +0.4 %, max +7 % (the 4-parameter illumination field).
``--objective dice`` (1 - Dice per print) on seed
451170: 6 right, 1 missed, 1 false alarm (unexplained residual on the no-effect lab),
an extra anisotropy on the heavy-tail lab; selected IoU lower on 7 of 8 labs (median
gap to the floor 0.0042 vs 0.0022, fitted sigma 0.98 of the lab's): on prints that Eq. 1
and its effects describe, weighing each print alike adds the noise of the small prints
and buys nothing, so the paper's mismatch stays the default.

For each scenario the virtual lab prints ``count`` trial masks (its prints in mask
coordinates, microscope left out), Eq. 1 is calibrated on them as the workflow does
(``calibrate``, GA 48 x 30, no CV), and ``diagnose`` runs with its defaults (``--quick``:
256 x 256, 16 prints, ``quick=True``). Scenarios: the lab with everything beyond Eq. 1
off (``none``), each library effect alone, the lab's default (heavy tail on), a
combination (default + edge offset), and effects outside the library: a lamp hotspot,
which the low-order illumination terms only partly describe.

Measured on 2 shared CPU cores (torch 2.13 CPU, 1 torch thread), base calibration and
diagnosis wall times:

``python benchmarks/bench_diagnosis.py --quick`` (16 prints of 256 x 256, 3 folds, whole library):

    scenario            effects named            expected                IoU before -> after  pixel error before -> after  unexplained  cal  diagnosis
    none                -                        -                       0.9810 -> 0.9810     0.0192 -> 0.0192             no           10s   8s
    heavy_tail          heavy_tail               heavy_tail              0.9635 -> 0.9751     0.0378 -> 0.0252             no            8s  16s
    anisotropy          anisotropy               anisotropy              0.9679 -> 0.9822     0.0329 -> 0.0180             no            4s  18s
    dose_nonlinearity   dose_nonlinearity        dose_nonlinearity       0.9152 -> 0.9781     0.0882 -> 0.0224             no            4s  23s
    illumination_field  illumination_field       illumination_field      0.9744 -> 0.9766     0.0260 -> 0.0237             no            4s  14s
    edge_offset         edge_offset              edge_offset             0.9507 -> 0.9796     0.0524 -> 0.0206             no            4s  13s
    lab_default         heavy_tail               heavy_tail              0.9635 -> 0.9751     0.0378 -> 0.0252             no            4s  14s
    default+edge_offset edge_offset,heavy_tail   heavy_tail,edge_offset  0.9328 -> 0.9704     0.0702 -> 0.0303             no            4s  20s
    hotspot (outside)   -                        illumination_field      0.9741 -> 0.9741     0.0262 -> 0.0262             position      4s   7s

(lab_default is the heavy_tail scenario: the lab's default tail is that one. The hotspot
is not named, and the residual vs position is flagged as unexplained structure.)

``python benchmarks/bench_diagnosis.py --scenarios lab_default`` (32 prints of 512 x 512, 4 folds,
whole library, the defaults; the workflow's size):

    lab_default         heavy_tail               heavy_tail              0.9744 -> 0.9828     0.0261 -> 0.0174             no           15s  153s
    none                -                        -                       0.9845 -> 0.9845     0.0159 -> 0.0159             no           18s   71s
    edge_offset         edge_offset              edge_offset             0.9499 -> 0.9845     0.0548 -> 0.0160             no            8s  155s
    default+edge_offset edge_offset,heavy_tail,  heavy_tail,edge_offset  0.9521 -> 0.9806     0.0492 -> 0.0197             orientation   8s  285s
                        anisotropy
    hotspot (outside)   -                        illumination_field      0.9826 -> 0.9826     0.0176 -> 0.0176             density_10um, 8s   63s
                                                                                                                       position
(At 512 x 512 the erosion of default+edge_offset is named first, then the tail; a third
round adds a small anisotropy and orientation structure is still flagged: the lab erodes
with a disk of whole pixels, which the first-order edge offset does not quite describe.
Three rounds of the whole library take 285 s, at the edge of the 5-minute budget. The
hotspot is not named at either size; its residual vs position is flagged as unexplained.)
"""

from __future__ import annotations

import argparse
import copy
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from unscatter.calibration import calibrate
from unscatter.diagnosis import diagnose
from unscatter.fitting import mask_threshold, print_weights
from unscatter.io import write_png, write_tsv, write_yaml
from unscatter.masks import trial_masks
from unscatter.prints import load_prints
from unscatter.settings import DIAGNOSIS

GAIN_TEST = DIAGNOSIS.default.gain_test  # the diagnosis's test of a candidate's gain, where --gain-test does not name one
OFF = {"printer": {"kernel": {"heavy_tail": None, "anisotropy": {"ratio": 1.0, "angle_deg": 0.0}},
                   "illumination": {"quartic": 0.0, "hotspot": None}, "dose_gamma": 1.0, "edge_offset_um": 0.0}}
SCENARIOS = {
    "none": OFF,
    "heavy_tail": {"printer": {"kernel": {"heavy_tail": {"fraction": 0.25, "length_um": 60.0}}}},
    "anisotropy": {"printer": {"kernel": {"anisotropy": {"ratio": 1.8, "angle_deg": 30.0}}}},
    "dose_nonlinearity": {"printer": {"dose_gamma": 1.8}},
    "illumination_field": {"printer": {"illumination": {"quartic": -0.15}}},
    "edge_offset": {"printer": {"edge_offset_um": 6.0}},
    "lab_default": None,  # the lab as the workflow runs it: heavy tail on
    "default+edge_offset": {"printer": {"edge_offset_um": -6.0}},
    "hotspot (outside)": {"printer": {"illumination": {"hotspot": {"amplitude": 0.3, "x0": 0.35, "y0": -0.3, "width": 0.2}}}},
}
EXPECTED = {"none": [], "heavy_tail": ["heavy_tail"], "anisotropy": ["anisotropy"], "dose_nonlinearity": ["dose_nonlinearity"],
            "illumination_field": ["illumination_field"], "edge_offset": ["edge_offset"], "lab_default": ["heavy_tail"],
            "default+edge_offset": ["heavy_tail", "edge_offset"], "hotspot (outside)": ["illumination_field"]}


def _merge(a: dict, b: dict) -> dict:
    out = copy.deepcopy(a)
    for k, v in (b or {}).items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def overrides(name: str) -> dict | None:
    over = SCENARIOS[name]
    if name in ("lab_default", "default+edge_offset"):
        return over  # on top of the lab's defaults (heavy tail on)
    return _merge(OFF, over)


def lab_prints(out: Path, name: str, count: int, size: int) -> Path:
    from unscatter.lab import Printer, load_config

    cfg = load_config(overrides=overrides(name))
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
    return out


# ------------------------------------------------------------------ random labs

# one effect beyond Eq. 1 per random lab (or none); "hotspot" is outside the library
RANDOM_EFFECTS = ("none", "heavy_tail", "anisotropy", "dose_nonlinearity", "illumination_field", "edge_offset", "outside")
# physics of the lab that the model library lacks: an "outside" lab has one or two of them
OUTSIDE_PHYSICS = ("hotspot", "oxygen_inhibition", "kernel_dose_growth")
OUTSIDE = {"outside", *OUTSIDE_PHYSICS}
VERDICTS = ("right", "partial", "wrong", "missed", "false alarm")  # of one lab (``verdict``)


def random_effect_lab(rng: np.random.Generator, effect: str, strength: str = "wide") -> tuple[dict, str]:
    """Printer overrides of a random lab (``unscatter.lab.random_lab``: optics, noise and
    cure over wide ranges) with every effect beyond Eq. 1 off but ``effect``. With
    ``strength`` 'wide' the effect's magnitude is drawn log-uniformly from barely
    detectable to strong (the detection limit is read off the results); 'strong' keeps to
    the upper part. ``outside``: one or two of ``OUTSIDE_PHYSICS`` (not in the library).
    Returns (overrides, magnitude)."""
    from unscatter.lab import random_lab

    p = random_lab(rng)["printer"]
    p["kernel"]["heavy_tail"] = None
    p["kernel"]["anisotropy"] = {"ratio": 1.0, "angle_deg": 0.0}
    p["illumination"].update(quartic=0.0, hotspot=None)
    p["dose_gamma"] = 1.0
    p["edge_offset_um"] = 0.0
    sign = 1.0 if rng.random() < 0.5 else -1.0
    # the share of each effect's range drawn: log-uniform over [lo, 1] of its strong end
    lo = 0.08 if strength == "wide" else 0.5

    def amount(top: float, floor: float = 0.0) -> float:
        return floor + (top - floor) * float(np.exp(rng.uniform(np.log(lo), 0.0)))

    if effect == "none":
        mag = "-"
    elif effect == "heavy_tail":
        f, lam = amount(0.4), float(rng.uniform(25.0, 90.0))
        p["kernel"]["heavy_tail"] = {"fraction": f, "length_um": lam}
        mag = f"tail {f:.3f} x {lam:.0f} um"
    elif effect == "anisotropy":
        r, a = 1.0 + amount(0.8), float(rng.uniform(0.0, 180.0))
        p["kernel"]["anisotropy"] = {"ratio": r, "angle_deg": a}
        mag = f"ratio {r:.3f} at {a:.0f} deg"
    elif effect == "dose_nonlinearity":
        g = 1.0 + amount(0.8) if sign > 0 else 1.0 - amount(0.4)
        p["dose_gamma"] = g
        mag = f"gamma {g:.3f}"
    elif effect == "illumination_field":
        q = sign * amount(0.25)  # the library's bound
        p["illumination"]["quartic"] = q
        mag = f"quartic {q:+.3f}"
    elif effect == "edge_offset":
        e = sign * amount(7.0)
        p["edge_offset_um"] = e
        mag = f"edge {e:+.2f} um"
    elif effect in OUTSIDE:
        kinds = [effect] if effect != "outside" else list(rng.choice(OUTSIDE_PHYSICS, size=int(rng.integers(1, 3)),
                                                                     replace=False))
        parts = []
        for kind in kinds:
            if kind == "hotspot":
                hs = dict(amplitude=amount(0.4), x0=float(rng.uniform(-0.6, 0.6)), y0=float(rng.uniform(-0.6, 0.6)),
                          width=float(rng.uniform(0.12, 0.3)))
                p["illumination"]["hotspot"] = hs
                parts.append(f"hotspot {hs['amplitude']:.2f} w {hs['width']:.2f}")
            elif kind == "oxygen_inhibition":
                ox = dict(strength=amount(0.5), length_um=float(rng.uniform(8.0, 40.0)))
                p["oxygen_inhibition"] = ox
                parts.append(f"O2 {ox['strength']:.2f} over {ox['length_um']:.0f} um")
            else:
                k = amount(0.8)
                p["kernel_dose_growth"] = k
                parts.append(f"kernel x{1 + k:.2f} at full grey")
        mag = " + ".join(parts)
    else:
        raise ValueError(effect)
    return {"printer": p}, mag


def _with_sigma(lab: tuple[dict, str], lab_seed: int, args) -> tuple[dict, str]:
    """``--sigma-um LO,HI``: the lab's scattering sigma drawn log-uniformly over that range
    instead (from its own stream, so the rest of the lab is the same draw)."""
    over, mag = lab
    if args.sigma_um:
        lo, hi = (float(x) for x in args.sigma_um.split(","))
        over["printer"]["kernel"]["sigma_um"] = float(np.exp(np.random.default_rng([lab_seed, 17]).uniform(np.log(lo), np.log(hi))))
    return over, mag


TRUTH_DRAWS = 8  # independent noisy prints of each held-out mask that every model is scored against
FLOOR_VOTES = 31  # prints a held-out mask's floor is the per-pixel majority of


def _lab_truth(printer, level, masks: dict, seed: int) -> dict:
    """The lab's prints of ``masks`` in mask coordinates (the microscope left out: only
    calibration and diagnosis are judged), one noisy print each (id -> print)."""
    return {mid: printer.crop(printer.density(m, np.random.default_rng([seed, i]))) >= level
            for i, (mid, m) in enumerate(masks.items())}


def held_out_truth(printer, level, masks: dict, seed: int, draws: int = TRUTH_DRAWS, votes: int = FLOOR_VOTES):
    """The lab's held-out prints to score against and its floor.

    ``draws`` independent noisy prints of each mask (id -> list; the first is
    ``_lab_truth``'s print of ``seed``): a near-threshold mask prints anything from nothing
    to its whole extent under the lab's print-to-print dose noise, so one print a mask makes
    a lab's scores a draw (seen: a no-effect lab's Eq. 1 0.014 below a floor of 11 votes on
    one print a mask; against 8 other prints, level with the lab's noise-free printer and
    0.012 above that floor). The floor (id -> print; empty with ``votes``
    0): the per-pixel majority of ``votes`` more prints, the best the lab's own printer
    predicts one print (its noise-free print is not: erosion and swelling act on the noisy
    density). Their print-to-print dose factors are the ``votes`` quantiles of its
    distribution, not draws, so that the floor is not itself a print at a random dose (a
    majority of 11 drawn prints was 0.001 to 0.011 below the noise-free print in pooled
    IoU on 10 labs, and moved 0.03 from one set of 11 to another on a near-threshold lab).
    """
    from scipy.stats import norm

    prints = {mid: [p] for mid, p in _lab_truth(printer, level, masks, seed).items()}
    for k in range(1, draws):
        for mid, p in _lab_truth(printer, level, masks, int(np.random.default_rng([seed, 7919, k]).integers(1 << 31))).items():
            prints[mid].append(p)
    floor = {}
    if votes:
        cells = printer.cfg["cells"]
        steady = type(printer)({**printer.cfg, "cells": {**cells, "print_to_print": 0.0}}, printer.size, printer.pixel_um)
        factors = 1.0 + float(cells["print_to_print"]) * norm.ppf((np.arange(votes) + 0.5) / votes)
        for i, (mid, m) in enumerate(masks.items()):
            n = sum((steady.crop(steady.cure(steady.dose(m, np.random.default_rng([seed, i, 1 + v])) * f)) >= level).astype(int)
                    for v, f in enumerate(factors))
            floor[mid] = n > votes // 2
    return prints, floor


def scored(sims: dict, truth: dict, ids: list) -> tuple[dict, dict]:
    """Each model's IoU against the lab's draws (``held_out_truth``): per mask, the mean
    over the draws (id -> model -> IoU), and pooled over the masks (``metrics.pooled_iou``),
    the mean over the draws (model -> IoU)."""
    from unscatter import metrics

    draws = len(truth[ids[0]])
    per_mask = {mid: {k: float(np.mean([metrics.iou(v[j], t) for t in truth[mid]])) for k, v in sims.items()}
                for j, mid in enumerate(ids)}
    pooled = {k: float(np.mean([metrics.pooled_iou(list(v), [truth[mid][d] for mid in ids]) for d in range(draws)]))
              for k, v in sims.items()}
    return per_mask, pooled


def _write_batch(out: Path, masks: dict, prints: dict, px: float) -> Path:
    rows = []
    for mid, m in masks.items():
        write_png(out / "masks" / f"{mid}.png", m)
        write_png(out / f"{mid}.png", prints[mid])
        rows.append(dict(id=mid, status="ok" if prints[mid].any() else "empty", reason="", mask=f"masks/{mid}.png"))
    write_tsv(out / "qc.tsv", rows, ["id", "status", "reason", "mask"])
    write_yaml(out / "batch.yaml", dict(pixel_size_um=px))
    return out


REFERENCE = "dense_ref"  # the benchmarks' dense reference print, at 4 times the exposure (the id of the runs the
# docs report: the lab's own dense_reference option names it otherwise, and a print's noise follows its id)


def print_lab_batch(masks_dir: Path, batch_dir: Path, overrides: dict, seed: int, size: int, dense_reference: bool) -> None:
    """``print_batch`` of ``masks_dir``; with ``dense_reference`` one more print, a dense
    reference (``masks.dense_reference_mask`` at 4 times the exposure), named in batch.yaml."""
    from unscatter.io import read_yaml
    from unscatter.lab import print_batch
    from unscatter.masks import dense_reference_mask

    if dense_reference:
        write_png(masks_dir / f"{REFERENCE}.png", dense_reference_mask(size))
    print_batch(masks_dir, batch_dir, overrides=overrides, seed=seed, progress=False,
                exposures={REFERENCE: 4.0} if dense_reference else None)
    if dense_reference:
        write_yaml(batch_dir / "batch.yaml", {**read_yaml(batch_dir / "batch.yaml"), "dense_reference": [REFERENCE]})


def _registered_batch(d: Path, trial: dict, over: dict, lab_seed: int, size: int,
                      declare_blur: bool = False, dense_reference: bool = False, half_cure: bool = False) -> tuple[Path, dict]:
    """The trial masks printed and imaged by the whole random lab (``random_lab``'s
    microscope, camera and metadata drawn from ``lab_seed`` as ``random_effect_lab``
    drew its printer, with that printer), and registered as the workflow does: the
    prints the calibration and diagnosis get, failed prints skipped. Returns the
    registered folder and what the registration did (against the lab's true poses,
    ``bench_registration``). ``dense_reference``: the batch holds a dense reference
    (``masks.dense_reference_mask`` at 4 times the exposure, batch.yaml ``dense_reference``),
    on which the registration measures the fully cured level."""
    import bench_registration
    from unscatter.imaging import register_batch
    from unscatter.lab import random_lab
    from unscatter.lab.random import describe_lab

    full = dict(random_lab(np.random.default_rng(lab_seed)), printer=over["printer"])
    if declare_blur:  # batch.yaml states the microscope's blur (lab.run.psf_sigma_um): a calibration through the
        # measurement holds it
        full["microscope"] = dict(full["microscope"], declare_blur=True)
    for mid, m in trial.items():
        write_png(d / "masks" / f"{mid}.png", m)
    print_lab_batch(d / "masks", d / "batch", full, lab_seed, size, dense_reference)
    t0 = time.perf_counter()
    qc = register_batch(d / "batch", d / "prints", skip_failed=True, progress=False, half_cure=half_cure)
    t_reg = time.perf_counter() - t0
    rows = bench_registration.evaluate(d / "prints", d / "batch.truth", size=size)
    failed = sum(r["status"] == "failed" for r in qc)
    return d / "prints", dict(microscope=describe_lab(full).split(" | ")[0], prints_used=len(qc) - failed, failed=failed,
                              silently_wrong=sum(bench_registration.silently_wrong(r) for r in rows),
                              reg_s=round(t_reg, 1))


def verdict(effect: str, named: list, unexplained: bool) -> str:
    """right / wrong / missed / false alarm (and partial: an outside effect described by a
    library term without the residual flagged)."""
    if effect == "none":
        return "right" if not named and not unexplained else "false alarm"
    if effect in OUTSIDE:
        if unexplained:
            return "right"
        if named == ["illumination_field"]:
            return "partial"
        return "wrong" if named else "missed"
    if effect in named:
        return "right"
    return "wrong" if named else "missed"


def _designed_tag(args) -> str:
    """The output folder's suffix for the trial masks: '' (paper), '_designed', plus the
    design's criterion and noise model where they are not the defaults."""
    if args.trial != "designed":
        return ""
    return ("_designed" + (f"_{args.criterion}" if args.criterion != "d" else "")
            + (f"_{args.noise}noise" if args.noise else ""))


def random_labs(args) -> None:
    from unscatter import metrics
    from unscatter.lab import Printer, load_config
    from unscatter.masks import test_pattern_masks, test_pattern_of
    from unscatter.model import load_params, simulate

    seed = args.seed if args.seed is not None else int.from_bytes(os.urandom(4), "little") % 1_000_000
    size = args.size or (256 if args.quick else 512)
    count = args.count or 32
    held = args.heldout
    effects = args.effects.split(",") if args.effects else list(RANDOM_EFFECTS)
    # a run with other counts or sizes than the defaults gets its own folder (and says so in its command)
    shape = ((f"_n{count}" if count != 32 else "") + (f"_s{args.size}" if args.size else "")
             + (f"_h{held}" if held != 16 else ""))
    root = Path(args.out or "benchmarks/out/diagnosis") / (f"seed{seed}{'_quick' if args.quick else ''}{shape}"
                                                          f"{_designed_tag(args)}{'_registered' if args.registered else ''}"
                                                          f"{'_sigma' + args.sigma_um.replace(',', '-') if args.sigma_um else ''}"
                                                          f"{'_blur' if args.declare_blur else ''}"
                                                          f"{'_ref' if args.dense_reference else ''}"
                                                          f"{'_halfcure' if args.half_cure else ''}"
                                                          f"{'_' + args.gain_test + 'test' if args.gain_test != GAIN_TEST else ''}"
                                                          f"{args.tag}")
    root.mkdir(parents=True, exist_ok=True)
    cmd = (f"python benchmarks/bench_diagnosis.py --random-labs {args.random_labs} --seed {seed}"
           + (" --quick" if args.quick else "") + (f" --effects {args.effects}" if args.effects else "")
           + (f" --count {count}" if count != 32 else "") + (f" --size {args.size}" if args.size else "")
           + (f" --heldout {held}" if held != 16 else "")
           + (f" --strength {args.strength}" if args.strength != "wide" else "")
           + (f" --objective {args.objective}" if args.objective else "")
           + (f" --trial {args.trial}" if args.trial != "paper" else "")
           + (f" --criterion {args.criterion}" if args.trial == "designed" and args.criterion != "d" else "")
           + (f" --noise {args.noise}" if args.trial == "designed" and args.noise else "")
           + (" --registered" if args.registered else "") + (f" --sigma-um {args.sigma_um}" if args.sigma_um else "")
           + (" --declare-blur" if args.declare_blur else "")
           + (" --dense-reference" if args.dense_reference else "")
           + (" --half-cure" if args.half_cure else "")
           + (f" --gain-test {args.gain_test}" if args.gain_test != GAIN_TEST else "")
           + (f" --tag {args.tag}" if args.tag else ""))
    print(f"seed {seed} (reproduce: {cmd}); {count} trial prints + {held} paper + {held} test-pattern held-out masks "
          f"of {size}x{size}; {'quick' if args.quick else 'default'} diagnosis; outputs in {root}", flush=True)
    rng = np.random.default_rng(seed)
    order = []
    while len(order) < args.random_labs:  # every effect once per round, shuffled
        order += [effects[i] for i in rng.permutation(len(effects))]
    if args.trial == "designed":  # one design at the prior for every lab (as the paper masks are one draw)
        from unscatter import design

        if args.noise:
            design.NOISE = args.noise
        t0 = time.perf_counter()
        trial = design.design_masks(count, seed=0, size=size, progress=False, compare=False,
                                    criterion=args.criterion)["masks"]
        print(f"{count} designed trial masks in {time.perf_counter() - t0:.0f} s", flush=True)
    else:
        trial = trial_masks(count, seed=0, size=size)
    ho_masks = {f"paper_{k}": v for k, v in trial_masks(held, seed=seed % 100_000 + 1, size=size).items()}
    ho_masks.update(test_pattern_masks(held, seed=seed, size=size))
    lab_rows, print_rows = [], []
    head = (f"{'lab':<4}{'effect':<19}{'magnitude':<27}{'1-IoU fx':>9}{'trial':>7}  {'named':<32}{'unexpl.':<8}{'verdict':<12}{'IoU eq1':>8}{'sel':>7}"
            f"{'floor':>7}{'gap':>7}{'pooled eq1/sel/floor':>22}{'pat eq1':>8}{'pat sel':>8}{'pat flr':>8}{'sig fit/lab':>12}{'T fit/lab':>10}{'cal':>6}{'diag':>6}")
    print(head, flush=True)
    lines = [head]
    for li, effect in enumerate(order[: args.random_labs]):
        lab_seed = int(rng.integers(1 << 31))
        over, mag = _with_sigma(random_effect_lab(np.random.default_rng(lab_seed), effect, args.strength), lab_seed, args)
        cfg = load_config(overrides=over)
        px = cfg["batch"]["pixel_size_um"]
        level = cfg["microscope"]["level"]
        printer = Printer(cfg["printer"], size, px)
        d = root / f"lab{li:02d}_{effect}"
        tr_prints = _lab_truth(printer, level, trial, lab_seed)
        ho_prints, ho_floor = held_out_truth(printer, level, ho_masks, lab_seed + 1)
        # how much the effect matters: the lab's noise-free held-out prints with it vs without it
        quiet = {"printer": {"cells": {"dose_noise": 0.0, "print_to_print": 0.0}}}
        with_fx = Printer(load_config(overrides=_merge(over, quiet))["printer"], size, px)
        without = Printer(load_config(overrides=_merge(_with_sigma(random_effect_lab(np.random.default_rng(lab_seed), "none"),
                                                                   lab_seed, args)[0], quiet))
                          ["printer"], size, px)
        a = _lab_truth(with_fx, level, ho_masks, 0)
        b = _lab_truth(without, level, ho_masks, 0)
        effect_iou = float(np.mean([metrics.iou(a[k], b[k]) for k in ho_masks]))
        # what the trial masks show of the effect: Eq. 1 calibrated on the lab's noise-free trial prints (with the
        # effect) leaves this mismatch there, the most that any candidate can take off Eq. 1's error on the trial prints
        clean = _lab_truth(with_fx, level, trial, 0)
        calibrate([_write_batch(d / "clean", trial, clean, px)], d / "cal_clean", seed=0, folds=0, bootstrap=0,
                  residual_maps=False, figure=False, progress=False, **({"objective": args.objective} if args.objective else {}))
        fit_clean = simulate(load_params(d / "cal_clean" / "params.yaml"), np.stack(list(trial.values())))
        trial_visible = float(np.mean(fit_clean != np.stack([clean[k] for k in trial])))
        reg = {}
        if args.registered:  # the trial prints through the lab's microscope and the registration
            prints, reg = _registered_batch(d, trial, over, lab_seed, size, args.declare_blur, args.dense_reference,
                                            args.half_cure)
        else:
            prints = _write_batch(d / "prints", trial, tr_prints, px)
        write_yaml(d / "lab.yaml", dict(seed=lab_seed, effect=effect, magnitude=mag, printer=cfg["printer"], **reg))
        t0 = time.perf_counter()
        calibrate([prints], d / "cal", seed=0, folds=0, bootstrap=0, residual_maps=False, figure=False, progress=False,
                  **({"objective": args.objective} if args.objective else {}))
        t_cal = time.perf_counter() - t0
        t0 = time.perf_counter()
        r = diagnose([prints], d / "cal" / "params.yaml", d / "diag", quick=args.quick, seed=0, progress=False,
                     figures=False, workers=args.workers, gain_test=args.gain_test)
        t_diag = time.perf_counter() - t0
        eq1 = load_params(d / "cal" / "params.yaml")
        sel = load_params(d / "diag" / "model.yaml")
        ids = list(ho_masks)
        arr = np.stack([ho_masks[k] for k in ids])
        sim_eq1, sim_sel = simulate(eq1, arr), simulate(sel, arr)
        # the mask itself, printed where its grey level reaches the threshold that fits the trial prints best
        tp = load_prints(prints)
        obj = args.objective or "mismatch"
        t_mask = mask_threshold(tp.masks, tp.prints, obj, weights=print_weights(tp.prints, obj))
        sim_mask = arr >= t_mask
        sims = dict(eq1=sim_eq1, selected=sim_sel, mask=sim_mask, floor=np.stack([ho_floor[mid] for mid in ids]),
                    noise_free=np.stack([a[mid] for mid in ids]))
        per_mask, pooled = scored(sims, ho_prints, ids)
        for j, mid in enumerate(ids):
            print_rows.append(dict(lab=li, effect=effect, id=mid, pattern=mid.split("_")[0] if mid.startswith("paper_")
                                   else test_pattern_of(mid), printed_px=int(np.median([t.sum() for t in ho_prints[mid]])),
                                   **{f"iou_{k}": v for k, v in per_mask[mid].items()},
                                   **{f"px_{k}": int(np.count_nonzero(v[j])) for k, v in sims.items()}))
        rows = print_rows[-len(ids):]
        pat = [x for x in rows if not x["id"].startswith("paper_")]
        mean = lambda rs, k: float(np.mean([x[k] for x in rs]))  # noqa: E731
        empty = {k: sum((x["printed_px"] == 0) != (x[f"px_{k}"] == 0) for x in rows) for k in ("eq1", "selected")}
        sig_lab = cfg["printer"]["kernel"]["sigma_um"] / px
        v = verdict(effect, r["effects"], r["unexplained_residual"])
        eq1_heldout = float(r["before"]["heldout_mismatch"])
        row = dict(lab=li, lab_seed=lab_seed, effect=effect, magnitude=mag, effect_iou=effect_iou,
                   trial_visible=trial_visible, eq1_heldout_mismatch=eq1_heldout, trial_share=trial_visible / max(eq1_heldout, 1e-12),
                   named=",".join(r["effects"]) or "-",
                   unexplained=",".join(r["unexplained_diagnostics"]) if r["unexplained_residual"] else "-", verdict=v,
                   iou_eq1=mean(rows, "iou_eq1"), iou_selected=mean(rows, "iou_selected"), iou_floor=mean(rows, "iou_floor"),
                   patterns_iou_eq1=mean(pat, "iou_eq1"), patterns_iou_selected=mean(pat, "iou_selected"),
                   patterns_iou_floor=mean(pat, "iou_floor"), pooled_iou_eq1=pooled["eq1"],
                   pooled_iou_selected=pooled["selected"], pooled_iou_floor=pooled["floor"], pooled_iou_mask=pooled["mask"],
                   pooled_iou_noise_free=pooled["noise_free"],
                   mask_threshold=t_mask, beats_mask_flag=r["beats_mask"],
                   resolved_flag=(eq1.info.get("validation", {}).get("resolution") or {}).get("resolved", ""),
                   empty_wrong_eq1=empty["eq1"],
                   empty_wrong_selected=empty["selected"], sigma_lab_px=sig_lab, sigma_eq1_px=eq1.values["sigma_px"],
                   sigma_selected_px=sel.values["sigma_px"], T_lab=cfg["printer"]["cure"]["threshold"], T_eq1=eq1.values["T"],
                   T_selected=sel.values["T"], cal_s=round(t_cal, 1), diag_s=round(t_diag, 1),
                   **{k: v for k, v in reg.items() if k != "microscope"})
        lab_rows.append(row)
        line = (f"{li:<4}{effect:<19}{mag:<27}{1 - effect_iou:9.4f}{100 * row['trial_share']:6.1f}%  {row['named']:<32}{'yes' if r['unexplained_residual'] else 'no':<8}{v:<12}"
                f"{row['iou_eq1']:8.4f}{row['iou_selected']:7.4f}{row['iou_floor']:7.4f}{row['iou_floor'] - row['iou_selected']:+7.4f}"
                f"{pooled['eq1']:8.4f}/{pooled['selected']:.4f}/{pooled['floor']:.4f}{row['patterns_iou_eq1']:8.4f}{row['patterns_iou_selected']:8.4f}{row['patterns_iou_floor']:8.4f}"
                f"{row['sigma_eq1_px'] / sig_lab:7.3f}/{row['sigma_selected_px'] / sig_lab:.3f}"
                f"{row['T_eq1'] / row['T_lab']:5.2f}/{row['T_selected'] / row['T_lab']:.2f}{t_cal:5.0f}s{t_diag:5.0f}s"
                + (f"  reg: {reg['prints_used']} used, {reg['failed']} failed, {reg['silently_wrong']} silent" if reg else ""))
        lines.append(line)
        print(line, flush=True)
        write_tsv(root / "labs.tsv", lab_rows, list(row))
        write_tsv(root / "prints.tsv", print_rows, list(print_rows[0]))
    lines += ["", summary(lab_rows), "", f"command: {cmd}"]
    text = "\n".join(lines) + "\n"
    (root / "summary.txt").write_text(text)
    print("\n" + summary(lab_rows))


def binned(rows: list, size, edges: list):
    """(lo, hi, rows) for each bin lo <= size(row) < hi between consecutive ``edges`` that
    holds a row: the power study's tables by an effect's size."""
    for a, b in zip(edges[:-1], edges[1:]):
        sel = [r for r in rows if a <= size(r) < b]
        if sel:
            yield a, b, sel


def power(rows: list) -> list[str]:
    """The power study's tables: confusion matrix (true effect x what was named), the
    library effects named against their size (1 - IoU of the lab's noise-free prints with
    and without the effect), false alarms on no-effect labs, outside effects flagged."""
    named_cols = ["-", *[e for e in RANDOM_EFFECTS if e not in ("none", "outside")], "unexplained", "several"]
    out = ["", "confusion (rows: the lab's effect; columns: what the diagnosis named; unexplained: the residual flagged "
           "with nothing named)", f"{'':<20}" + "".join(f"{c[:11]:>12}" for c in named_cols)]
    for eff in dict.fromkeys(r["effect"] for r in rows):
        counts = dict.fromkeys(named_cols, 0)
        for r in (r for r in rows if r["effect"] == eff):
            named = [] if r["named"] == "-" else r["named"].split(",")
            col = "several" if len(named) > 1 else named[0] if named else ("unexplained" if r["unexplained"] != "-" else "-")
            counts[col] += 1
        out.append(f"{eff:<20}" + "".join(f"{counts[c]:>12}" for c in named_cols))
    lib = [r for r in rows if r["effect"] not in OUTSIDE and r["effect"] != "none"]
    if lib:
        out += ["", "library effects named against their size (1 - IoU, the lab's noise-free prints with vs without):"]
        for a, b, sel in binned(lib, lambda r: 1 - r["effect_iou"], [0.0, 0.002, 0.005, 0.01, 0.02, 0.05, 1.0]):
            right = sum(r["verdict"] == "right" for r in sel)
            out.append(f"  {a:.3f}-{b:.3f}: {right} of {len(sel)} named right ({100 * right / len(sel):.0f} %)")
        out.append("library effects named against what Eq. 1 leaves to explain (held-out IoU: the floor minus Eq. 1's):")
        for a, b, sel in binned(lib, lambda r: r["iou_floor"] - r["iou_eq1"], [-1.0, 0.0, 0.005, 0.01, 0.02, 0.05, 1.0]):
            right = sum(r["verdict"] == "right" for r in sel)
            out.append(f"  {a:+.3f}..{b:+.3f}: {right} of {len(sel)} named right ({100 * right / len(sel):.0f} %)")
        if "trial_share" in lib[0]:  # runs before it lack the trial prints' share
            out.append("library effects named against what the trial prints show of them (Eq. 1 calibrated on the lab's "
                       "noise-free trial prints: the mismatch it leaves there, over Eq. 1's held-out mismatch on the lab's "
                       "prints; the diagnosis accepts a gain of at least 3 %):")
            for a, b, sel in binned(lib, lambda r: r["trial_share"], [0.0, 0.015, 0.03, 0.06, 0.12, 0.25, np.inf]):
                right = sum(r["verdict"] == "right" for r in sel)
                out.append(f"  {100 * a:4.1f}..{100 * b:4.1f} %: {right} of {len(sel)} named right ({100 * right / len(sel):.0f} %)")
            base = [r["trial_share"] for r in rows if r["effect"] == "none"]
            if base:
                out.append(f"  (no-effect labs, the calibration's own shortfall on noise-free prints: "
                           + ", ".join(f"{100 * x:.1f}" for x in base) + " %)")
        def limit(size) -> str:  # the smallest size above which every effect (at least 3) was named right
            sizes = sorted(size(r) for r in lib)
            x = next((x for x in sizes if all(r["verdict"] == "right" for r in lib if size(r) >= x)
                      and sum(size(r) >= x for r in lib) >= 3), None)
            return "none" if x is None else f"{x:.4f} ({sum(size(r) >= x for r in lib)} labs)"

        out.append("  smallest size above which every effect (at least 3) was named right: "
                   + limit(lambda r: 1 - r["effect_iou"])
                   + ("; by what the trial prints show: " + limit(lambda r: r["trial_share"]) if "trial_share" in lib[0] else ""))
    none = [r for r in rows if r["effect"] == "none"]
    outside = [r for r in rows if r["effect"] in OUTSIDE]
    if none:
        fa = sum(r["verdict"] == "false alarm" for r in none)
        out.append(f"no-effect labs given an effect or flagged: {fa} of {len(none)} ({100 * fa / len(none):.0f} %)")
    if outside:
        fl = sum(r["unexplained"] != "-" for r in outside)
        out.append(f"outside effects flagged unexplained: {fl} of {len(outside)} ({100 * fl / len(outside):.0f} %)")
        # what there is to find: an outside effect that Eq. 1 already predicts at the floor leaves no
        # residual for any test (the library effects' table by what Eq. 1 leaves, above, likewise)
        key = "pooled_iou_eq1" if "pooled_iou_eq1" in outside[0] else "iou_eq1"
        floor = "pooled_iou_floor" if key == "pooled_iou_eq1" else "iou_floor"
        out.append("outside effects against what Eq. 1 leaves to explain (held-out IoU"
                   + (", pooled" if key == "pooled_iou_eq1" else "") + ": the floor minus Eq. 1's): flagged / "
                   "named a library effect / neither")
        for a, b, sel in binned(outside, lambda r: r[floor] - r[key], [-1.0, 0.0, 0.005, 0.01, 0.02, 1.0]):
            f_ = sum(r["unexplained"] != "-" for r in sel)
            n_ = sum(r["unexplained"] == "-" and r["named"] != "-" for r in sel)
            out.append(f"  {a:+.3f}..{b:+.3f}: {f_} / {n_} / {len(sel) - f_ - n_} of {len(sel)}")
    return out


def summary(rows: list) -> str:
    counts = {v: sum(r["verdict"] == v for r in rows) for v in VERDICTS}
    gap_sel = [r["iou_floor"] - r["iou_selected"] for r in rows]
    gap_eq1 = [r["iou_floor"] - r["iou_eq1"] for r in rows]
    pgap = [r["patterns_iou_floor"] - r["patterns_iou_selected"] for r in rows]
    plain = [r for r in rows if r["effect"] in ("none", "dose_nonlinearity", "illumination_field", "edge_offset")]
    sig = [r["sigma_eq1_px"] / r["sigma_lab_px"] for r in plain]
    sig_sel = [r["sigma_selected_px"] / r["sigma_lab_px"] for r in rows if r["effect"] != "heavy_tail"]
    T = [r["T_selected"] / r["T_lab"] for r in rows if r["effect"] in ("none", "illumination_field", "anisotropy")]
    out = [f"detection over {len(rows)} labs: " + ", ".join(f"{v} {n}" for v, n in counts.items())]
    if "prints_used" in rows[0]:  # --registered: the trial prints through the microscope and the registration
        out.append(f"registration: {int(sum(r['prints_used'] for r in rows))} trial prints used, "
                   f"{int(sum(r['failed'] for r in rows))} failed QC, {int(sum(r['silently_wrong'] for r in rows))} "
                   f"silently wrong (of {len(rows)} labs' trial prints)")
    out += power(rows)
    if "pooled_iou_eq1" in rows[0]:  # runs before the pooled score have only the per-print mean
        pg_sel = [r["pooled_iou_floor"] - r["pooled_iou_selected"] for r in rows]
        pg_eq1 = [r["pooled_iou_floor"] - r["pooled_iou_eq1"] for r in rows]
        fx = [r for r in rows if r["effect"] != "none" and r["named"] != "-"]
        worse = [r for r in fx if r["pooled_iou_selected"] < r["pooled_iou_eq1"]]
        nf = [r["pooled_iou_noise_free"] - r["pooled_iou_floor"] for r in rows if "pooled_iou_noise_free" in r]
        out += [f"held-out IoU pooled over prints, gap to the floor, median [max]: Eq. 1 {np.median(pg_eq1):.4f} "
                f"[{max(pg_eq1):.4f}], selected {np.median(pg_sel):.4f} [{max(pg_sel):.4f}]",
                f"labs with an effect and a model selected: selected worse than Eq. 1 (pooled) in {len(worse)} of {len(fx)}"
                + "".join(f"; lab {int(r['lab'])} ({r['effect']}, named {r['named']}) {r['pooled_iou_eq1']:.4f} -> "
                          f"{r['pooled_iou_selected']:.4f}" for r in worse),
                *([f"the lab's noise-free printer, pooled, against the floor: median {np.median(nf):+.4f} [{min(nf):+.4f}, "
                   f"{max(nf):+.4f}] (the floor is the majority of {FLOOR_VOTES} noisy prints)"] if nf else []),
                "held-out masks the lab prints nothing of that a model prints (or the reverse), in all labs: Eq. 1 "
                f"{int(sum(r['empty_wrong_eq1'] for r in rows))}, selected {int(sum(r['empty_wrong_selected'] for r in rows))}"]
    if "pooled_iou_mask" in rows[0]:  # runs before the mask baseline lack it
        below = [r for r in rows if r["pooled_iou_selected"] <= r["pooled_iou_mask"]]
        flagged = [r for r in rows if str(r["beats_mask_flag"]) in ("False", "0", "false")]
        gain = [r["pooled_iou_selected"] - r["pooled_iou_mask"] for r in rows]
        out += [f"the mask itself (threshold fitted on the trial prints), pooled held-out IoU: median "
                f"{np.median([r['pooled_iou_mask'] for r in rows]):.4f}; selected model above it by a median {np.median(gain):.4f} "
                f"[min {min(gain):.4f}]; selected at or below it in {len(below)} of {len(rows)} labs against the truth"
                + "".join(f" (lab {int(r['lab'])}: {r['pooled_iou_selected']:.4f} against {r['pooled_iou_mask']:.4f})" for r in below)
                + f"; the diagnosis said so (no model beats the mask, on the trial prints) in {len(flagged)}"
                + (f", of them rightly {sum(r in below for r in flagged)}" if flagged else "")]
        eq1_below = [r for r in rows if r["pooled_iou_eq1"] <= r["pooled_iou_mask"]]
        unresolved = [r for r in rows if str(r.get("resolved_flag")) in ("False", "0", "false")]
        out += [f"Eq. 1 at or below the mask against the truth in {len(eq1_below)} of {len(rows)} labs; the calibration said "
                f"its sigma is within the microscope's blur (not resolved) in {len(unresolved)}, of them Eq. 1 below the mask in "
                f"{sum(r in eq1_below for r in unresolved)}"]
    out += [
           f"held-out IoU (mean of per-print IoU) gap to the floor (floor - model), median [max]: Eq. 1 {np.median(gap_eq1):.4f} [{max(gap_eq1):.4f}], "
           f"selected {np.median(gap_sel):.4f} [{max(gap_sel):.4f}]; test patterns only, selected {np.median(pgap):.4f}",
           f"sigma fitted / lab: Eq. 1 on labs with a Gaussian core and no kernel effect, median {np.median(sig) if sig else float('nan'):.3f} "
           f"(range {min(sig, default=float('nan')):.3f}..{max(sig, default=float('nan')):.3f}); selected model, all labs but heavy tail, "
           f"median {np.median(sig_sel):.3f}",
           f"T selected / lab (labs where T is identifiable: none, illumination, anisotropy): median "
           f"{np.median(T) if T else float('nan'):.3f}",
           f"time per lab: calibration median {np.median([r['cal_s'] for r in rows]):.0f} s, diagnosis median "
           f"{np.median([r['diag_s'] for r in rows]):.0f} s (max {max(r['diag_s'] for r in rows):.0f} s)"]
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="256 x 256, 16 prints, diagnose(quick=True)")
    ap.add_argument("--scenarios", default=",".join(SCENARIOS), help="comma-separated scenario names")
    ap.add_argument("--size", type=int, default=None)
    ap.add_argument("--count", type=int, default=None)
    ap.add_argument("--out", default=None, help="keep the outputs here (default: a temporary folder; random labs: "
                    "benchmarks/out/diagnosis)")
    ap.add_argument("--random-labs", type=int, default=0, metavar="N",
                    help="N random labs (unscatter.lab.random_lab), one effect each, instead of the scenarios")
    ap.add_argument("--seed", type=int, default=None, help="random labs: the seed (default: a new one, printed)")
    ap.add_argument("--heldout", type=int, default=16, help="random labs: held-out paper masks and as many test patterns")
    ap.add_argument("--objective", default=None, help="random labs: the calibration's objective (fitting.OBJECTIVES; "
                    "default: its default); the diagnosis uses the calibration's")
    ap.add_argument("--gain-test", choices=DIAGNOSIS["gain_test"].choices, default=GAIN_TEST,
                    help="random labs: the diagnosis's test of a candidate's held-out gain (diagnosis gain_test; "
                         "output folder suffix _<test>test where it is not the default)")
    ap.add_argument("--tag", default="", help="random labs: appended to the output folder's name")
    ap.add_argument("--effects", default=None, help=f"random labs: effects to draw from (default: {','.join(RANDOM_EFFECTS)}; "
                    f"outside: one or two of {','.join(OUTSIDE_PHYSICS)}, or name one of them)")
    ap.add_argument("--strength", choices=("wide", "strong"), default="wide",
                    help="random labs: effect magnitudes from barely detectable to strong (wide), or strong only")
    ap.add_argument("--trial", choices=("paper", "designed"), default="paper",
                    help="random labs: the trial masks, the paper's random ones or designed ones (design.design_masks at "
                         "the prior, seed 0, the workflow's pool, draws and registration marks)")
    ap.add_argument("--criterion", choices=("d", "discrimination", "paired"), default="d",
                    help="--trial designed: the design's criterion (design.design_masks; d, as the runs in docs/diagnosis.md "
                         "before 2026-11-30 had it: unscatter's own default is paired)")
    ap.add_argument("--noise", choices=("edge", "pixel"), default=None,
                    help="--trial designed: the design's model of the print noise (design.NOISE; default: its default)")
    ap.add_argument("--workers", type=int, default=None,
                    help="the diagnosis's worker processes (default: one per CPU core; the result does not depend on it)")
    ap.add_argument("--registered", action="store_true",
                    help="random labs: the trial prints through the whole lab (its random microscope, camera and "
                         "metadata) and the registration, failed prints skipped, instead of the lab's true prints")
    ap.add_argument("--sigma-um", default=None, metavar="LO,HI",
                    help="random labs: draw the scattering sigma log-uniformly over LO..HI um instead of the random lab's "
                         "range (e.g. 1,4: a sharp printer, where the mask itself is a strong baseline)")
    ap.add_argument("--declare-blur", action="store_true",
                    help="--registered: the lab's batch.yaml states its microscope's blur (microscope_blur_um), as a lab "
                         "that imaged beads would; where the prints do not resolve the scattering the calibration then "
                         "fits through the measurement stage holding it, not the registration's template blur "
                         "(output folder suffix _blur)")
    ap.add_argument("--dense-reference", action="store_true",
                    help="--registered: each batch holds a dense reference (a large block at 4 times the exposure, "
                         "batch.yaml dense_reference), on which the registration measures the fully cured level instead "
                         "of estimating it from the batch's brightest polymer (output folder suffix _ref)")
    ap.add_argument("--half-cure", action="store_true",
                    help="--registered: the registration cuts each print where the batch's template puts the half cure "
                         "(registration setting half_cure, template.half_cure_level; output folder suffix _halfcure)")
    ap.add_argument("--summarize", default=None, metavar="LABS_TSV",
                    help="print the summary of an earlier random-labs run's labs.tsv (and nothing else)")
    args = ap.parse_args()
    if args.half_cure and not args.registered:
        ap.error("--half-cure applies to the registration: use it with --registered")
    if args.summarize:
        from unscatter.io import read_tsv

        rows = []
        for r in read_tsv(args.summarize):
            row = dict(r)
            for k, v in r.items():
                try:
                    row[k] = float(v) if k not in ("named", "unexplained", "verdict", "effect", "magnitude") else v
                except ValueError:
                    pass
            rows.append(row)
        print(summary(rows))
        return
    if args.random_labs:
        random_labs(args)
        return
    size = args.size or (256 if args.quick else 512)
    count = args.count or (16 if args.quick else 32)
    root = Path(args.out or tempfile.mkdtemp(prefix="bench_diagnosis_"))
    print(f"{count} prints of {size}x{size}, {'quick' if args.quick else 'default'} diagnosis; {os.cpu_count()} CPUs; outputs in {root}")
    header = (f"{'scenario':<20}{'effects named':<36}{'expected':<30}{'IoU before -> after':<22}{'pixel error before -> after':<29}"
              f"{'unexplained':<24}{'base cal':>9}{'diagnosis':>10}")
    lines = [header]
    print(header, flush=True)
    for name in args.scenarios.split(","):
        d = root / name.replace(" ", "_").replace("(", "").replace(")", "").replace("+", "_")
        prints = lab_prints(d / "prints", name, count, size)
        t0 = time.perf_counter()
        calibrate([prints], d / "cal", seed=0, folds=0, bootstrap=0, residual_maps=False, figure=False, progress=False)
        t_cal = time.perf_counter() - t0
        t0 = time.perf_counter()
        r = diagnose([prints], d / "cal" / "params.yaml", d / "diag", quick=args.quick, seed=0, progress=False,
                     workers=args.workers)
        t_diag = time.perf_counter() - t0
        b, a = r["before"], r["after"]
        un = ",".join(r["unexplained_diagnostics"]) if r["unexplained_residual"] else "no"
        line = (f"{name:<20}{','.join(r['effects']) or '-':<36}{','.join(EXPECTED[name]) or '-':<30}"
                f"{b['heldout_iou']:.4f} -> {a['heldout_iou']:.4f}    {b['heldout_pixel_error']:.4f} -> {a['heldout_pixel_error']:.4f}"
                f"{'':<11}{un:<24}{t_cal:8.0f}s{t_diag:9.0f}s")
        lines.append(line)
        print(line, flush=True)
    (root / "bench_diagnosis.txt").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
