"""Multi-layer prints on 3-D virtual labs (not a test): z-stack registration, depth
calibration, held-out voxel IoU, and compensated designs against identical masks at the
best uniform dose.

    python benchmarks/bench_lab3d.py [--labs 3] [--seed S] [--size 128] [--layers 8]
                                     [--optics random|default] [--through registration|truth]

For each lab (a new seed each run; with ``--optics random`` the printer and microscope
are drawn by ``unscatter.lab.random.random_lab`` (kernel, tails, anisotropy, hot spots,
dose response, cure, camera, pose) and the confocal (axial and lateral blur, z offset,
slice step, fall-off) and layer thickness too; the depth physics always: initiator and
cell absorption, bleaching, depth scatter):

1. 3-D trial prints (bridges, channels, towers, stairs; ``calibration3d.trial_masks3d``)
   are printed on the lab and imaged as z-stacks. With ``--through registration`` the
   stacks are registered (``imaging.register_stacks``; prints that fail QC are left out)
   and their voxel prints are the data; with ``--through truth`` the lab's voxel truth is;
2. the depth parameters and sigma and T are fitted to the first 12 of them
   (``calibration3d.fit_depth``), their spread from 8 bootstrap resamples
   (``calibration3d.bootstrap_depth``); the held-out voxel IoU on 6 others is scored
   against the lab's truth, with the identical fit of a model without depth (every layer
   alone: att_length 10 um) beside it; the lab's own attenuation length one layer down
   (1 / (cells + initiator x (1 - bleaching))) and depth scatter are printed beside the fit;
3. the designs of data/designs3d (resampled to ``--layers`` x ``--size``) are compensated
   through the calibrated model (``compensation3d.optimise_layers``) and printed on the
   lab, as are the identical masks at the model's best uniform dose; both are scored
   against the design with ``metrics.score3d`` on the lab's truth.

The lab's physics differs from the model's on purpose (bleaching, a saturating cure, cell
noise, and with random optics whatever ``random_lab`` draws that Eq. 1 lacks).
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


def draw_confocal(rng) -> dict:
    return dict(axial_sigma_um=float(rng.uniform(4.0, 16.0)), lateral_sigma_um=float(rng.uniform(1.0, 4.0)),
                z_offset_um=float(rng.uniform(5.0, 40.0)), z_step_um=float(rng.choice([5.0, 10.0, 15.0])),
                signal_length_um=float(np.exp(rng.uniform(np.log(200.0), np.log(1500.0)))),
                slice_jitter=float(rng.uniform(0.0, 0.05)))


def lab_overrides(rng, optics: str, size: int) -> dict:
    """The lab's overrides: depth physics drawn, and with optics 'random' the printer,
    microscope, confocal and layer thickness too. The field of view is sized to the
    print (``size`` DMD pixels) as the lab's zoom would be, not to a 512 px 2-D field."""
    from unscatter.lab.random import MARGIN_PX, field_extent_px, random_lab

    layers = draw_depth(rng)
    if optics == "default":
        return dict(layers=layers, printer=dict(pad_px=64))
    over = random_lab(rng)
    over["printer"]["pad_px"] = 64
    m = over["microscope"]
    need = int(np.ceil(field_extent_px(m["scale"][1], m["rotation_deg"], size))) + 2 * MARGIN_PX
    m["image_size"] = [int(need * rng.uniform(1.0, 1.3)) for _ in range(2)]
    layers.update(layer_um=float(np.round(np.exp(rng.uniform(np.log(25.0), np.log(80.0))))), confocal=draw_confocal(rng))
    over["layers"] = layers
    return over


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--labs", type=int, default=3)
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--layers", type=int, default=8)
    ap.add_argument("--steps", type=int, default=80)
    ap.add_argument("--optics", choices=("random", "default"), default="random")
    ap.add_argument("--through", choices=("registration", "truth"), default="registration")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    from unscatter import metrics
    from unscatter.calibration3d import bootstrap_depth, fit_depth, load_voxel_prints, trial_masks3d, voxel_prints
    from unscatter.compensation3d import best_uniform_dose, optimise_layers, read_design3d
    from unscatter.imaging import register_stacks
    from unscatter.io import read_tsv
    from unscatter.lab import load_config
    from unscatter.lab.random import describe_lab
    from unscatter.model import default_params
    from bench_compensation3d import stretch

    seed = a.seed if a.seed is not None else int(np.random.default_rng().integers(2**31))
    print(f"seed {seed} (repeat with --seed {seed}); optics {a.optics}, data through {a.through}", flush=True)
    designs = {p.name: stretch(read_design3d(p), a.layers, a.size)
               for p in sorted((ROOT / "data" / "designs3d").iterdir()) if p.is_dir()}
    summary = []
    for i in range(a.labs):
        rng = np.random.default_rng([seed, i])
        over = lab_overrides(rng, a.optics, a.size)
        cfg = load_config(overrides=over)
        lay = cfg["layers"]
        px, dz = float(cfg["batch"]["pixel_size_um"]), float(lay["layer_um"])
        # the lab's attenuation length one layer down (the initiator bleached once) and as a
        # mean over the print's depth (bleached up to layers - 1 times)
        mu = [lay["absorbance_cells_per_um"] + lay["absorbance_initiator_per_um"] * (1 - lay["bleaching"]) ** n
              for n in range(1, a.layers)]
        att_lab, att_deep = 1.0 / mu[0], len(mu) / sum(mu)
        print(f"lab {i}: layer {dz:g} um, att_length one layer down {att_lab:.1f} um, depth scatter "
              f"{lay['scatter_growth_um']:.3g} um, bleaching {lay['bleaching']:.2f}, axial blur "
              f"{lay['confocal']['axial_sigma_um']:.1f} um, z step {lay['confocal']['z_step_um']:g} um", flush=True)
        if a.optics == "random":
            print("  " + describe_lab(over), flush=True)
        with tempfile.TemporaryDirectory() as tmp:
            trials = trial_masks3d(18, layers=a.layers, size=a.size, seed=int(rng.integers(2**31)))
            truth = lab_prints(trials, over, Path(tmp) / "trials", int(rng.integers(2**31)))
            ids = list(trials)
            fit_ids, held_ids = ids[:12], ids[12:]
            data, failed = truth, []
            if a.through == "registration":
                t0 = time.perf_counter()
                rows = register_stacks(Path(tmp) / "trials" / "batch", Path(tmp) / "reg", skip_failed=True, progress=False)
                _, data, _ = load_voxel_prints(Path(tmp) / "reg")
                failed = [r for r in rows if r["status"] != "ok"]
                poses = {r["id"]: r for r in read_tsv(Path(tmp) / "trials" / "batch.truth" / "transforms.tsv")}
                vox = [metrics.iou(data[k], truth[k]) for k in data]
                print(f"  registration ({time.perf_counter() - t0:.0f} s): {len(data)} of {len(rows)} ok, voxel IoU "
                      f"against the truth median {np.median(vox):.4f}, worst {min(vox):.4f}; failed: "
                      + ("; ".join(f"{r['id']} ({r['reason'][:70]})" for r in failed) or "none"), flush=True)
                zerr = [abs(float(r["bottom_um"]) - (-float(poses[r["id"]]["z0_um"]))) for r in rows if r["status"] == "ok"]
                print(f"  z offset error: median {np.median(zerr):.1f} um, worst {max(zerr):.1f} um "
                      f"(layer {dz:g} um)", flush=True)
            fit_ids = [k for k in fit_ids if k in data]
            base = default_params(pixel_size_um=px)
            t0 = time.perf_counter()
            fm, fp = [trials[k] for k in fit_ids], [data[k] for k in fit_ids]
            fit = fit_depth(fm, fp, base, dz, px, free2d=("sigma_px", "T"), steps=a.steps)
            flat = fit_depth(fm, fp, base, dz, px, free2d=("sigma_px", "T"), steps=a.steps, starts=(10.0,))
            t_fit = time.perf_counter() - t0
            boot = bootstrap_depth(fm, fp, base, dz, px, fit, free2d=("sigma_px", "T"), replicates=8, seed=i)
            sd = {k: float(np.std([b[k] for b in boot], ddof=1)) for k in fit["values"]}
            v = fit["values"]
            params = base.with_values(sigma_px=v["sigma_px"], T=v["T"])
            depth = dict(att_length_um=v["att_length_um"], diffusion_um=v["diffusion_um"], layer_um=dz)
            sims = voxel_prints([trials[k] for k in held_ids], params, depth, dz, px)
            held = np.mean([metrics.iou(s, truth[k]) for s, k in zip(sims, held_ids)])
            print(f"  depth fit on {len(fit_ids)} prints ({t_fit:.0f} s): att_length {v['att_length_um']:.1f} "
                  f"+- {sd['att_length_um']:.1f} um (lab {att_lab:.1f} one layer down, {att_deep:.1f} over the print), diffusion {v['diffusion_um']:.3g} "
                  f"+- {sd['diffusion_um']:.2g} um (lab {lay['scatter_growth_um']:.3g}), sigma {v['sigma_px']:.2f} "
                  f"+- {sd['sigma_px']:.2f} px (lab core {cfg['printer']['kernel']['sigma_um'] / px:.2f}), T {v['T']:.3f}; "
                  f"held-out voxel IoU against the truth {held:.4f}; objective {fit['objective']:.5f} "
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
                summary.append(dict(lab=i, design=name, ilt=si["iou"], same=ss["iou"], open_ilt=si["open_channels"],
                                    open_same=ss["open_channels"], held=held, failed=len(failed)))
                print(f"  lab print {name:16s} IoU {si['iou']:.4f} vs {ss['iou']:.4f}  open channels "
                      f"{si['open_channels']:.2f} vs {ss['open_channels']:.2f}  overhang {si['overhang_error_um']:.1f} "
                      f"vs {ss['overhang_error_um']:.1f} um  wall {si['wall_error_um']:+.1f} vs {ss['wall_error_um']:+.1f} um",
                      flush=True)
    if summary:
        won = sum(r["ilt"] > r["same"] for r in summary)
        print(f"summary over {a.labs} labs: compensated beat identical in {won} of {len(summary)} lab x design prints; "
              f"3-D IoU median {np.median([r['ilt'] for r in summary]):.4f} vs {np.median([r['same'] for r in summary]):.4f}; "
              f"held-out voxel IoU per lab " + ", ".join(f"{h:.3f}" for h in sorted({r['lab']: r['held'] for r in summary}.values())),
              flush=True)


if __name__ == "__main__":
    main()
