"""Multi-layer compensation (unscatter.compensation3d) and the 3-D metrics."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import yaml
from click.testing import CliRunner

from unscatter import metrics
from unscatter.cli import main
from unscatter.compensation3d import best_uniform_dose, load_depth, optimise_layers, read_design3d
from unscatter.io import InputError, read_mask, write_png
from unscatter.model import default_params, layer_dose, save_params

PX, DZ = 2.96, 50.0
DEPTH = dict(att_length_um=80.0, diffusion_um=4.0, layer_um=DZ)


def bridge(L=6, n=64):
    d = np.zeros((L, n, n), bool)
    d[:, 16:48, 8:18] = True
    d[:, 16:48, 46:56] = True
    d[-2:, 16:48, 8:56] = True
    return d


def tube(L=4, n=48):
    yy, xx = np.mgrid[:n, :n] - (n - 1) / 2
    r = np.hypot(yy, xx)
    return np.broadcast_to((r <= 16) & (r > 8), (L, n, n)).copy()


# ----------------------------------------------------------------------- metrics
def test_channel_metrics_on_a_tube():
    d = tube()
    assert metrics.open_channel_fraction(d, d) == 1.0
    plugged = d.copy()
    plugged[2] |= ~d[2]  # one layer fills the lumen
    assert metrics.open_channel_fraction(plugged, d) == 0.0
    yy, xx = np.mgrid[:48, :48] - 23.5
    r = np.hypot(yy, xx)[None]
    narrowed = d | ((r > 5) & (r <= 16))  # the wall grew inward, a lumen of 5 px is left
    assert metrics.open_channel_fraction(narrowed, d) == 1.0
    assert np.isnan(metrics.open_channel_fraction(bridge(), bridge()))  # the gap under a bridge is no channel


def test_overhang_and_wall_errors():
    d = bridge()
    assert metrics.overhang_thickness_error_um(d, d, DZ) == 0.0
    grown = d.copy()
    grown[-3, 16:48, 8:56] = True  # the span grew one layer down
    assert metrics.overhang_thickness_error_um(grown, d, DZ) == pytest.approx(DZ)
    from scipy import ndimage

    thick = np.stack([ndimage.binary_dilation(layer) for layer in d])  # one pixel thicker all round
    assert metrics.wall_thickness_error_um(thick, d, PX) == pytest.approx(2 * PX, rel=0.25)
    assert metrics.wall_thickness_error_um(d, d, PX) == 0.0


# ----------------------------------------------------------------- compensation
@pytest.fixture(scope="module")
def params():
    return default_params(pixel_size_um=PX).with_values(sigma_px=3.0, T=0.5)


def test_ilt_over_layers_beats_identical_masks_at_the_best_dose(params):
    d = bridge()
    masks, info = optimise_layers(d, params, DEPTH, schedule=((2, 30), (1, 15)))
    assert masks.shape == d.shape and masks.dtype == np.uint8
    assert info["model_iou"] > info["identical_model_iou"] + 0.03
    model = params.build()
    th = model.theta(params.values)
    printed = (layer_dose(model, torch.from_numpy(masks / 255.0).float(), th, DEPTH, DZ, PX)[0] >= 0.5).numpy()
    k = info["identical_best_dose"]
    same = (layer_dose(model, torch.from_numpy(d * k).float(), th, DEPTH, DZ, PX)[0] >= 0.5).numpy()
    assert metrics.iou(printed, d) == pytest.approx(info["model_iou"])
    # the overhang: identical masks cure the void under the span, the ILT masks much less
    assert metrics.overhang_thickness_error_um(printed, d, DZ) < 0.5 * metrics.overhang_thickness_error_um(same, d, DZ)


def test_exposure_bound_is_kept(params):
    masks, _ = optimise_layers(bridge(L=3, n=32), params, DEPTH, schedule=((1, 5),), exposure_max=0.6)
    assert masks.max() <= round(0.6 * 255)


def test_best_uniform_dose_is_the_best_of_its_grid(params):
    d = bridge()
    k, best = best_uniform_dose(d, params, DEPTH, PX, doses=(0.4, 0.7, 1.0))
    model = params.build()
    th = model.theta(params.values)
    for other in (0.4, 0.7, 1.0):
        p = (layer_dose(model, torch.from_numpy(d * other).float(), th, DEPTH, DZ, PX)[0] >= 0.5).numpy()
        assert metrics.iou(p, d) <= best + 1e-12


# ------------------------------------------------------------------ files, CLI
def test_depth_file_is_checked(tmp_path):
    f = tmp_path / "depth.yaml"
    f.write_text(yaml.safe_dump(DEPTH))
    assert load_depth(f) == DEPTH
    f.write_text(yaml.safe_dump(dict(DEPTH, diffusion_um=70)))
    with pytest.raises(InputError, match="diffusion_um"):
        load_depth(f)
    f.write_text(yaml.safe_dump(dict(DEPTH, att_lenght_um=3)))
    with pytest.raises(InputError, match="unknown"):
        load_depth(f)


def test_cli_compensate3d(tmp_path, params):
    for name, d in (("bridge", bridge(L=4, n=32)), ("tube", tube())):
        for j, layer in enumerate(d):
            write_png(tmp_path / "designs" / name / f"{j:03d}.png", layer)
    save_params(tmp_path / "params.yaml", params)
    (tmp_path / "depth.yaml").write_text(yaml.safe_dump(DEPTH))
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["compensate3d", str(tmp_path / "designs"), "--params", str(tmp_path / "params.yaml"),
                                  "--depth", str(tmp_path / "depth.yaml"), "-o", str(out), "--name", "bridge"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (out / "bridge").iterdir()) == [f"{j:03d}.png" for j in range(4)]
    assert read_mask(out / "bridge" / "000.png").shape == (32, 32) and (out / "compensation3d.tsv").is_file()
    assert not (out / "tube").exists()
    bad = CliRunner().invoke(main, ["compensate3d", str(tmp_path / "designs"), "--params", str(tmp_path / "params.yaml"),
                                    "--depth", str(tmp_path / "depth.yaml"), "-o", str(tmp_path / "o2"), "--name", "x"])
    assert bad.exit_code == 2 and "x" in bad.output
    assert read_design3d(tmp_path / "designs" / "tube").shape == (4, 48, 48)
    # the print job frames every design with registration marks in a margin, and the
    # scoring cuts a print of it back to the design's field
    from unscatter.compensation3d import frame3d, job_margin, unframe3d, write_job3d
    from unscatter.io import read_tsv

    rows = write_job3d(tmp_path / "designs", out, tmp_path / "params.yaml", tmp_path / "depth.yaml", tmp_path / "job")
    m = job_margin(32)
    assert {r["id"] for r in rows} == {"bridge__ilt", "bridge__identical"}
    assert {int(r["margin_px"]) for r in read_tsv(tmp_path / "job" / "job.tsv")} == {m}
    ilt = np.stack([read_mask(tmp_path / "job" / "masks" / "bridge__ilt" / f"{j:03d}.png") for j in range(4)])
    assert ilt.shape == (4, 32 + 2 * m, 32 + 2 * m)
    assert np.array_equal(ilt[:, m:m + 32, m:m + 32], np.stack([read_mask(out / "bridge" / f"{j:03d}.png") for j in range(4)]))
    ring = np.ones(ilt.shape[1:], bool)
    ring[m // 2:-(m // 2), m // 2:-(m // 2)] = False
    marks = ilt[0] > 0
    assert marks[ring].sum() > 0 and not marks[~ring & ~np.pad(np.ones((32, 32), bool), m)].any()  # marks in the outer half
    framed = frame3d(bridge(L=4, n=32), m)
    assert np.array_equal(unframe3d(framed, 32, "x"), bridge(L=4, n=32))
    with pytest.raises(InputError, match="fits neither"):
        unframe3d(framed[:, 1:, 1:], 32, "x")
