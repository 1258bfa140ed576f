"""Compensation: ILT, nn and nn+ilt masks beat identical masks on the simulator; 8-bit
masks of the design's size; the DMD frame; the command line."""

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from unscatter import metrics
from unscatter.compensation import (
    DMD_FRAME,
    ILT_DEFAULTS,
    compensate,
    compensate_designs,
    dmd_frame,
    load_printer,
    optimise_mask,
    write_mask_and_frame,
)
from unscatter.io import read_mask, read_tsv, write_png
from unscatter.model import default_params, save_params, simulate

PX_UM = 2.96
# A plausible calibrated printer: sigma 5 px (~15 um), threshold at half the full-grey dose.
VALUES = dict(c1=-0.06, c2=-0.04, c3=0.03, c4=-0.02, sigma_px=5.0, T=0.5)
FAST = dict(threads=1)


@pytest.fixture(scope="module")
def params_path(tmp_path_factory):
    root = tmp_path_factory.mktemp("calibration")
    save_params(root / "params.yaml", default_params(pixel_size_um=PX_UM).with_values(**VALUES))
    return root / "params.yaml"


@pytest.fixture(scope="module")
def star():
    return read_mask("data/designs/star.png") != 0


@pytest.fixture(scope="module")
def cross():
    return read_mask("data/designs/cross.png") != 0


@pytest.fixture(scope="module")
def tiny_net(params_path, tmp_path_factory):
    """A seconds-long training run (the 'ci' preset): enough to exercise nn and nn+ilt."""
    training = pytest.importorskip("unscatter.training", reason="the network training code is not available")
    from unscatter.augment import augment

    root = tmp_path_factory.mktemp("tiny_net")
    augment(params_path, root / "eq1.zarr", count=24, seed=1, size=512, progress=False)
    training.train(root / "eq1.zarr", root / "train", preset="ci", settings=dict(epochs=2), threads=1, progress=False)
    return root / "train"


def _scores(params_path, mask, design):
    printed = simulate(params_path, mask)
    return metrics.iou(printed, design), metrics.epe_um(printed, design, PX_UM)


def _identical(design):
    return design.astype(np.uint8) * 255


def _check_mask(mask, design):
    assert isinstance(mask, np.ndarray) and mask.dtype == np.uint8 and mask.shape == design.shape


# ------------------------------------------------------------------------------ ILT


@pytest.mark.parametrize("name", ["star", "cross"])
def test_ilt_beats_the_identical_mask(name, params_path, request):
    design = request.getfixturevalue(name)
    mask, info = optimise_mask(design, params_path, **FAST)
    _check_mask(mask, design)
    iou_c, epe_c = _scores(params_path, mask, design)
    iou_i, epe_i = _scores(params_path, _identical(design), design)
    assert iou_c > iou_i and epe_c < epe_i
    assert iou_c > 0.995 and epe_c < 0.5 * epe_i
    assert info["model_iou"] == pytest.approx(iou_c, abs=1e-6)  # the summary scores the same print
    assert info["loss"][-1] < info["loss"][0]
    assert info["steps"] == sum(n for _, n in ILT_DEFAULTS["schedule"])
    # it is a real grey-level mask, not the design: light added at the tips, taken at notches
    assert (mask[~design] > 127).any() and (mask[design] < 128).any()


def test_ilt_stretches_out_at_the_tips(params_path, star):
    """Fig. 5(e): the mask 'stretches out' at protruding sharp features."""
    mask = compensate(star, "ilt", params_path=params_path, **FAST)
    tip_row = np.nonzero(star.any(axis=1))[0][0]  # the star's top tip
    col = np.nonzero(star[tip_row])[0].mean()
    above = mask[max(tip_row - 6, 0) : tip_row, int(col) - 3 : int(col) + 4]
    assert above.max() > 127


def test_robust_ilt_narrows_the_pv_band(params_path, cross):
    p = load_printer(params_path)
    plain = compensate(cross, "ilt", params_path=p, robust=False, **FAST)
    robust = compensate(cross, "ilt", params_path=p, robust=True, **FAST)

    def pv(mask):
        lo = simulate(p.with_values(T=p.values["T"] / 0.9), mask)
        hi = simulate(p.with_values(T=p.values["T"] / 1.1), mask)
        return metrics.pv_band_um(lo, hi, cross, PX_UM)

    assert pv(robust) < pv(plain)
    iou_r, _ = _scores(params_path, robust, cross)
    assert iou_r > _scores(params_path, _identical(cross), cross)[0]


def test_ilt_is_deterministic_and_honours_the_schedule(params_path, cross):
    small = dict(schedule=((4, 5), (1, 2)), **FAST)
    a, ia = optimise_mask(cross, params_path, **small)
    b, _ = optimise_mask(cross, params_path, **small)
    assert np.array_equal(a, b) and ia["steps"] == 7


def test_odd_sized_designs_skip_coarse_grids(params_path):
    d = np.zeros((90, 70), bool)
    d[20:70, 15:55] = True
    m, info = optimise_mask(d, params_path, schedule=((4, 3), (2, 3), (1, 2)), **FAST)
    assert m.shape == d.shape and info["steps"] == 5  # 90 x 70: only 2 and 1 divide it


def test_calibration_folder_and_bad_settings(params_path, cross):
    assert load_printer(params_path.parent).values == load_printer(params_path).values
    with pytest.raises(ValueError, match="unknown compensation setting"):
        compensate(cross, "ilt", params_path=params_path, learning_rate=1)
    with pytest.raises(ValueError, match="full resolution"):
        compensate(cross, "ilt", params_path=params_path, schedule=((4, 10),))
    with pytest.raises(ValueError, match="unknown compensation method"):
        compensate(cross, "magic", params_path=params_path)
    with pytest.raises(ValueError, match="needs the calibrated printer"):
        compensate(cross, "ilt")
    with pytest.raises(ValueError, match="training folder"):
        compensate(cross, "nn")


def test_threads_setting_is_restored(params_path, cross):
    before = torch.get_num_threads()
    optimise_mask(cross, params_path, schedule=((4, 2), (1, 1)), threads=1)
    assert torch.get_num_threads() == before


# ------------------------------------------------------------------------ nn, nn+ilt


def test_nn_and_nn_ilt(params_path, cross, tiny_net):
    nn = compensate(cross, "nn", train_dir=tiny_net)
    _check_mask(nn, cross)
    refined = compensate(cross, "nn+ilt", params_path=params_path, train_dir=tiny_net, **FAST)
    _check_mask(refined, cross)
    # the tiny net alone is no compensation (seconds of training); a few ILT steps from it are
    iou_r, epe_r = _scores(params_path, refined, cross)
    iou_n, _ = _scores(params_path, nn, cross)
    iou_i, epe_i = _scores(params_path, _identical(cross), cross)
    assert iou_r > iou_n
    assert iou_r > iou_i and epe_r < epe_i
    with pytest.raises(ValueError, match="params.yaml too"):
        compensate(cross, "nn+ilt", train_dir=tiny_net)


# ------------------------------------------------------------------------- DMD frame


def test_dmd_frame_places_the_mask_at_the_offset(tmp_path):
    rng = np.random.default_rng(0)
    mask = rng.integers(1, 256, (512, 512), dtype=np.uint8)
    for offset, expect in ((None, ((1600 - 512) // 2, (2560 - 512) // 2)), ((10, 2000), (10, 2000))):
        off = write_mask_and_frame(mask, tmp_path / "mask.png", tmp_path / "frame.png", offset=offset)
        assert off == expect
        frame = read_mask(tmp_path / "frame.png")
        assert frame.shape == DMD_FRAME == (1600, 2560)
        oy, ox = off
        assert np.array_equal(frame[oy : oy + 512, ox : ox + 512], mask)
        rest = frame.copy()
        rest[oy : oy + 512, ox : ox + 512] = 0
        assert not rest.any()
        assert np.array_equal(read_mask(tmp_path / "mask.png"), mask)
    with pytest.raises(ValueError, match="does not fit"):
        dmd_frame(mask, offset=(1200, 0))
    with pytest.raises(ValueError, match="uint8"):
        dmd_frame(mask.astype(np.float32))


def test_compensate_designs_writes_masks_frames_and_timings(params_path, tmp_path, cross):
    designs = tmp_path / "designs"
    write_png(designs / "cross.png", cross)
    out = tmp_path / "ilt"
    rows = compensate_designs(designs, out, "ilt", params_path=params_path, schedule=((4, 10), (1, 2)), **FAST)
    assert [r["design"] for r in rows] == ["cross"]
    m = read_mask(out / "cross.png")
    f = read_mask(out / "frames" / "cross.png")
    _check_mask(m, cross)
    assert f.shape == DMD_FRAME and f.sum(dtype=np.int64) == m.sum(dtype=np.int64)
    assert read_tsv(out / "compensation.tsv")[0]["method"] == "ilt"


# ------------------------------------------------------------------------------- CLI


def test_cli_compensate_ilt(params_path, tmp_path, cross):
    from unscatter.cli import main

    write_png(tmp_path / "cross.png", cross)
    r = CliRunner().invoke(main, ["compensate", str(tmp_path / "cross.png"), "--model", str(params_path.parent),
                                  "--method", "ilt", "-o", str(tmp_path / "m.png"), "--frame", str(tmp_path / "f.png"),
                                  "--robust"])
    assert r.exit_code == 0, r.output
    m = read_mask(tmp_path / "m.png")
    _check_mask(m, cross)
    assert read_mask(tmp_path / "f.png").shape == DMD_FRAME
    assert _scores(params_path, m, cross)[0] > _scores(params_path, _identical(cross), cross)[0]


def test_cli_compensate_bad_model(tmp_path, cross):
    from unscatter.cli import main

    write_png(tmp_path / "cross.png", cross)
    (tmp_path / "empty").mkdir()
    r = CliRunner().invoke(main, ["compensate", str(tmp_path / "cross.png"), "--model", str(tmp_path / "empty"),
                                  "--method", "ilt", "-o", str(tmp_path / "m.png")])
    assert r.exit_code == 2 and "params.yaml" in r.output
