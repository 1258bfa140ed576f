"""Benchmark of the residual diagnosis (not a test): does the loop name the lab's effect,
how much does it lower the held-out error, and how long does it take.

    python benchmarks/bench_diagnosis.py [--quick] [--scenarios a,b,...] [--size N] [--count N]

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
from unscatter.io import write_png, write_tsv, write_yaml
from unscatter.masks import trial_masks

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


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="256 x 256, 16 prints, diagnose(quick=True)")
    ap.add_argument("--scenarios", default=",".join(SCENARIOS), help="comma-separated scenario names")
    ap.add_argument("--size", type=int, default=None)
    ap.add_argument("--count", type=int, default=None)
    ap.add_argument("--out", default=None, help="keep the outputs here (default: a temporary folder)")
    args = ap.parse_args()
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
        r = diagnose([prints], d / "cal" / "params.yaml", d / "diag", quick=args.quick, seed=0, progress=False)
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
