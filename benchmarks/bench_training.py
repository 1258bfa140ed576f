"""Training and inference cost of the master/slave U-Nets on this machine, the presets'
runs, and whether coordinate channels matter when training on crops.

    python benchmarks/bench_training.py steps      # seconds per Eq. 2 iteration by width and side
    python benchmarks/bench_training.py preset default [--dataset D.zarr]   # a preset's run
    python benchmarks/bench_training.py coords     # crops with and without X, Y channels
    python benchmarks/bench_training.py inference [--train-dir DIR]        # 512 x 512 compensation

Measured on a 2-core AMD EPYC (torch 2.13 CPU; the machine was shared with other jobs
for some runs, so CPU seconds are given where wall time is not comparable):

- steps: CPU s per iteration of 10 pairs, width 8/16/32 at 128 px 0.11/0.26/0.62, at
  256 px 0.29/0.72/2.2; width 16 at 512 px 3.3; the paper's width 64 at 512 px 2.6 s
  per pair (an epoch of 3,600 pairs: ~2.6 h on this CPU).
- preset default (1,200 pairs): 8 epochs in 485 s wall on two idle cores (780 CPU s),
  55 to 65 s per epoch; held-out IoU of the master's printed masks 0.970 (pixel error
  0.030) vs identity masks 0.938 (0.063); slave IoU 0.960. With lr 1e-5 instead of 1e-3,
  after 2 epochs: test loss 1.36 vs 0.063, master IoU 0.69.
- preset ci: 2 epochs in 3 s.
- coords (128 px crops of the 512 field, width 16): with the default field (a few per
  cent of curvature; 9 epochs) coordinates change nothing: master IoU 0.916 with, 0.919
  without, slave 0.938 / 0.939, identity 0.905. With a field three times as curved
  (6 epochs): slave IoU 0.922 with vs 0.908 without, master 0.935 vs 0.932 (pixel error
  0.066 vs 0.072), identity 0.890: the slave needs to know where it is once the field
  varies by tens of per cent; the default preset trains on the whole field instead.
- inference: compensate_nn on 512 x 512 with the default preset's master 0.015 s; the
  master's forward at 512 x 512 with the paper's width 64, 0.39 s.

Outputs go to benchmarks/out/training/. Without --dataset a dataset of the preset's size
(settings.PRESET_PAIRS) is simulated from a plausible calibrated Eq. 1 (see
bench_augment.py). CPU time is printed next to wall time: on a machine shared with other
jobs, wall time stretches.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch loads: no spinning threads

import argparse
import json
import time
from pathlib import Path

import numpy as np

OUT = Path("benchmarks/out/training")


def _params(path: Path, field: float = 1.0) -> Path:
    from unscatter.model import default_params, save_params

    p = default_params(pixel_size_um=2.96).with_values(
        c1=-0.07 * field, c2=-0.05 * field, c3=0.03 * field, c4=-0.02 * field, sigma_px=4.05, T=0.5
    )
    save_params(path, p)
    return path


def _dataset(count: int, name: str, field: float = 1.0) -> Path:
    from unscatter.augment import augment

    store = OUT / f"{name}.zarr"
    if not (store / "zarr.json").is_file():
        t = time.perf_counter()
        augment(_params(OUT / f"{name}.params.yaml", field), store, count=count, seed=11, progress=False)
        print(f"simulated {count} pairs -> {store} in {time.perf_counter() - t:.1f} s")
    return store


def steps(a):
    """Seconds per Eq. 2 iteration (master forward/backward, slave on x and on Master(y))."""
    import torch

    from unscatter.nets import master_net, slave_net
    from unscatter.training import eq2_total, loss_terms

    torch.set_num_threads(a.threads)
    print(f"threads {a.threads}, load average {os.getloadavg()[0]:.2f}")
    for width, side, batch in [(8, 128, 10), (16, 128, 10), (32, 128, 10), (8, 256, 10), (16, 256, 10),
                               (32, 256, 10), (16, 512, 10), (64, 256, 2), (64, 512, 2)]:
        m, s = master_net(width), slave_net(width)
        om, os_ = torch.optim.Adam(m.parameters(), 1e-4), torch.optim.Adam(s.parameters(), 1e-4)
        x = torch.rand(batch, 1, side, side) * 2 - 1
        p = (torch.rand(batch, 1, side, side) > 0.5).float()

        def one():
            om.zero_grad()
            os_.zero_grad()
            sx = s(x)
            my = m(2 * p - 1)
            s.eval()
            s.requires_grad_(False)
            smy = s(my)
            s.requires_grad_(True)
            s.train()
            eq2_total(loss_terms(my, smy, sx, x, p), 1.0).backward()
            om.step()
            os_.step()

        walls, cpus = [], []
        for _ in range(4):
            c0, t0 = time.process_time(), time.perf_counter()
            one()
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        w, c = min(walls[1:]), min(cpus[1:])
        print(f"width {width:3d} side {side:4d} batch {batch:2d}: {w:7.3f} s/iteration wall, {c:7.3f} CPU, "
              f"{w / batch * 1e3:7.1f} ms per pair")


def run_preset(a):
    from unscatter.settings import PRESET_PAIRS
    from unscatter.training import settings_for, train

    ds = a.dataset or _dataset(PRESET_PAIRS[a.name], f"data_{a.name}")
    settings = json.loads(a.settings) if a.settings else {}
    out = OUT / f"run_{a.name}{a.tag}"
    print(f"preset {a.name}: {json.dumps({k: v for k, v in settings_for(a.name, **settings).items()}, default=str)}")
    c0, t0 = time.process_time(), time.perf_counter()
    r = train(ds, out, preset=a.name, settings=settings, resume=False, progress=False, threads=a.threads)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    per = r["seconds_per_epoch"]
    print(f"{r['epochs']} epochs, {r['iterations']} iterations: wall {wall:.1f} s (CPU {cpu:.1f} s), "
          f"seconds per epoch {[round(x, 1) for x in per]}, load average {os.getloadavg()[0]:.2f}")
    _print_eval(r["eval"])
    return r


def _print_eval(rows):
    print(f"  {'method':9s} {'family':17s} {'n':>4s} {'IoU':>7s} {'pix.err':>8s} {'pix.acc':>8s}")
    for row in rows:
        print(f"  {row['method']:9s} {row['family']:17s} {row['n']:4d} {row['iou']:7.4f} {row['pixel_error']:8.4f} "
              f"{row['pixel_accuracy']:8.4f}")


def coords(a):
    """Training on crops, with and without the crop's position as input, for the default
    field and one three times as curved (half the dose in a corner): does the net need
    to know where it is?"""
    from unscatter.training import train

    for field in a.fields:
        ds = _dataset(a.count, f"data_field{field:g}", field)
        for use in (False, True):
            s = dict(scale=1, crop=128, coords=use, width=16, epochs=a.epochs, max_test=60, eval_pairs=a.eval_pairs)
            t0 = time.perf_counter()
            r = train(ds, OUT / f"coords_field{field:g}_{use}", preset="default", settings=s, resume=False,
                      progress=False, threads=a.threads)
            ev = {row["method"]: row for row in r["eval"] if row["family"] == "all"}
            print(f"field x{field:g}, coords {str(use):5s}: {time.perf_counter() - t0:6.1f} s, "
                  f"slave IoU {ev['slave']['iou']:.4f}, master IoU {ev['master']['iou']:.4f} "
                  f"(pixel error {ev['master']['pixel_error']:.4f}), identity IoU {ev['identity']['iou']:.4f}")


def inference(a):
    """compensate_nn on a 512 x 512 design; and the master's forward at the paper's width."""
    import torch

    from unscatter.nets import master_net
    from unscatter.training import compensate_nn

    torch.set_num_threads(a.threads)
    design = np.zeros((512, 512), np.uint8)
    design[128:384, 200:312] = 255
    design[240:272, 60:452] = 255
    if a.train_dir:
        compensate_nn(design, a.train_dir)  # load once
        ts = []
        for _ in range(5):
            t0 = time.perf_counter()
            compensate_nn(design, a.train_dir)
            ts.append(time.perf_counter() - t0)
        print(f"compensate_nn 512 x 512 ({a.train_dir}): median {np.median(ts):.3f} s, min {min(ts):.3f} s")
    for width in (16, 64):
        net = master_net(width).eval()
        with torch.no_grad():
            net(torch.zeros(1, 1, 512, 512))
            t0 = time.perf_counter()
            net(torch.zeros(1, 1, 512, 512))
        print(f"master forward at 512 x 512, width {width}: {time.perf_counter() - t0:.3f} s")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("steps")
    p = sub.add_parser("preset")
    p.add_argument("name", choices=["paper", "default", "ci"])
    p.add_argument("--dataset", type=Path)
    p.add_argument("--settings", help="JSON overrides of the preset")
    p.add_argument("--tag", default="")
    c = sub.add_parser("coords")
    c.add_argument("--count", type=int, default=1200)
    c.add_argument("--epochs", type=int, default=8)
    c.add_argument("--eval-pairs", type=int, default=60)
    c.add_argument("--fields", type=float, nargs="+", default=[1.0, 3.0])
    i = sub.add_parser("inference")
    i.add_argument("--train-dir", type=Path)
    a = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    dict(steps=steps, preset=run_preset, coords=coords, inference=inference)[a.cmd](a)


if __name__ == "__main__":
    main()
