"""Speed and quality of multi-layer compensation (not a test).

    python benchmarks/bench_compensation3d.py [--layers 40] [--size 512] [--threads 1]

Compensates the 3-D designs of data/designs3d (stretched to ``--layers`` layers and
``--size`` pixels a side) through the multi-layer model with Eq. 1 at sigma 4 px and
depth parameters att_length_um 80, diffusion_um 4, 50 um layers, and prints per design: the
wall time, the model's 3-D IoU of the ILT masks and of the identical masks at the best
uniform dose, and the open-channel fraction and overhang and wall thickness errors of
both. Target (issue 14): a 40-layer 512 x 512 design in 60 s or less on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]


def stretch(d: np.ndarray, layers: int, size: int) -> np.ndarray:
    """A design resampled to ``layers`` x ``size`` x ``size`` (nearest neighbour)."""
    z = ndimage.zoom(d.astype(np.uint8), (layers / d.shape[0], size / d.shape[1], size / d.shape[2]), order=0)
    return z.astype(bool)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--layers", type=int, default=40)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--designs", default="", help="comma-separated names (default: all)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    from unscatter import metrics
    from unscatter.compensation3d import optimise_layers, read_design3d
    from unscatter.model import default_params, layer_dose

    px, dz = 2.96, 50.0
    depth = dict(att_length_um=80.0, diffusion_um=4.0, layer_um=dz)
    p = default_params(pixel_size_um=px).with_values(sigma_px=4.0, T=0.5)
    model = p.build()
    th = model.theta(p.values)
    names = a.designs.split(",") if a.designs else sorted(x.name for x in (ROOT / "data" / "designs3d").iterdir())
    print(f"{a.layers} layers of {a.size} x {a.size}, {a.threads} torch thread(s)")
    for name in names:
        d = stretch(read_design3d(ROOT / "data" / "designs3d" / name), a.layers, a.size)
        t0 = time.perf_counter()
        masks, info = optimise_layers(d, p, depth, threads=a.threads)
        wall = time.perf_counter() - t0
        with torch.no_grad():
            ilt = (layer_dose(model, torch.from_numpy(masks / 255.0).float(), th, depth, dz, px)[0] >= 0.5).numpy()
            k = info["identical_best_dose"]
            same = (layer_dose(model, torch.from_numpy(d * k).float(), th, depth, dz, px)[0] >= 0.5).numpy()
        si, ss = metrics.score3d(ilt, d, px, dz), metrics.score3d(same, d, px, dz)
        print(f"{name:16s} {wall:6.1f} s (ILT {info['seconds']:.1f} s)  "
              f"IoU {si['iou']:.4f} vs {ss['iou']:.4f} (identical at {k:.2f})  "
              f"open channels {si['open_channels']:.2f} vs {ss['open_channels']:.2f}  "
              f"overhang {si['overhang_error_um']:.1f} vs {ss['overhang_error_um']:.1f} um  "
              f"wall {si['wall_error_um']:+.1f} vs {ss['wall_error_um']:+.1f} um", flush=True)


if __name__ == "__main__":
    main()
