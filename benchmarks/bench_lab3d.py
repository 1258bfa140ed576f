"""Multi-layer prints on the 3-D virtual lab (not a test): depth calibration, held-out
voxel IoU, and compensated designs against identical masks at the best uniform dose.

    python benchmarks/bench_lab3d.py [--labs 3] [--seed S] [--size 128] [--layers 8]

For each lab (the default lab's printer with its depth physics drawn over wide ranges:
initiator and cell absorption, bleaching, depth scatter; a new seed each run):

1. 3-D trial prints (bridges, channels, towers, stairs; ``calibration3d.trial_masks3d``)
   are printed on the lab; their voxel prints are the lab's truth in mask coordinates
   (registration of the z-stacks is left out here, so only the model is judged);
2. the depth parameters and sigma and T are fitted to 12 of them
   (``calibration3d.fit_depth``); the held-out voxel IoU on 6 others is reported, with the
   identical fit of a model without depth (every layer alone: att_length 10 um) beside it;
3. the designs of data/designs3d (resampled to ``--layers`` x ``--size``) are compensated
   through the calibrated model (``compensation3d.optimise_layers``) and printed on the
   lab, as are the identical masks at the model's best uniform dose; both are scored
   against the design with ``metrics.score3d``.

The lab's depth physics differs from the model's on purpose (bleaching, diffusive
rather than linear depth scatter, a saturating cure, cell noise).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]


def draw_depth(rng) -> dict:
    return dict(absorbance_initiator_per_um=float(np.exp(rng.uniform(np.log(0.003), np.log(0.02)))),
                absorbance_cells_per_um=float(rng.uniform(0.0005, 0.006)),
                bleaching=float(rng.uniform(0.0, 0.3)),
                scatter_growth_um=float(np.exp(rng.uniform(np.log(0.5), np.log(8.0)))))


def lab_prints(masks: dict, over: dict, root: Path, seed: int) -> dict:
    """Print layer masks on the lab; return id -> truth voxel print (L, H, W) bool."""
    from unscatter.io import read_print, write_png
    from unscatter.lab import print_layers

    for mid, m in masks.items():
        for j, layer in enumerate(m):
            write_png(root / "masks" / mid / f"{j:03d}.png", layer)
    print_layers(root / "masks", root / "batch", overrides=over, seed=seed, progress=False)
    return {mid: np.stack([read_print(root / "batch.truth" / "prints" / mid / f"{j:03d}.png") for j in range(len(m))])
            for mid, m in masks.items()}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--labs", type=int, default=3)
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--layers", type=int, default=8)
    ap.add_argument("--steps", type=int, default=80)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    from unscatter import metrics
    from unscatter.calibration3d import fit_depth, trial_masks3d, voxel_prints
    from unscatter.compensation3d import best_uniform_dose, optimise_layers, read_design3d
    from unscatter.lab import load_config
    from unscatter.model import default_params
    from bench_compensation3d import stretch

    seed = a.seed if a.seed is not None else int(np.random.default_rng().integers(2**31))
    print(f"seed {seed} (repeat with --seed {seed})", flush=True)
    designs = {p.name: stretch(read_design3d(p), a.layers, a.size)
               for p in sorted((ROOT / "data" / "designs3d").iterdir()) if p.is_dir()}
    for i in range(a.labs):
        rng = np.random.default_rng([seed, i])
        depth_lab = draw_depth(rng)
        over = dict(layers=depth_lab, printer=dict(pad_px=64))
        cfg = load_config(overrides=over)
        px, dz = float(cfg["batch"]["pixel_size_um"]), float(cfg["layers"]["layer_um"])
        print(f"lab {i}: " + ", ".join(f"{k} {v:.4g}" for k, v in depth_lab.items()), flush=True)
        with tempfile.TemporaryDirectory() as tmp:
            trials = trial_masks3d(18, layers=a.layers, size=a.size, seed=int(rng.integers(2**31)))
            truth = lab_prints(trials, over, Path(tmp) / "trials", int(rng.integers(2**31)))
            ids = list(trials)
            fit_ids, held_ids = ids[:12], ids[12:]
            base = default_params(pixel_size_um=px)
            t0 = time.perf_counter()
            fit = fit_depth([trials[k] for k in fit_ids], [truth[k] for k in fit_ids], base, dz, px,
                            free2d=("sigma_px", "T"), steps=a.steps)
            flat = fit_depth([trials[k] for k in fit_ids], [truth[k] for k in fit_ids], base, dz, px,
                             free2d=("sigma_px", "T"), steps=a.steps, starts=(10.0,))
            t_fit = time.perf_counter() - t0
            v = fit["values"]
            params = base.with_values(sigma_px=v["sigma_px"], T=v["T"])
            depth = dict(att_length_um=v["att_length_um"], diffusion_um=v["diffusion_um"], layer_um=dz)
            sims = voxel_prints([trials[k] for k in held_ids], params, depth, dz, px)
            held = np.mean([metrics.iou(s, truth[k]) for s, k in zip(sims, held_ids)])
            print(f"  depth fit ({t_fit:.0f} s): att_length {v['att_length_um']:.1f} um, diffusion {v['diffusion_um']:.3g} um, "
                  f"sigma {v['sigma_px']:.2f} px (lab {cfg['printer']['kernel']['sigma_um'] / px:.2f}), T {v['T']:.3f}; "
                  f"held-out voxel IoU {held:.4f}; objective {fit['objective']:.5f} "
                  f"(starting at 10 um, no depth reach: {flat['objective']:.5f})", flush=True)
            comp, same = {}, {}
            for name, d in designs.items():
                t1 = time.perf_counter()
                masks, info = optimise_layers(d, params, depth)
                k, _ = best_uniform_dose(d, params, depth, px)
                comp[name], same[name] = masks, (d * round(255 * k)).astype(np.uint8)
                print(f"  {name}: ILT {time.perf_counter() - t1:.0f} s, model IoU {info['model_iou']:.4f} vs "
                      f"identical at {k:.2f} {info['identical_model_iou']:.4f}", flush=True)
            printed = lab_prints({**{f"ilt_{n}": m for n, m in comp.items()}, **{f"same_{n}": m for n, m in same.items()}},
                                 over, Path(tmp) / "designs", int(rng.integers(2**31)))
            for name, d in designs.items():
                si = metrics.score3d(printed[f"ilt_{name}"], d, px, dz)
                ss = metrics.score3d(printed[f"same_{name}"], d, px, dz)
                print(f"  lab print {name:16s} IoU {si['iou']:.4f} vs {ss['iou']:.4f}  open channels "
                      f"{si['open_channels']:.2f} vs {ss['open_channels']:.2f}  overhang {si['overhang_error_um']:.1f} "
                      f"vs {ss['overhang_error_um']:.1f} um  wall {si['wall_error_um']:+.1f} vs {ss['wall_error_um']:+.1f} um",
                      flush=True)


if __name__ == "__main__":
    main()
