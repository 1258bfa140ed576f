"""Augmentation speed: the paper's 4,000 pairs at 512 x 512 (target: 60 s on 2 cores).

    python benchmarks/bench_augment.py [--count 4000] [--size 512] [--params PARAMS.yaml]
                                       [--workers 1 2] [--out benchmarks/out/augment]

Without --params a plausible calibrated Eq. 1 is used (sigma 4.05 px = 12 um at 2.96 um
per pixel, T 0.5, a field curved by a few per cent, as the virtual lab's default).
Prints the cost of each part per pair on one core (mask generation by family, the
simulation, the Zarr write), then the wall time and CPU time of whole runs with each
number of workers, and the store's size on disk. CPU time is printed next to wall time
because a machine shared with other jobs stretches wall time.

Measured on a 2-core AMD EPYC, idle (torch 2.13 CPU, zarr 3.1): 4,000 pairs at 512 x 512
in 19.0 s with 2 workers (210 pairs/s, 28 CPU s), 29.6 s with 1; per pair on one thread:
mask 1.8 ms (vasculature 8 ms, lines 0.2 to 0.4 ms), simulation 5.0 ms, write 2.3 ms;
a random read of one pair 1.6 ms; the store takes 12 MB (zstd).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads: no spinning threads

import argparse
import shutil
import time
from pathlib import Path

import numpy as np


def plausible_params(path: Path) -> Path:
    from unscatter.model import default_params, save_params

    p = default_params(pixel_size_um=2.96).with_values(c1=-0.07, c2=-0.05, c3=0.03, c4=-0.02, sigma_px=4.05, T=0.5)
    save_params(path, p)
    return path


def parts(params: Path, size: int, n: int = 112) -> dict:
    """Per-pair cost of each step on one thread (ms)."""
    import torch
    import zarr
    from zarr.codecs import ZstdCodec

    from unscatter.masks import AUGMENT_FAMILIES, augmentation_mask
    from unscatter.model import load_params, simulate

    torch.set_num_threads(1)
    out = {}
    masks = []
    for fam in AUGMENT_FAMILIES:
        t = time.perf_counter()
        ms = [augmentation_mask(fam, 0, i, size) for i in range(n // len(AUGMENT_FAMILIES))]
        out[f"generate {fam}"] = (time.perf_counter() - t) / len(ms) * 1e3
        masks += ms
    out["generate (mean)"] = float(np.mean([out[f"generate {f}"] for f in AUGMENT_FAMILIES]))
    p = load_params(params)
    m = np.stack(masks)
    simulate(p, list(m[:16]), device="cpu", batch=16)
    t = time.perf_counter()
    prints = np.concatenate([simulate(p, list(m[i : i + 16]), device="cpu", batch=16) for i in range(0, len(m), 16)])
    out["simulate"] = (time.perf_counter() - t) / len(m) * 1e3
    tmp = Path("/tmp") / f"bench_augment_parts_{os.getpid()}.zarr"
    g = zarr.open_group(str(tmp), mode="w")
    a = g.create_array("masks", shape=m.shape, chunks=(1, size, size), dtype="uint8", compressors=ZstdCodec(level=1))
    b = g.create_array("prints", shape=m.shape, chunks=(1, size, size), dtype="bool", compressors=ZstdCodec(level=1))
    t = time.perf_counter()
    for i in range(0, len(m), 16):
        a[i : i + 16] = m[i : i + 16]
        b[i : i + 16] = prints[i : i + 16]
    out["write"] = (time.perf_counter() - t) / len(m) * 1e3
    t = time.perf_counter()
    idx = np.random.default_rng(0).permutation(len(m))[:40]
    for i in idx:
        a[int(i)], b[int(i)]
    out["random read"] = (time.perf_counter() - t) / len(idx) * 1e3
    shutil.rmtree(tmp, ignore_errors=True)
    torch.set_num_threads(os.cpu_count() or 1)
    return out


def du_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 2**20


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--count", type=int, default=4000)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--params", type=Path)
    ap.add_argument("--workers", type=int, nargs="+", default=[None])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/out/augment"))
    a = ap.parse_args()
    from unscatter.augment import augment

    a.out.mkdir(parents=True, exist_ok=True)
    params = a.params or plausible_params(a.out / "params.yaml")
    print(f"cores available: {len(os.sched_getaffinity(0))}, load average {os.getloadavg()[0]:.2f}")
    print("per pair on one thread (ms):")
    for k, v in parts(params, a.size).items():
        print(f"  {k:28s} {v:7.2f}")
    for w in a.workers:
        store = a.out / "bench.zarr"
        c0, t0 = time.process_time(), time.perf_counter()
        s = augment(params, store, count=a.count, seed=0, size=a.size, workers=w, progress=False)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        print(
            f"{a.count} pairs at {a.size}x{a.size}, {s['workers']} worker(s): wall {wall:.1f} s "
            f"({a.count / wall:.0f} pairs/s), CPU {cpu:.1f} s, store {du_mb(store):.0f} MB, "
            f"print fraction {s['print_fraction']:.3f}, empty prints {s['empty_prints']}, "
            f"load average after {os.getloadavg()[0]:.2f}"
        )


if __name__ == "__main__":
    main()
