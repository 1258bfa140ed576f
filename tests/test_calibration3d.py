"""Depth calibration from 3-D trial prints (unscatter.calibration3d)."""

from __future__ import annotations

import numpy as np
import pytest

from unscatter.calibration3d import KINDS3D, fit_depth, trial_masks3d, voxel_prints
from unscatter.metrics import iou
from unscatter.model import default_params

PX, DZ = 2.96, 50.0


def test_trial_masks3d_are_seeded_and_of_every_kind():
    a, b = trial_masks3d(8, layers=5, size=48, seed=2), trial_masks3d(8, layers=5, size=48, seed=2)
    assert list(a) == list(b) and all(np.array_equal(a[k], b[k]) for k in a)
    assert {k.rsplit("_", 1)[0] for k in a} == set(KINDS3D)
    assert all(m.shape == (5, 48, 48) and m.dtype == np.uint8 and m.any() for m in a.values())
    # the bridges overhang: solid over void somewhere
    br = next(m for k, m in a.items() if k.startswith("bridge")) > 0
    assert (br[1:] & ~br[:-1]).any()


def test_fit_depth_recovers_the_attenuation_length():
    p = default_params(pixel_size_um=PX).with_values(sigma_px=2.0, T=0.5)
    masks = [m for k, m in trial_masks3d(8, layers=4, size=40, seed=1).items() if k.split("_")[0] in ("bridge", "channel")]
    truth = dict(att_length_um=60.0, diffusion_um=2.0)
    prints = voxel_prints(masks, p, truth, DZ, PX)
    r = fit_depth(masks, prints, p, DZ, PX, steps=50, starts=(100.0,))
    assert r["values"]["att_length_um"] == pytest.approx(60.0, rel=0.25)
    fitted = voxel_prints(masks, p, dict(att_length_um=r["values"]["att_length_um"], diffusion_um=r["values"]["diffusion_um"]), DZ, PX)
    assert np.mean([iou(a, b) for a, b in zip(fitted, prints)]) > 0.98
    # a model in which light reaches no layer below fits clearly worse
    shallow = voxel_prints(masks, p, dict(att_length_um=10.0, diffusion_um=0.0), DZ, PX)
    assert np.mean([iou(a, b) for a, b in zip(shallow, prints)]) < 0.97


def test_a_zero_weight_leaves_a_print_out_and_the_bootstrap_spreads():
    """fit_depth's weights are a bootstrap's counts: a print of weight 0 is as if absent;
    resamples of noisy prints give replicates that differ, around the fit."""
    from unscatter.calibration3d import bootstrap_depth

    p = default_params(pixel_size_um=PX).with_values(sigma_px=2.0, T=0.5)
    masks = list(trial_masks3d(6, layers=4, size=40, seed=4).values())
    truth = dict(att_length_um=60.0, diffusion_um=2.0)
    rng = np.random.default_rng(0)
    prints = [v ^ (rng.random(v.shape) < 0.03) for v in voxel_prints(masks, p, truth, DZ, PX)]  # 3 % voxels flipped
    fit = fit_depth(masks, prints, p, DZ, PX, steps=30, starts=(100.0,))
    a = fit_depth(masks, prints, p, DZ, PX, steps=10, init=fit["u"], weights=[1, 1, 0, 1, 1, 1])
    b = fit_depth(masks[:2] + masks[3:], prints[:2] + prints[3:], p, DZ, PX, steps=10, init=fit["u"])
    assert a["values"] == pytest.approx(b["values"], rel=1e-4)
    boot = bootstrap_depth(masks, prints, p, DZ, PX, fit, replicates=4, steps=15, seed=1)
    att = np.array([r["att_length_um"] for r in boot])
    assert len(boot) == 4 and att.std() > 0.01
    assert abs(att.mean() - fit["values"]["att_length_um"]) < 0.25 * fit["values"]["att_length_um"]
