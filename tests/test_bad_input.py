"""Every kind of bad print batch gets a clear error naming the file and the problem."""

import shutil

import numpy as np
import pytest
import tifffile
import yaml
from click.testing import CliRunner
from PIL import Image

from unscatter.cli import main
from unscatter.imaging import register_batch
from unscatter.io import InputError, open_batch, read_mask


@pytest.fixture
def batch(lab_batch, tmp_path):
    """A private copy of the lab batch to spoil."""
    b = tmp_path / "batch"
    shutil.copytree(lab_batch, b)
    return b


def _register_error(batch, tmp_path) -> InputError:
    with pytest.raises(InputError) as exc:
        register_batch(batch, tmp_path / "out", progress=False)
    return exc.value


def test_missing_image(batch, tmp_path):
    (batch / "images" / "trial_003.tif").unlink()
    err = _register_error(batch, tmp_path)
    assert err.path.name == "images" and "trial_003" in err.problem and "no image" in err.problem


def test_extra_image(batch, tmp_path):
    shutil.copyfile(batch / "images" / "trial_003.tif", batch / "images" / "stray.tif")
    err = _register_error(batch, tmp_path)
    assert "stray.tif" in str(err) and "without a mask" in err.problem


def test_truncated_tiff(batch, tmp_path):
    p = batch / "images" / "trial_004.tif"
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 3])
    err = _register_error(batch, tmp_path)
    assert err.path == p and ("truncated" in err.problem or "unreadable" in err.problem)


def test_unreadable_image(batch, tmp_path):
    p = batch / "images" / "trial_004.tif"
    p.write_bytes(b"this is not a tiff")
    err = _register_error(batch, tmp_path)
    assert err.path == p and "cannot read" in err.problem


def test_constant_image(batch, tmp_path):
    p = batch / "images" / "trial_005.tif"
    tifffile.imwrite(p, np.full((720, 720), 100, np.uint16))
    err = _register_error(batch, tmp_path)
    assert err.path == p and "constant" in err.problem


def test_saturated_image(batch, tmp_path):
    p = batch / "images" / "trial_005.tif"
    img = tifffile.imread(p)
    img[img > np.percentile(img, 80)] = 65535
    tifffile.imwrite(p, img)
    err = _register_error(batch, tmp_path)
    assert err.path == p and "saturated" in err.problem


def test_colour_image(batch, tmp_path):
    p = batch / "images" / "trial_005.tif"
    tifffile.imwrite(p, np.zeros((720, 720, 3), np.uint8) + 7)
    (batch / "images" / "trial_005.tif")
    err = _register_error(batch, tmp_path)
    assert err.path == p and "colour" in err.problem


@pytest.mark.parametrize("kind", ["rgb", "16bit"])
def test_mask_not_8bit_grayscale(batch, tmp_path, kind):
    p = batch / "masks" / "trial_000.png"
    m = read_mask(p)
    if kind == "rgb":
        Image.fromarray(np.stack([m] * 3, -1), mode="RGB").save(p)
    else:
        Image.fromarray(m.astype(np.uint16) * 257).save(p)
    err = _register_error(batch, tmp_path)
    assert err.path == p and "8-bit grayscale" in err.problem


@pytest.mark.parametrize(
    "edit, words",
    [
        (lambda d: d.pop("pixel_size_um"), "missing field 'pixel_size_um'"),
        (lambda d: d.update(exposure_s=-20), "'exposure_s' must be a positive number"),
        (lambda d: d.update(max_intensity_mw_cm2="bright"), "'max_intensity_mw_cm2' must be a number"),
        (lambda d: d.update(pixel_size_um=2960), "not a plausible DMD pixel size"),
        (lambda d: d.update(material=""), "'material' must be a non-empty string"),
    ],
)
def test_bad_batch_yaml(batch, tmp_path, edit, words):
    p = batch / "batch.yaml"
    d = yaml.safe_load(p.read_text())
    edit(d)
    p.write_text(yaml.safe_dump(d))
    err = _register_error(batch, tmp_path)
    assert err.path == p and words in err.problem


def test_batch_yaml_not_a_mapping(batch, tmp_path):
    (batch / "batch.yaml").write_text("- just\n- a list\n")
    err = _register_error(batch, tmp_path)
    assert "mapping" in err.problem


def test_cli_reports_bad_input_in_one_line(batch, tmp_path):
    (batch / "images" / "trial_003.tif").unlink()
    res = CliRunner().invoke(main, ["register", str(batch), str(tmp_path / "out")])
    assert res.exit_code == 2
    assert "error:" in res.output and "trial_003" in res.output and "Traceback" not in res.output


def test_nothing_is_written_into_the_batch(lab_batch, tmp_path):
    before = sorted((p.relative_to(lab_batch), p.stat().st_mtime_ns) for p in lab_batch.rglob("*"))
    register_batch(lab_batch, tmp_path / "out", progress=False)
    after = sorted((p.relative_to(lab_batch), p.stat().st_mtime_ns) for p in lab_batch.rglob("*"))
    assert before == after


def test_open_batch_pairs_masks_and_images(lab_batch):
    b = open_batch(lab_batch)
    assert set(b.ids) == set(b.images) and len(b.ids) == 11
    assert b.meta.pixel_size_um == pytest.approx(2.96)
