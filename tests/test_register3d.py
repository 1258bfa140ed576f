"""Registration of confocal z-stacks to layer masks (unscatter.imaging.stack)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import tifffile
from click.testing import CliRunner

from unscatter.calibration3d import trial_masks3d
from unscatter.cli import main
from unscatter.imaging import register_stacks
from unscatter.imaging.stack import axial_profile, fit_axial
from unscatter.io import InputError, read_print, read_tsv, write_png
from unscatter.lab import print_layers
from unscatter.metrics import iou

OVER = dict(printer=dict(pad_px=64), microscope=dict(image_size=[256, 256]))


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    root = tmp_path_factory.mktemp("stacks")
    ms = {k: v for k, v in trial_masks3d(8, layers=6, size=128, seed=3).items() if k.startswith(("channel", "stairs"))}
    for mid, m in ms.items():
        for j, layer in enumerate(m):
            write_png(root / "masks" / mid / f"{j:03d}.png", layer)
    print_layers(root / "masks", root / "batch", overrides=OVER, progress=False)
    return root, ms


def test_fit_axial_finds_the_bottom():
    z = np.arange(0, 200, 10.0)
    area = np.array([1.0, 1.0, 0.5, 0.5])
    prof = 3.0 * axial_profile(37.0, 6.0, z, area, 25.0) + 0.2
    r = fit_axial(prof, z, area, 25.0)
    assert r["bottom_um"] == pytest.approx(37.0, abs=1.0) and r["r2"] > 0.999


def test_stacks_register_or_fail_never_silently_wrong(batch, tmp_path):
    root, ms = batch
    rows = register_stacks(root / "batch", tmp_path / "reg", skip_failed=True, progress=False)
    truth_pose = {r["id"]: r for r in read_tsv(root / "batch.truth" / "transforms.tsv")}
    ok = [r for r in rows if r["status"] == "ok"]
    assert len(ok) >= 2
    for r in ok:
        L = len(ms[r["id"]])
        truth = np.stack([read_print(root / "batch.truth" / "prints" / r["id"] / f"{j:03d}.png") for j in range(L)])
        vox = np.stack([read_print(tmp_path / "reg" / r["id"] / f"{j:03d}.png") for j in range(L)])
        assert iou(vox, truth) > 0.75, r["id"]
        assert abs(float(r["bottom_um"]) + float(truth_pose[r["id"]]["z0_um"])) < 10.0, r["id"]  # within a slice
        assert (tmp_path / "reg" / "overlays" / f"{r['id']}.png").is_file()
    for r in rows:
        if r["status"] == "failed":
            assert r["reason"] and not (tmp_path / "reg" / r["id"]).exists()


def test_bad_stack_batches_are_clear_errors(batch, tmp_path):
    root, ms = batch
    b = tmp_path / "b"
    shutil.copytree(root / "batch", b)
    first = next(iter(ms))
    (b / "masks" / first / "002.png").unlink()
    with pytest.raises(InputError, match="002.png"):
        register_stacks(b, tmp_path / "o1", progress=False)
    shutil.rmtree(b)
    shutil.copytree(root / "batch", b)
    st = tifffile.imread(b / "images" / f"{first}.tif")
    tifffile.imwrite(b / "images" / f"{first}.tif", st[:3], photometric="minisblack")  # too few slices for the depth
    with pytest.raises(InputError, match="cover"):
        register_stacks(b, tmp_path / "o2", progress=False)
    yml = b / "batch.yaml"
    text = yml.read_text()
    for extra, key in (("dense_level: 3.0\n", "dense_level"), ("dense_reference: [x]\n", "dense_reference")):
        yml.write_text(text + extra)  # a widefield image's level: not a stack's
        with pytest.raises(InputError, match=f"{key} is for single-layer"):
            register_stacks(b, tmp_path / "o4", progress=False)
    yml.write_text(text)
    (b / "images" / f"{first}.tif").unlink()
    r = CliRunner().invoke(main, ["register3d", str(b), str(tmp_path / "o3")])
    assert r.exit_code == 2 and "no z-stack" in r.output and not (tmp_path / "o3").exists()


def test_registered_stacks_calibrate_and_score(batch, tmp_path):
    """The chain after registration: depth calibration on the voxel prints, and the 3-D
    benchmark's scoring of registered prints against designs."""
    import yaml

    from unscatter.calibration3d import calibrate3d
    from unscatter.compensation3d import load_depth, score3d_batch
    from unscatter.model import default_params, save_params

    root, ms = batch
    register_stacks(root / "batch", tmp_path / "reg", skip_failed=True, progress=False)
    save_params(tmp_path / "p.yaml", default_params(pixel_size_um=2.96).with_values(sigma_px=4.0))
    r = calibrate3d(tmp_path / "reg", tmp_path / "p.yaml", tmp_path / "cal", steps=10)
    depth = load_depth(tmp_path / "cal" / "depth.yaml")  # within its bounds, or this raises
    assert depth["layer_um"] == 50.0 and r["prints"] >= 2 and 0 < r["fit_voxel_iou"] <= 1
    assert yaml.safe_load((tmp_path / "cal" / "params.yaml").read_text())["depth_fit"]["free"] == ["sigma_px", "T"]
    for mid, m in ms.items():
        for j, layer in enumerate(m):
            write_png(tmp_path / "designs" / mid / f"{j:03d}.png", layer > 0)
    # two registered batches calibrate together, their prints named by batch; the spread
    # comes from the bootstrap; a batch of another layer thickness is refused
    shutil.copytree(tmp_path / "reg", tmp_path / "reg2")
    r2 = calibrate3d([tmp_path / "reg", tmp_path / "reg2"], tmp_path / "p.yaml", tmp_path / "cal2", steps=4, bootstrap=2)
    assert r2["prints"] == 2 * r["prints"] and r2["bootstrap"] == 2 and set(r2["spread"]) == set(r2["values"])
    fit = (tmp_path / "cal2" / "fit.tsv").read_text()
    assert "reg:" in fit and "reg2:" in fit and (tmp_path / "cal2" / "bootstrap.tsv").is_file()
    meta = yaml.safe_load((tmp_path / "reg2" / "batch.yaml").read_text())
    (tmp_path / "reg2" / "batch.yaml").write_text(yaml.safe_dump(dict(meta, layer_um=25)))
    with pytest.raises(InputError, match="layer_um 25 and pixel_size_um"):
        calibrate3d([tmp_path / "reg", tmp_path / "reg2"], tmp_path / "p.yaml", tmp_path / "cal3", steps=2)
    assert not (tmp_path / "cal3").exists()
    rows = score3d_batch(tmp_path / "reg", tmp_path / "designs", tmp_path / "scores")
    assert {r["id"] for r in rows} == set(ms)
    assert all(0.5 < r["iou"] <= 1 for r in rows if r["status"] == "ok")
    assert (tmp_path / "scores" / "sections.png").is_file() and (tmp_path / "scores" / "metrics.tsv").is_file()


def test_the_threshold_falloff_comes_from_the_dense_polymer_not_the_print_shape():
    """A print grown beyond its masks (an overhang cured down to the floor) has a flat
    dense level: no fall-off to undo, so its lower layers keep their voxels. A real
    fall-off is found despite layers that did not cure as their mask says, either way up."""
    from unscatter.imaging.stack import dense_falloff

    L, S = 12, 40
    z = (np.arange(L) + 0.5) * 40.0
    solid = np.zeros((L, S, S), bool)
    solid[:, 10:20, 10:20] = True
    solid[8:, 10:30, 10:30] = True  # a deck over the top layers
    grown = np.zeros((L, S, S))
    grown[:, 10:30, 10:30] = 1.0  # the deck cured down to the floor, dense polymer everywhere
    assert abs(dense_falloff(grown, solid, z)) > 1e4
    rng = np.random.default_rng(0)
    for f in (300.0, -500.0):
        at = solid * np.exp(-z / f)[:, None, None] * (1 + 0.02 * rng.standard_normal((L, S, S)))
        at[[2, 7]] *= 0.4  # two layers that cured less than their masks say
        assert dense_falloff(at, solid, z) == pytest.approx(f, rel=0.1)
