"""Registration accuracy and speed against the virtual lab's truth.

    python benchmarks/bench_registration.py [--count 32] [--seed 3] [--out benchmarks/out/registration]

Prints per-print transform error (RMS over the mask field, mask pixels), IoU of the
registered print vs the lab's noise-free print, the mean over non-empty prints, and the
wall time of registering the batch. The IoU a perfect registration would reach (the
true transform, same thresholding) is printed beside it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from unscatter.imaging import Settings, correct_image, threshold_print, transform_rms_px
from unscatter.io import read_print, read_tsv, read_yaml
from unscatter.metrics import iou


def evaluate(reg_dir: Path, truth_dir: Path, size: int = 512) -> list[dict]:
    """Per print: transform error, IoU as registered, and IoU with the true transform
    (a perfect registration of the same image, same flat field and threshold)."""
    qc = {r["id"]: r for r in read_tsv(reg_dir / "qc.tsv")}
    offset = float(read_yaml(reg_dir / "batch.yaml").get("camera_offset_adu", 0) or 0)
    truth = {r["id"]: r for r in read_tsv(truth_dir / "transforms.tsv")}
    out = []
    for mid, t in truth.items():
        q = qc[mid]
        tp = read_print(truth_dir / "prints" / f"{mid}.png")
        row = dict(id=mid, status=q["status"], truth_solid=float(tp.mean()))
        if q["status"] == "ok":
            Mt = np.array([[float(t[f"m{a}{b}"]) for b in range(3)] for a in range(2)])
            Me = np.array([[float(q[f"m{a}{b}"]) for b in range(3)] for a in range(2)])
            row["rms_px"] = transform_rms_px(Me, Mt, size)
            k = correct_image(mid, Path(q["image"]), offset, Settings(), q["flatfield"])
            row["iou_perfect"] = iou(threshold_print(k.c, Mt, float(q["threshold"]), size)[1], tp)
        if q["status"] in ("ok", "empty"):
            row["iou"] = iou(read_print(reg_dir / f"{mid}.png"), tp)
        out.append(row)
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--count", type=int, default=32)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/registration"))
    ap.add_argument("--lab-config", type=Path)
    a = ap.parse_args()
    from unscatter.imaging import register_batch
    from unscatter.lab import print_batch
    from unscatter.masks import write_trial_masks

    write_trial_masks(a.out / "masks", a.count, seed=a.seed)
    print_batch(a.out / "masks", a.out / "batch", lab_config=a.lab_config, seed=a.seed, progress=False)
    t0 = time.perf_counter()
    register_batch(a.out / "batch", a.out / "reg", skip_failed=True)
    dt = time.perf_counter() - t0
    rows = evaluate(a.out / "reg", a.out / "batch.truth")
    for r in rows:
        print(f"{r['id']}  {r['status']:6s}  rms {r.get('rms_px', float('nan')):6.3f} px  IoU {r.get('iou', float('nan')):.4f}"
              f" (perfect registration {r.get('iou_perfect', float('nan')):.4f})  solid {r['truth_solid']:.3f}")
    ok = [r for r in rows if "rms_px" in r]
    ne = [r for r in rows if r["truth_solid"] > 0 and "iou" in r]
    print(f"registered {len(rows)} images in {dt:.1f} s ({dt / len(rows):.2f} s each)")
    print(f"transform RMS over the mask field: mean {np.mean([r['rms_px'] for r in ok]):.3f} px, max {np.max([r['rms_px'] for r in ok]):.3f} px")
    print(f"IoU vs the lab's noise-free print (non-empty prints): mean {np.mean([r['iou'] for r in ne]):.4f}, min {np.min([r['iou'] for r in ne]):.4f}")
    perf = [r["iou_perfect"] for r in ne if "iou_perfect" in r]
    print(f"IoU with the true transform (same images, same threshold): mean {np.mean(perf):.4f}")
    print(f"empty: {sum(r['status'] == 'empty' for r in rows)} (truth empty: {sum(r['truth_solid'] == 0 for r in rows)})")
    print(f"failed: {sum(r['status'] == 'failed' for r in rows)}")


if __name__ == "__main__":
    main()
