"""Registration that is never silently wrong: periodic prints, swapped images, ambiguity,
images that are no prints, and pose priors from metadata."""

import shutil
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy import ndimage
import pytest
import tifffile

from unscatter import masks as patterns
from unscatter.imaging import register_batch, transform_rms_px
from unscatter.imaging.priors import image_pixel_size_um, rotation_range, scale_range
from unscatter.io import InputError, read_print, read_tsv, read_yaml, write_png
from unscatter.lab import print_batch


def _matrix(row):
    return np.array([[float(row[f"m{a}{b}"]) for b in range(3)] for a in range(2)])


def _printed_alone(root, name, mask, overrides, seed):
    """One mask printed on the virtual lab: its corrected image, smoothed as the pose
    search sees it, and the true pose on the registration's padded grid (``to_design``
    the other way)."""
    import cv2

    from unscatter.imaging.batch import MARGIN, Settings
    from unscatter.imaging.flatfield import correct_image
    from unscatter.imaging.pose import to_design

    write_png(root / "masks" / f"{name}.png", mask)
    print_batch(root / "masks", root / "batch", overrides=overrides, seed=seed, progress=False)
    k = correct_image(name, next((root / "batch" / "images").iterdir()), 0.0, Settings(), "divide")
    return cv2.GaussianBlur(k.c, (0, 0), 1.0), to_design(_matrix(read_tsv(root / "batch.truth" / "transforms.tsv")[0]), -MARGIN)


def _pose_errors(reg_dir, truth_dir):
    """id -> (status, reason, pose error in design px or nan)."""
    truth = {r["id"]: r for r in read_tsv(truth_dir / "transforms.tsv")}
    out = {}
    for q in read_tsv(reg_dir / "qc.tsv"):
        err = transform_rms_px(_matrix(q), _matrix(truth[q["id"]]), 512) if q["m00"] != "" else float("nan")
        out[q["id"]] = (q["status"], q["reason"], err)
    return out


@pytest.fixture(scope="module")
def grating_batch(tmp_path_factory):
    """Gratings of 6 to 24 px pitch, a cut-off grating and trial masks, printed on a lab
    with stronger scatter and blur than the default one."""
    root = tmp_path_factory.mktemp("gratings")
    m = root / "masks"
    rng = np.random.default_rng(7)
    for i, (pitch, angle) in enumerate([(6, 0), (10, 90), (16, 45), (24, 0)]):
        write_png(m / f"grating_{i}.png", patterns.grating(rng, pitch=pitch, duty=0.5, angle_deg=angle))
    write_png(m / "cutoff.png", patterns.grating_cutoff(rng, pitch=12, duty=0.5, angle_deg=90))
    for k, mask in patterns.trial_masks(6, seed=3).items():
        write_png(m / f"{k}.png", mask)
    over = {"microscope": {"blur_px": [1.0, 2.0], "rotation_deg": 12.0, "scale": [0.75, 1.3]},
            "printer": {"kernel": {"sigma_um": 15.0}}}
    print_batch(m, root / "batch", overrides=over, seed=21, progress=False)
    register_batch(root / "batch", root / "reg", skip_failed=True, progress=False)
    return root


def test_trial_prints_register_and_gratings_are_not_given_up(grating_batch):
    errs = _pose_errors(grating_batch / "reg", grating_batch / "batch.truth")
    trial = [errs[k] for k in errs if k.startswith("trial")]
    assert all(st == "ok" and e <= 1.5 for st, _, e in trial) and np.median([e for _, _, e in trial]) < 0.6, trial
    assert sum(errs[k][0] == "ok" for k in errs if k.startswith("grating")) >= 2, errs
    # what is not ok says why, and gets no print
    for k, (st, why, _) in errs.items():
        assert st == "ok" or (why and not (grating_batch / "reg" / f"{k}.png").exists()), (k, st, why)


def test_no_print_is_ok_with_its_pose_off(grating_batch):
    """A 6 px pitch grating that this lab prints as one block has a scale that only its
    size sets: it fails as not determined rather than passing 2 to 3 % off in scale."""
    errs = _pose_errors(grating_batch / "reg", grating_batch / "batch.truth")
    wrong = {k: v for k, v in errs.items() if v[0] == "ok" and not v[2] <= 1.5}
    assert not wrong, wrong


def test_a_print_whose_size_sets_its_scale_says_what_would_hold_it(grating_batch):
    """The batch states no camera pixel size and zooms by image: a print that fails because
    its scale rests on the size of a feature (the 6 px grating printed as one block) says
    that a stated pixel size would hold it, and where to state one."""
    sized = [why for st, why, _ in _pose_errors(grating_batch / "reg", grating_batch / "batch.truth").values()
             if st == "failed" and "size of a feature" in why]
    assert sized
    assert all("no camera pixel size is stated" in why and "image_pixel_size_um" in why for why in sized), sized
    # ... within its one reason (QC reasons are split on "; "): the print is undetermined, its
    # fit as good as an ok print's, and the mismatch test compares with it (``determinacy_only``)
    parts = [part for why in sized for part in why.split("; ")]
    assert not [part for part in parts if part.startswith("no camera pixel size")], sized


def test_a_grating_started_one_pitch_off_is_never_ok_there(grating_batch):
    """Start the pose search one pitch off: the chosen pose comes back, or the print fails
    (ambiguous, or, for a 10 px grating that this lab prints as one block and that settles
    2.8 px off, because its scale rests on the size of that block)."""
    import cv2

    from unscatter.imaging.batch import MARGIN, Settings, choose_pose, predicted_print
    from unscatter.imaging.pose import merged_features, size_spread, to_design
    from unscatter.imaging.flatfield import correct_image
    from unscatter.imaging.template import PrintTemplate
    from unscatter.io import read_mask, read_yaml

    reg = read_yaml(grating_batch / "reg" / "registration.yaml")
    x = np.array([reg["print_template"][k] for k in PrintTemplate.NAMES])
    truth = {r["id"]: r for r in read_tsv(grating_batch / "batch.truth" / "transforms.tsv")}
    s = Settings()
    for mid, pitch in (("grating_1", 10), ("grating_3", 24)):
        k = correct_image(mid, grating_batch / "batch" / "images" / f"{mid}.tif", 100.0, s, reg["flatfield"])
        img = cv2.GaussianBlur(k.c, (0, 0), 1.0)
        mask = read_mask(grating_batch / "batch" / "masks" / f"{mid}.png")
        Mg = to_design(_matrix(truth[mid]), -MARGIN)  # design -> grid
        across = np.array([0.0, 1.0]) if mid == "grating_1" else np.array([1.0, 0.0])  # 90 deg: lines along x
        off = Mg.copy()
        off[:, 2] += Mg[:, :2] @ (pitch * across)
        ch = choose_pose(mask, img, [off], x, s, 512, s.scale_range)
        grid_err = transform_rms_px(ch.fit.M, Mg, 512 + 2 * MARGIN)
        tmpl = PrintTemplate(512, MARGIN)
        T = predicted_print(tmpl, tmpl.exposure(tmpl.padded(mask), x), x, ch.fit)
        size_fails = merged_features(T, tmpl.padded(mask)) and size_spread(T, s.mode) > s.max_size_sd  # as register_batch
        assert grid_err <= 1.5 or ch.evidence < s.min_evidence or size_fails, (mid, grid_err, ch.evidence)


def test_a_grating_whose_fits_stay_a_pitch_either_side_finds_the_pose_between(tmp_path, monkeypatch):
    """A 25 px grating printed on a random lab (zoom by image, 18 um scatter, 18 % haze),
    the pose search started a pitch either side of the true pose and no self-similar moves
    to reach it from there. Both fits stay where they started and fit alike, so neither
    is a rival of the other, but the pose halfway between fits far better: it is refined
    and chosen (before, the print was ok a pitch off, with no rival). The template's
    numbers are the ones this lab's batch of 32 test prints fitted."""
    import unscatter.imaging.batch as batch
    from unscatter.lab import random_lab
    from unscatter.masks import test_pattern_masks

    over = random_lab(np.random.default_rng([172094, 3, 0]))
    mask = test_pattern_masks(32, seed=3071290980)["grating_014"]
    img, Mg = _printed_alone(tmp_path, "grating_014", mask, over, 5)
    x = np.array([5.7914, 0.3394, 0.1517, 0.1242, -0.1236, 0.1681, -0.0728, 0.0105, -0.2713, 15.0, 4.0354, 0.2849, 9.6736])
    s = batch.Settings()
    starts = []
    for sign in (1, -1):  # the lines run along x: a pitch is 25 px along y
        off = Mg.copy()
        off[:, 2] += Mg[:, :2] @ np.array([0.0, 25.0 * sign])
        starts.append(off)
    monkeypatch.setattr(batch, "self_similar_moves", lambda *a, **kw: [])
    ch = batch.choose_pose(mask, img, starts, x, s, 512, s.scale_range)
    grid_err = transform_rms_px(ch.fit.M, Mg, 512 + 2 * batch.MARGIN)
    assert grid_err <= 1.5 or ch.evidence < s.min_evidence, (grid_err, ch.evidence)  # never ok a pitch off
    assert grid_err <= 1.5, grid_err  # and here the pose between them is found


def test_swapped_images_both_fail(tmp_path, grating_batch):
    batch = tmp_path / "batch"
    shutil.copytree(grating_batch / "batch", batch)
    a, b = batch / "images" / "trial_000.tif", batch / "images" / "trial_003.tif"  # two checkerboards
    tmp = a.read_bytes()
    a.write_bytes(b.read_bytes())
    b.write_bytes(tmp)
    rows = {r["id"]: r for r in register_batch(batch, tmp_path / "reg", skip_failed=True, progress=False)}
    for mid in ("trial_000", "trial_003"):
        assert rows[mid]["status"] == "failed", rows[mid]
        assert "does not match its mask" in rows[mid]["reason"] or "ambiguous" in rows[mid]["reason"], rows[mid]["reason"]
        assert not (tmp_path / "reg" / f"{mid}.png").exists()
    assert rows["trial_001"]["status"] == "ok"


def test_a_star_whose_spokes_repeat_within_the_rotation_range_is_ambiguous(tmp_path):
    m = tmp_path / "masks"
    rng = np.random.default_rng(1)
    write_png(m / "star.png", patterns.siemens_star(rng, spokes=24))  # 15 deg period, range +-20
    for k, mask in patterns.trial_masks(4, seed=9).items():
        write_png(m / f"{k}.png", mask)
    print_batch(m, tmp_path / "batch", overrides={"microscope": {"rotation_deg": 5.0}}, seed=4, progress=False)
    rows = {r["id"]: r for r in register_batch(tmp_path / "batch", tmp_path / "reg", skip_failed=True, progress=False)}
    errs = _pose_errors(tmp_path / "reg", tmp_path / "batch.truth")
    star = rows["star"]
    # one spoke off would print the same star: never 'ok' there, and said to be ambiguous
    assert star["status"] == "failed" or errs["star"][2] <= 1.5, (star, errs["star"])
    if star["status"] == "failed":
        assert "ambiguous" in star["reason"] or "not determined" in star["reason"], star["reason"]


def test_an_image_that_is_no_print_fails_instead_of_being_empty(tmp_path, grating_batch):
    batch = tmp_path / "batch"
    shutil.copytree(grating_batch / "batch", batch)
    noise = np.random.default_rng(0).integers(0, 65535, size=(720, 720), dtype=np.uint16)
    tifffile.imwrite(batch / "images" / "trial_002.tif", noise)
    rows = {r["id"]: r for r in register_batch(batch, tmp_path / "reg", skip_failed=True, progress=False)}
    assert rows["trial_002"]["status"] == "failed" and "not a print image" in rows["trial_002"]["reason"]
    assert rows["trial_001"]["status"] == "ok"


def test_a_dim_8bit_batch_whose_noise_is_below_one_count_is_still_a_batch_of_prints(tmp_path):
    """8-bit images whose background sits 4 to 5 counts above zero, with noise well under a
    count: an image whose background lies halfway between two counts reads a pixel noise of
    0.74 counts, one that lies on a count reads almost none. That is rounding, not another
    kind of image; full-range noise in the same batch still is one."""
    from PIL import Image

    from unscatter.imaging.batch import Settings, implausible
    from unscatter.imaging.flatfield import correct_image

    rng = np.random.default_rng(5)
    paths = {}
    for i, level in enumerate([4.5, 4.98, 5.0, 4.55, 4.99, 4.5, 5.02, 4.6]):
        img = level + 0.15 * rng.standard_normal((240, 240))
        img[80:160, 60:180] += 70.0  # a print
        paths[f"p{i}"] = tmp_path / f"p{i}.png"
        Image.fromarray(np.clip(np.round(img), 0, 255).astype(np.uint8)).save(paths[f"p{i}"])
    paths["noise"] = tmp_path / "noise.png"
    Image.fromarray(rng.integers(0, 256, (240, 240), dtype=np.uint8)).save(paths["noise"])
    s = Settings()
    corr = {k: correct_image(k, p, 0.0, s, "divide") for k, p in paths.items()}
    assert set(implausible(corr, s)) == {"noise"}


# ------------------------------------------------------------------------- priors


def test_camera_pixel_size_from_tiff_tags(tmp_path):
    img = np.zeros((64, 64), np.uint16)
    tifffile.imwrite(tmp_path / "ij.tif", img, imagej=True, resolution=(1 / 2.5, 1 / 2.5), metadata={"unit": "um"})
    tifffile.imwrite(tmp_path / "cm.tif", img, resolution=(1e4 / 3.2, 1e4 / 3.2), resolutionunit="CENTIMETER")
    tifffile.imwrite(tmp_path / "ome.tif", img, ome=True, metadata={"PhysicalSizeX": 650, "PhysicalSizeXUnit": "nm"})
    tifffile.imwrite(tmp_path / "dpi.tif", img, resolution=(72, 72), resolutionunit="INCH")
    tifffile.imwrite(tmp_path / "none.tif", img)
    assert image_pixel_size_um(tmp_path / "ij.tif")[0] == pytest.approx(2.5)
    assert image_pixel_size_um(tmp_path / "cm.tif")[0] == pytest.approx(3.2)
    assert image_pixel_size_um(tmp_path / "ome.tif")[0] == pytest.approx(0.65)
    assert image_pixel_size_um(tmp_path / "dpi.tif")[0] is None  # 72 dpi says nothing about a microscope
    assert image_pixel_size_um(tmp_path / "none.tif")[0] is None


def test_priors_from_batch_yaml():
    meta = {"pixel_size_um": 2.96, "image_pixel_size_um": 2.96 / 1.1, "image_rotation_deg": 5}
    (lo, hi), where = scale_range(meta, "x.png", (0.6, 1.6), 0.05, "batch.yaml")
    assert lo < 1.1 < hi and hi / lo == pytest.approx(1.05**2) and "batch.yaml" in where
    assert rotation_range(meta, (-20, 20), "batch.yaml") == (-5.0, 5.0)
    assert rotation_range({"image_rotation_deg": [-2, 8]}, (-20, 20), "b") == (-2.0, 8.0)
    assert rotation_range({}, (-20, 20), "b") == (-20, 20)
    with pytest.raises(InputError, match="image_rotation_deg"):
        rotation_range({"image_rotation_deg": "big"}, (-20, 20), "b")


def test_a_scale_prior_is_used_and_a_wrong_one_fails_loudly(tmp_path, trial_dir):
    over = {"microscope": {"scale": [1.1, 1.1], "rotation_deg": 4.0}}
    print_batch(trial_dir, tmp_path / "batch", overrides=over, seed=8, progress=False)
    yml = tmp_path / "batch" / "batch.yaml"
    text = yml.read_text()
    yml.write_text(text + f"image_pixel_size_um: {2.96 / 1.1}\nimage_rotation_deg: 5\n")
    rows = register_batch(tmp_path / "batch", tmp_path / "reg", progress=False)
    errs = _pose_errors(tmp_path / "reg", tmp_path / "batch.truth")
    assert all(r["status"] == "ok" for r in rows if float(r["solid_fraction"] or 0) > 0)
    assert max(e for s_, _, e in errs.values() if s_ == "ok") < 1.0
    # a camera pixel size 20 % off: no print is passed at the wrong scale
    yml.write_text(text + f"image_pixel_size_um: {2.96 / 1.1 * 1.2}\n")
    rows = register_batch(tmp_path / "batch", tmp_path / "reg2", skip_failed=True, progress=False)
    errs = _pose_errors(tmp_path / "reg2", tmp_path / "batch.truth")
    assert not [k for k, (st, _, e) in errs.items() if st == "ok" and not e <= 1.5]


def _edge_bias(reg_dir, truth_dir) -> list:
    """Per ok print: (registered area - true area) / true edge length, px per edge px."""
    from unscatter.io import read_print
    from unscatter.metrics import area_bias_px

    return [area_bias_px(read_print(reg_dir / f"{q['id']}.png"), read_print(truth_dir / "prints" / f"{q['id']}.png"))
            for q in read_tsv(reg_dir / "qc.tsv") if q["status"] == "ok"]


def test_a_declared_dense_level_measures_prints_that_never_cure_fully(tmp_path, trial_dir):
    """Prints whose densest polymer stays below full cure (gel dose 0.35, threshold 0.62: at
    most 0.8 of it) are measured too large when the fully cured level is estimated from the
    batch's brightest polymer; with the level the lab measured (batch.yaml dense_level, here
    the virtual microscope's 1 / background) they are measured where the density reaches the
    print level. A dense_level that is not a number is an error naming it."""
    from unscatter.lab import load_config

    over = {"printer": {"cure": {"threshold": 0.62, "gel_dose": 0.35}}}
    print_batch(trial_dir, tmp_path / "batch", overrides=over, seed=3, progress=False)
    register_batch(tmp_path / "batch", tmp_path / "reg", progress=False)
    estimated = _edge_bias(tmp_path / "reg", tmp_path / "batch.truth")
    yml = tmp_path / "batch" / "batch.yaml"
    text = yml.read_text()
    level = 1.0 / float(load_config(overrides=over)["microscope"]["background"])
    yml.write_text(text + f"dense_level: {level:.4f}\n")
    rows = register_batch(tmp_path / "batch", tmp_path / "reg2", progress=False)
    declared = _edge_bias(tmp_path / "reg2", tmp_path / "batch.truth")
    assert float(rows[0]["dense_level"]) == pytest.approx(level, rel=1e-3)
    assert len(estimated) >= 8 and len(declared) >= 8
    assert np.median(estimated) > 0.8  # too large by about a px per edge px
    assert abs(np.median(declared)) < 0.4
    yml.write_text(text + "dense_level: bright\n")
    with pytest.raises(InputError, match="dense_level"):
        register_batch(tmp_path / "batch", tmp_path / "reg3", progress=False)


def test_a_dense_reference_print_measures_the_level_that_prints_never_reach(tmp_path, trial_dir):
    """The same prints that never cure fully, with a dense reference in the batch (a large
    block printed at 4 times the exposure, batch.yaml dense_reference): the registration
    measures the fully cured level on it, within 5 % of the lab's own (1 / background), and
    the prints are measured where the density reaches the print level. The reference is no
    print (not in qc.tsv); registration.yaml records it. A reference the batch does not
    hold, one whose image shows no block, and a batch that gives dense_level as well are
    errors that name the file."""
    from unscatter.lab import load_config

    over = {"printer": {"cure": {"threshold": 0.62, "gel_dose": 0.35}}}
    masks = tmp_path / "masks"
    shutil.copytree(trial_dir, masks)
    write_png(masks / "dense_ref.png", patterns.dense_reference_mask())
    write_png(masks / "nothing.png", np.full((512, 512), 40, np.uint8))  # below the gel dose: no block
    print_batch(masks, tmp_path / "batch", overrides=over, seed=3, progress=False, exposures={"dense_ref": 4.0})
    yml = tmp_path / "batch" / "batch.yaml"
    text = yml.read_text()
    yml.write_text(text + "dense_reference: [dense_ref, nothing]\n")
    with pytest.raises(InputError, match="dense reference 'nothing'") as err:
        register_batch(tmp_path / "batch", tmp_path / "reg", progress=False)
    assert "nothing" in str(err.value.path)
    (tmp_path / "batch" / "masks" / "nothing.png").unlink()
    next((tmp_path / "batch" / "images").glob("nothing.*")).unlink()
    yml.write_text(text + "dense_reference: [dense_ref, gone]\n")
    with pytest.raises(InputError, match="'gone', which the batch does not hold") as err:
        register_batch(tmp_path / "batch", tmp_path / "reg", progress=False)
    assert err.value.path == yml
    yml.write_text(text + "dense_reference: dense_ref\ndense_level: 3.0\n")
    with pytest.raises(InputError, match="not both") as err:
        register_batch(tmp_path / "batch", tmp_path / "reg", progress=False)
    assert err.value.path == yml
    yml.write_text(text + "dense_reference: dense_ref\n")
    rows = register_batch(tmp_path / "batch", tmp_path / "reg", progress=False)
    level = 1.0 / float(load_config(overrides=over)["microscope"]["background"])
    meta = read_yaml(tmp_path / "reg" / "registration.yaml")
    assert meta["dense_reference"]["prints"] == ["dense_ref"] and meta["measurement"]["dense_level_from"] == "reference"
    assert meta["dense_level"] == pytest.approx(level, rel=0.05)
    assert "dense_ref" not in {r["id"] for r in rows} and len(rows) == 9
    bias = _edge_bias(tmp_path / "reg", tmp_path / "batch.truth")
    assert len(bias) >= 8 and abs(np.median(bias)) < 0.4


def test_a_measured_reference_level_is_in_the_images_units_whatever_the_flat_field():
    """A declared dense_level is in units of the background, which a batch corrected by
    subtraction with noisy backgrounds cannot use (an error); a level measured on the
    batch's own dense reference is in the images' units either way."""
    from pathlib import Path

    from unscatter.imaging.batch import Settings, declared_level
    from unscatter.imaging.flatfield import Corrected

    noisy = {"a": Corrected("a", np.zeros((4, 4), np.float32), 1.5, 10.0, "uint8", 0.1)}
    with pytest.raises(InputError, match="remove dense_level"):
        declared_level(3.0, 2.0, noisy, "subtract", Settings(), Path("batch.yaml"))
    assert declared_level(3.0, 2.0, noisy, "subtract", Settings(), Path("batch.yaml"), "dense_reference") == (3.0, 1.5)


# ------------------------------------------------------------- pose spread, batch range


def _two_block_print(shift_right: int):
    """A mask of two blocks and its image (the print template itself, with noise) in which
    the right block printed ``shift_right`` px from where the mask puts it."""
    import cv2

    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.template import PrintTemplate

    mask = np.zeros((512, 512), np.uint8)
    mask[180:330, 80:200] = 255
    mask[180:330, 310:430] = 255
    printed = mask.copy()
    printed[:, 250:] = 0
    printed[180:330, 310 + shift_right:430 + shift_right] = 255
    tmpl = PrintTemplate(512, MARGIN)
    x = np.array(PrintTemplate.START)
    img = 0.1 + 0.8 * tmpl(tmpl.padded(printed), x)
    img = img + np.random.default_rng(0).normal(0, 0.02, img.shape).astype(np.float32)
    return mask, cv2.GaussianBlur(img, (0, 0), 1.0), tmpl, x


def test_a_print_that_fits_its_template_is_determined():
    """Two blocks printed where the mask puts them: the pose is known to well under 0.5 px."""
    from unscatter.imaging.pose import refine

    mask, img, tmpl, x = _two_block_print(0)
    fit = refine(img, np.hstack([np.eye(2), np.zeros((2, 1))]), tmpl, tmpl.exposure(tmpl.padded(mask), x), x, iters=30)
    assert fit.pose_sd < 0.1 and np.abs(fit.M[:, 2]).max() < 0.1, (fit.pose_sd, fit.M)


def test_the_template_fits_ncc_against_a_centred_image_is_ncc():
    """``template._Centred`` (each image centred once for the template fit) gives
    ``ncc``'s numbers to the last bit, with missing pixels in the image, in the template,
    and in nearly all of the image."""
    from unscatter.imaging.template import _Centred, ncc

    rng = np.random.default_rng(7)
    for share in (0.0, 0.3, 0.9995):
        img = rng.normal(1.0, 0.5, (96, 96)).astype(np.float32)
        img[rng.random(img.shape) < share] = np.nan
        seen = _Centred(img)
        for _ in range(5):
            b = rng.random((96, 96)).astype(np.float32)
            assert seen.ncc(b) == ncc(img, b)
        b[10:20, 10:20] = np.nan
        assert seen.ncc(b) == ncc(img, b)


def test_a_start_that_stays_where_no_pose_counts_stops():
    """``refine``'s ``outside``: a start 40 px off, at poses that the caller does not count,
    stops after OUTSIDE_STEPS steps, not converged; a start where poses count ends where it
    ends without the test, to the last digit."""
    from unscatter.imaging.pose import OUTSIDE_STEPS, refine

    mask, img, tmpl, x = _two_block_print(0)
    B = tmpl.exposure(tmpl.padded(mask), x)
    far = np.hstack([np.eye(2), [[40.0], [0.0]]])

    def beyond_20_px(M, gain):
        return abs(M[0, 2]) > 20 or gain <= 0

    walked = refine(img, far, tmpl, B, x, iters=30, spread=False)
    stopped = refine(img, far, tmpl, B, x, iters=30, spread=False, outside=beyond_20_px)
    assert walked.iterations > OUTSIDE_STEPS + 2, walked.iterations
    assert stopped.iterations == OUTSIDE_STEPS and not stopped.converged, (stopped.iterations, stopped.converged)
    near = np.hstack([np.eye(2), [[3.0], [-2.0]]])
    a = refine(img, near, tmpl, B, x, iters=30)
    b = refine(img, near, tmpl, B, x, iters=30, outside=beyond_20_px)
    assert a.converged and np.array_equal(a.M, b.M) and a.iterations == b.iterations, (a.M, b.M)


def test_a_displaced_block_is_read_as_a_scale_and_an_erosion():
    """The right block printed 6 px right of its mask place. Undamped Gauss-Newton ended
    with the dose at 4.5, the blur at 8 px and the edge offset at its bound of -6 px, a
    poor fit whose spread (1 px) failed the print. The damped refinement finds the fit
    that explains the print: a scale 2.6 % larger with every edge 1.8 px in, the residual
    at the noise and a small spread. From this one print a displaced feature cannot be told
    from a scale and an erosion; the pose is 4 px off. What holds such a print is its batch:
    a stated pixel size or a single magnification holds its scale (step 5c)."""
    from unscatter.imaging.pose import _BOUNDS, NUISANCE, refine

    mask, img, tmpl, x = _two_block_print(6)
    fit = refine(img, np.hstack([np.eye(2), np.zeros((2, 1))]), tmpl, tmpl.exposure(tmpl.padded(mask), x), x, iters=30)
    for (name, _, _), v in zip(NUISANCE, fit.q):
        lo, hi = _BOUNDS[name]
        assert lo + 0.05 * (hi - lo) < v < hi - 0.05 * (hi - lo), (name, v)
    assert fit.sigma < 0.012, fit.sigma
    assert abs(np.sqrt(np.linalg.det(fit.M[:, :2])) - 236 / 230) < 0.004 and fit.edge < -1.2, (fit.M, fit.q)


def test_a_grey_ramps_pose_rests_on_the_shape_of_the_kernel():
    """A block under a grey ramp and the same block at one grey level, printed with a
    scatter kernel whose tail (a third of the dose, wide) the template lacks, and refitted
    with the template at the true scale: the ramp's pose slides along the ramp by over
    1.5 px (its cut is where the dose places it, its bright end is where the kernel's
    shape does), the block's by under 0.1 px (its opposite edges move alike). The move
    that ``kernel_moves`` predicts at the fit says so: over 1 px for the ramp, under 0.1
    px for the block; and the residual of either print at its fit holds most of the
    tail's change (the share by which the batch's prints measure their kernel off,
    ``kernel_error``), whether or not its pose moved. Partial prints of our randomized
    labs were `ok` 1.6 to 4.7 px off along their ramps."""
    import cv2

    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.pose import _kernel_changed, kernel_moves, pose_distance, refine
    from unscatter.imaging.template import PrintTemplate

    n = 256
    tmpl = PrintTemplate(n, MARGIN)
    x = np.array(PrintTemplate.START, float)
    x[0], x[1], x[8], x[10] = 6.0, 0.3, 0.0, 2.0  # core width, gel point, no tail, microscope blur
    block = np.zeros((n, n), np.uint8)
    block[60:190, 70:200] = 230
    ramp = block.astype(float)
    ramp[60:190] *= np.linspace(0.25, 1.0, 130)[:, None]  # a quarter of the dose at the top to full at the bottom
    ramp = ramp.astype(np.uint8)
    M0 = np.hstack([np.eye(2), np.zeros((2, 1))])
    moved, spread, share = {}, {}, {}
    for name, mask in (("block", block), ("ramp", ramp)):
        m = tmpl.padded(mask)
        img = 0.1 + 0.8 * tmpl(m, _kernel_changed(x, "tail"))
        img = cv2.GaussianBlur(img + np.random.default_rng(0).normal(0, 0.02, img.shape).astype(np.float32), (0, 0), 1.0)
        B = tmpl.exposure(m, x)
        fit = refine(img, M0, tmpl, B, x, iters=30, scale_prior=(0.0, 0.001))
        assert fit.scale_held  # refined with the scale held: kernel_moves holds it too
        moved[name] = pose_distance(fit.M, M0, n + 2 * MARGIN, MARGIN)
        spread[name], shares = kernel_moves(tmpl, m, B, x, fit, "similarity", image=img)
        share[name] = shares["tail"]
    assert moved["ramp"] > 1.5 and moved["block"] < 0.1, moved
    assert spread["ramp"] > max(1.0, 0.4 * moved["ramp"]) and spread["block"] < 0.1, (spread, moved)
    assert all(0.5 < v < 1.5 for v in share.values()), share


def test_batch_range_bounds_the_poses_of_a_batch():
    from unscatter.imaging.batch import Settings, batch_range

    s = Settings()
    rng = np.random.default_rng(2)
    poses = [dict(rotation_deg=float(r), scale=float(c)) for r, c in zip(rng.uniform(-5, 5, 24), rng.uniform(0.9, 1.1, 24))]
    (rlo, rhi), (slo, shi) = batch_range(poses, s)
    rot, sc = [p["rotation_deg"] for p in poses], [p["scale"] for p in poses]
    # wider than the prints' own range by 6 mean gaps (2.4 deg, 4 % here); a star one 15 deg spoke off lies outside
    assert -7.5 < rlo < min(rot) - 1.5 and max(rot) + 1.5 < rhi < 7.5
    assert min(sc) / 1.06 < slo < min(sc) / 1.02 and max(sc) * 1.02 < shi < max(sc) * 1.06
    assert batch_range(poses[: s.batch_range_min - 1], s) is None


def test_batch_rotation_flags_a_print_turned_far_from_the_batch():
    from unscatter.imaging.batch import Settings, batch_rotation

    s = Settings()
    rng = np.random.default_rng(4)
    hand = list(rng.uniform(-3.4, 3.4, 20))  # samples placed by hand, one star a spoke (21 deg) off
    centre, limit = batch_rotation(hand + [-20.9], s)
    assert all(abs(r - centre) <= limit for r in hand) and abs(-20.9 - centre) > limit
    assert 6 < limit < 14  # about three times the half-range
    centre, limit = batch_rotation([2.0 + d for d in rng.normal(0, 0.05, 12)], s)  # one fixed rotation
    assert limit == pytest.approx(s.rotation_mads * s.min_rotation_spread) and abs(centre - 2.0) < 0.1
    assert batch_rotation(hand[: s.batch_range_min - 1], s) is None
    wide = list(rng.uniform(-15, 15, 20))  # a lab turning its samples anywhere within 15 deg: none is off
    centre, limit = batch_rotation(wide, s)
    assert all(abs(r - centre) <= limit for r in wide)
    # placed by hand within +-11 deg, the determined prints by chance mostly at 3..8 deg (seed 1985358721's
    # lab 5): the median and spread of those put the others off; three or more off is no one rotation
    lopsided = [3.3, 4.3, 4.4, 4.8, 5.3, 5.8, 6.2, 6.4, 6.6, 7.4, -9.2, -7.3, -5.0]
    assert batch_rotation(lopsided, s) is None
    assert batch_rotation(lopsided[:-1] + [5.0], s) is not None  # two off: outliers of one rotation


def test_a_print_that_is_one_feature_has_its_scale_from_its_size_only():
    """One block: without a bound on its size its scale is free (a large spread, however
    small the image noise); with the size known to 0.2 px, about 0.2 px over its radius
    times the field's. Blocks in a row fix the scale by where they lie, whatever their
    sizes."""
    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.pose import size_spread
    from unscatter.imaging.template import PrintTemplate

    tmpl = PrintTemplate(512, MARGIN)
    x = np.array(PrintTemplate.START)
    block = np.zeros((512, 512), np.uint8)
    block[200:320, 180:340] = 255
    row = np.zeros((512, 512), np.uint8)
    for c0 in range(60, 460, 80):
        row[200:260, c0:c0 + 40] = 255
    T_block, T_row = (tmpl(tmpl.padded(m), x) for m in (block, row))
    assert size_spread(T_block, "similarity") > 10.0
    assert 0.5 < size_spread(T_block, "similarity", 0.2) < 2.0
    assert size_spread(T_row, "similarity") < 0.4


def test_a_grating_printed_as_one_block_counts_as_merged_and_a_checkerboard_or_a_swollen_dot_does_not():
    """``merged_features`` on prints cut from known shapes: a grating whose lines are three
    times as wide as its gaps, printed as one block (1.33 times its exposed area: at the
    old 1.5 it passed, and a print of it on seed 724740725's lab 6 was ok 2.5 px off in
    scale), and the same in an image cut at a given level; not the grating resolved, a
    checkerboard whose squares meet at their corners, or one dot swollen to twice its area
    (one part of the mask: nothing joined)."""
    from unscatter.imaging.pose import merged_features

    m = np.zeros((120, 120))
    for c in range(10, 106, 8):
        m[10:110, c:c + 6] = 1
    block = np.zeros_like(m)
    block[10:110, 10:108] = 1
    assert merged_features(block, m)
    assert merged_features(0.8 * block + 0.1, m, level=0.5)
    assert not merged_features(0.8 * block + 0.1, m, level=0.95)
    assert not merged_features(m, m)
    cb = np.zeros_like(m)
    for i in range(4):
        for j in range(4):
            if (i + j) % 2 == 0:
                cb[10 + 20 * i:30 + 20 * i, 10 + 20 * j:30 + 20 * j] = 1
    assert not merged_features(cb, cb)
    yy, xx = np.mgrid[:120, :120]
    dot = ((yy - 60) ** 2 + (xx - 60) ** 2 < 100).astype(float)
    assert not merged_features(((yy - 60) ** 2 + (xx - 60) ** 2 < 200).astype(float), dot)


def test_a_feature_that_barely_or_does_not_print_fixes_no_scale():
    """A block and a thin line beside it: where the template predicts the line's peak
    well above the level, the two features' places fix the scale; where the line barely
    crosses it (specks along a ridge, as a thin line at the edge of curing does) or where
    the image does not show the line, the block's size alone sets it, as for one block."""
    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.pose import size_spread

    def blurred(m):
        return np.pad(cv2_blur(m.astype(np.float32), 2.0), MARGIN)

    block = np.zeros((512, 512), np.float32)
    block[300:420, 100:420] = 1.0
    line = np.zeros((512, 512), np.float32)
    line[120:126, 60:460] = 1.0
    T_block = blurred(block)
    alone = size_spread(T_block, "similarity", 0.2)
    peak = float(T_block.max())
    clear = T_block + blurred(line) * (0.9 * peak / float(blurred(line).max()))
    assert size_spread(clear, "similarity", 0.2) < 0.5 * alone  # two features far apart: their places fix the scale
    rng = np.random.default_rng(0)
    ridge = blurred(line) / float(blurred(line).max()) * (0.5 * peak) * (1.0 + 0.04 * rng.standard_normal(T_block.shape))
    marginal = T_block + np.where(blurred(line) > 0.5 * float(blurred(line).max()), ridge, 0.0)
    assert size_spread(marginal, "similarity", 0.2) == pytest.approx(alone, rel=0.05)
    shown = np.where(np.isfinite(T_block), T_block, np.nan)  # the image shows the block, not the line
    assert size_spread(clear, "similarity", 0.2, image=shown) == pytest.approx(alone, rel=0.05)
    assert size_spread(clear, "similarity", 0.2, image=clear) < 0.5 * alone


def test_a_feature_that_printed_smaller_than_predicted_still_fixes_the_scale():
    """A block and a dot far from it, in a lab that erodes: the image shows the dot with
    less than half of its predicted area above the level (a dot of seed 454132426's lab
    7, which left a ring and a dot's print undetermined), but its middle: the two
    features' places fix the scale. A line of which the image shows one end only (it
    printed in part) does not count."""
    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.pose import seen_shares, size_spread

    def blurred(m):
        return np.pad(cv2_blur(m.astype(np.float32), 2.0), MARGIN)

    yy, xx = np.mgrid[:512, :512]
    block = np.zeros((512, 512), np.float32)
    block[300:420, 100:420] = 1.0
    dot = ((yy - 100) ** 2 + (xx - 420) ** 2 <= 9**2).astype(np.float32)
    T_block, T = blurred(block), blurred(block) + blurred(dot)
    alone = size_spread(T_block, "similarity", 0.2)
    small = blurred(block) + blurred(((yy - 100) ** 2 + (xx - 420) ** 2 <= 5.5**2).astype(np.float32))
    lvl = 0.5 * float(T.max())
    lab, count = ndimage.label(T >= lvl)
    shares = seen_shares(lab, count, small >= lvl)
    whole = ndimage.mean(small >= lvl, lab, np.arange(1, count + 1))
    assert min(whole) < 0.5 and min(shares) > 0.9  # less than half its area seen, all of its middle
    both = size_spread(T, "similarity", 0.2, image=T)
    assert both < 0.7 * alone
    assert size_spread(T, "similarity", 0.2, image=small) == pytest.approx(both, rel=1e-6)
    line = np.zeros((512, 512), np.float32)
    line[120:126, 60:460] = 1.0
    T_line = T_block + blurred(line)
    part = line.copy()
    part[:, 200:] = 0.0  # a third of the line printed
    assert size_spread(T_line, "similarity", 0.2, image=T_block + blurred(part)) == pytest.approx(alone, rel=0.05)
    assert size_spread(T_line, "similarity", 0.2, image=T_line) < 0.7 * alone


def test_a_line_that_barely_cured_is_placed_only_as_well_as_the_dose_is_known():
    """A lone line in a batch of prints that cured well above the gel point: where the line
    did too, a change of dose moves its edges as far as the batch's, and its spread is as
    without the dose; where it barely cured, its ends move much further with the dose,
    and so does where along its length it lies."""
    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.pose import dose_sensitivity, size_spread
    from unscatter.imaging.template import PrintTemplate

    tmpl = PrintTemplate(512, MARGIN)
    x = np.array(PrintTemplate.START)
    line = np.zeros((512, 512), np.uint8)
    line[250:258, 60:460] = 255
    B = tmpl.exposure(tmpl.padded(line), x)

    def at(over):  # peak dose over the gel point
        dose = over * x[1] / float(B.max())
        T = tmpl.cure(B, x, dose)
        return T, (tmpl.cure(B, x, dose * 1.02) - T) / np.log(1.02)

    batch = dose_sensitivity(*at(4.0))
    spreads = {}
    for over in (1.05, 1.2, 4.0):
        T, R = at(over)
        spreads[over] = size_spread(T, "similarity", 0.2), size_spread(T, "similarity", 0.2, dose_response=R,
                                                                       dose_reference=batch)
    assert spreads[4.0][1] == pytest.approx(spreads[4.0][0], rel=0.1)
    assert spreads[1.2][1] > 1.5 * spreads[1.2][0] and spreads[1.05][1] > 4 * spreads[1.05][0]


def test_two_features_whose_edges_the_dose_moves_far_fix_the_scale_only_as_well_as_their_places():
    """Two dots far apart set a print's scale by where they lie. Where they barely cured,
    a few % more dose on one side of a dot moves it as a whole (``place_dose_sd``), and the
    scale is known only that well, however long their edges, even in a batch whose prints
    all barely cured (so that no edge of this one moves further than the batch's and the
    per-pixel weights leave it as it is); large blocks that cured well above the gel point
    are placed almost as before."""
    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.pose import dose_sensitivity, size_spread
    from unscatter.imaging.template import PrintTemplate

    tmpl = PrintTemplate(512, MARGIN)
    x = np.array(PrintTemplate.START)
    yy, xx = np.mgrid[:512, :512]
    dots = (((yy - 256) ** 2 + (xx - 100) ** 2 < 12**2) | ((yy - 256) ** 2 + (xx - 420) ** 2 < 12**2)).astype(np.uint8) * 255
    blocks = np.zeros((512, 512), np.uint8)
    blocks[100:200, 100:200] = blocks[300:420, 280:400] = 255

    def spreads(mask, over):  # over: the peak dose over the gel point, this print's and the batch's
        B = tmpl.exposure(tmpl.padded(mask), x)
        dose = over * x[1] / float(B.max())
        T = tmpl.cure(B, x, dose)
        R = (tmpl.cure(B, x, dose * 1.02) - T) / np.log(1.02)
        ref = dose_sensitivity(T, R)
        return [size_spread(T, "similarity", 0.2, dose_response=R, dose_reference=ref, place_dose_sd=c) for c in (0.0, 0.02)]

    alone, placed = spreads(dots, 1.1)
    assert placed > 1.5 * alone and placed > 1.5  # fails QC's 1.5 px; the pixels alone pass it
    alone, placed = spreads(blocks, 4.0)
    assert placed < 1.3 * alone


def test_the_batch_measures_how_far_its_features_sit_off_their_places():
    """Features moved off their predicted places by a few px, in proportion to how far the
    dose moves their edges, are measured as such; features where they belong, under noise,
    as (nearly) not moved: the measurement takes out what the noise and the pose explain."""
    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.pose import feature_places, place_dose_spread
    from unscatter.imaging.template import PrintTemplate

    tmpl = PrintTemplate(512, MARGIN)
    x = np.array(PrintTemplate.START)
    rng = np.random.default_rng(5)
    mask = np.zeros((512, 512), np.uint8)
    centres = [(cy, cx) for cy in (100, 256, 412) for cx in (100, 256, 412)]
    for cy, cx in centres:
        mask[cy - 30:cy + 30, cx - 30:cx + 30] = 255
    B = tmpl.exposure(tmpl.padded(mask), x)
    dose = 1.5 * x[1] / float(B.max())
    T = tmpl.cure(B, x, dose)
    R = (tmpl.cure(B, x, dose * 1.02) - T) / np.log(1.02)
    noise = 0.01

    def image(shifts):
        img = T.copy()
        for (cy, cx), (dy, dx) in zip(centres, shifts):
            sl = np.s_[MARGIN + cy - 60:MARGIN + cy + 60, MARGIN + cx - 60:MARGIN + cx + 60]
            img[sl] = ndimage.shift(T, (dy, dx), order=1)[sl]
        return img + rng.normal(0, noise, T.shape)

    # the noise of a boundary pixel's place: noise over the edge's slope, one per EDGE_CORR_PX
    edge_sd = 0.05
    still = [feature_places(image([(0, 0)] * 9), T, R) for _ in range(4)]
    c_still, n = place_dose_spread(still, edge_sd)
    moved = still[0][:, 1]
    c = 0.05
    off = [feature_places(image([tuple(rng.normal(0, c * m, 2)) for m in moved]), T, R) for _ in range(4)]
    c_off, _ = place_dose_spread(off, edge_sd)
    assert n == 36 and c_still < 0.01
    assert 0.5 * c < c_off < 2 * c


def test_a_star_is_one_feature_and_its_scale_rests_on_its_size():
    """A Siemens star is one feature: where its spoke tips lie against its spoke sides is
    what the template predicts worst, so without a bound on its size its scale is free;
    a faint ripple inside a block (a fine grating printed as one) fixes nothing either."""
    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.pose import size_spread
    from unscatter.imaging.template import PrintTemplate

    tmpl = PrintTemplate(512, MARGIN)
    x = np.array(PrintTemplate.START)
    star = patterns.siemens_star(np.random.default_rng(2), spokes=16)
    T_star = tmpl(tmpl.padded(star), x)
    assert size_spread(T_star, "similarity") > 5.0
    assert size_spread(T_star, "similarity", 0.2) < 1.5
    block = np.zeros((512, 512), np.float32)
    block[150:400, 100:420] = 1.0
    T_ripple = block * (1.0 + 0.03 * np.sin(2 * np.pi * np.arange(512)[:, None] / 4.0)) * np.linspace(1.0, 0.6, 512)[None, :]
    T_ripple = np.pad(cv2_blur(T_ripple.astype(np.float32), 2.0), MARGIN)
    assert size_spread(T_ripple, "similarity") > 5.0


def test_thin_lines_image_below_the_level_they_cured_at():
    from unscatter.imaging.batch import imaged_peak

    block = np.zeros((512, 512), np.uint8)
    block[100:300, 100:300] = 90
    lines = np.zeros((512, 512), np.uint8)
    lines[100:300:8, 100:300] = 255
    assert imaged_peak(block, 2.0) == pytest.approx(1.0, abs=1e-3)
    assert imaged_peak(lines, 2.0) < 0.5
    assert imaged_peak(np.zeros((64, 64), np.uint8), 2.0) == 1.0


def test_the_templates_cure_of_a_mask_is_measured_against_a_large_blocks():
    """``template_cure_share``: a large block at full grey cures as densely as the
    reference block; lines 4 px wide, whose scattered dose under a kernel of 4 px stays
    near the gel point, to a small share of it; more dose cures more; below the gel
    dose, nothing."""
    from unscatter.imaging.batch import MARGIN, template_cure_share
    from unscatter.imaging.template import PrintTemplate

    tmpl = PrintTemplate(256, MARGIN)
    x = np.array(PrintTemplate.START)  # sigma 4 px, gel 0.3, k 0.2
    block = np.zeros((256, 256), np.uint8)
    block[40:220, 40:220] = 255
    lines = np.zeros((256, 256), np.uint8)
    for y in range(60, 200, 12):
        lines[y:y + 4, 60:200] = 255  # 4 px lines, 8 px gaps
    assert template_cure_share(tmpl, block, x, 1.0) == pytest.approx(1.0, abs=1e-3)
    thin = [template_cure_share(tmpl, lines, x, d) for d in (0.8, 1.0, 1.5)]
    assert 0 < thin[0] < thin[1] < thin[2] and thin[1] < 0.45 < thin[2]
    assert template_cure_share(tmpl, lines, x, 0.5) == 0.0


def test_an_eroding_batchs_thin_lines_image_dimmer_still():
    """Lines 6 px wide lose their peak as erosion thins them and vanish at 3 px; a block
    keeps its peak; no erosion is the bare mask."""
    from unscatter.imaging.batch import imaged_peak

    lines = np.zeros((256, 256), np.uint8)
    for y in range(40, 200, 16):
        lines[y:y + 6, 40:200] = 255
    block = np.zeros((256, 256), np.uint8)
    block[60:200, 60:200] = 255
    peaks = [imaged_peak(lines, 2.0, e) for e in (0.0, 1.0, 2.0, 2.9, 3.0)]
    assert peaks[0] == imaged_peak(lines, 2.0) and peaks[0] > 0.8
    assert peaks[0] > peaks[1] > peaks[2] > peaks[3] > 0 == peaks[4]
    assert 0.3 < peaks[2] / peaks[0] < 0.45  # a line 2 px wide of the 6 images at about a third of it
    assert imaged_peak(block, 2.0, 3.0) == pytest.approx(1.0, abs=1e-3)


def cv2_blur(a, sigma):
    import cv2

    return cv2.GaussianBlur(a, (0, 0), sigma)


def test_feature_sizes_are_known_as_well_as_the_batch_shows():
    from types import SimpleNamespace

    from unscatter.imaging.batch import Settings, size_error

    s = Settings()
    fits = [SimpleNamespace(edge=e, edge_c2=0.0, edge_s2=0.0) for e in (-1.8, -1.6, -2.0, -1.7, -1.9, 2.5)]
    (e0, c2, s2), sd = size_error(fits, s)
    # an eroded batch (and one partial print): a single block is held to its erosion
    assert e0 == pytest.approx(-1.75) and c2 == s2 == 0.0
    assert 0.1 < sd[0] < 0.3 and sd[1] == sd[2] == s.min_size_sd
    assert size_error([SimpleNamespace(edge=0.0, edge_c2=0.0, edge_s2=0.0)] * 5, s)[1] == (s.min_size_sd,) * 3
    assert size_error(fits[: s.size_min_prints - 1], s) == ((0.0, 0.0, 0.0), (s.size_sd,) * 3)


def test_edge_misfit_measures_how_far_the_images_edges_lie_from_the_templates():
    """A disc imaged 1 px (0.5 px) larger than its template reads about 1 px (0.5 px) off,
    the template itself 0; the noise counts as misfit too (it only overstates)."""
    from types import SimpleNamespace

    import cv2

    from unscatter.imaging.pose import edge_misfit

    yy, xx = np.mgrid[:200, :200]
    r = np.hypot(xx - 100.3, yy - 99.6)

    def disc(radius):
        return cv2.GaussianBlur((r <= radius).astype(np.float32), (0, 0), 2.0)

    T = disc(40.0)
    fit = SimpleNamespace(gain=3.0, offset=0.5)
    noise = np.random.default_rng(4).normal(0, 0.05, T.shape).astype(np.float32)
    assert edge_misfit(3.0 * disc(41.0) + 0.5 + noise, T, fit) == pytest.approx(1.0, abs=0.15)
    assert edge_misfit(3.0 * disc(40.5) + 0.5, T, fit) == pytest.approx(0.5, abs=0.1)
    assert edge_misfit(3.0 * T + 0.5, T, fit) < 0.01
    assert 0.05 < edge_misfit(3.0 * T + 0.5 + noise, T, fit) < 0.25
    nan = np.full(T.shape, np.nan, np.float32)
    assert edge_misfit(nan, T, fit) == float("inf")


def test_edge_places_are_known_as_well_as_the_batch_shows_but_never_worse_than_assumed():
    from unscatter.imaging.batch import Settings, edge_place_sd
    from unscatter.imaging.pose import EDGE_SD

    s = Settings()
    assert edge_place_sd([0.2, 0.25, 0.22, 0.9, float("inf")], s)[0] == pytest.approx(0.235)
    assert edge_place_sd([1.2, 1.5, 0.9, 1.1], s)[0] == EDGE_SD  # a stain reads as misfit too: not taken as worse edges
    assert edge_place_sd([0.01] * 6, s)[0] == s.min_edge_sd
    assert edge_place_sd([0.2] * (s.size_min_prints - 1), s)[0] == EDGE_SD


def test_a_dot_row_is_placed_as_well_as_its_edges_are():
    """Three dots in a row fix the pose by where they lie; how well, the edges' places say:
    the spread shrinks with ``edge_sd``."""
    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.pose import EDGE_SD, size_spread
    from unscatter.imaging.template import PrintTemplate

    tmpl = PrintTemplate(512, MARGIN)
    x = np.array(PrintTemplate.START)
    dots = np.zeros((512, 512), np.uint8)
    yy, xx = np.mgrid[:512, :512]
    for cx in (210, 256, 302):
        dots[np.hypot(xx - cx, yy - 400) <= 9] = 255
    T = tmpl(tmpl.padded(dots), x)
    wide, close = (size_spread(T, "similarity", 0.2, edge_sd=e) for e in (EDGE_SD, 0.2))
    assert wide > 1.5 > close


def test_one_magnification_holds_the_scale_of_prints_that_cannot_fix_theirs(tmp_path):
    """A batch imaged at one scale: a block and an L, whose scale would rest on their size
    alone, take the scale that the trial prints agree on and register where they are;
    registration.yaml says so, and a batch whose scale varies per image is not taken for
    one of one magnification."""
    from unscatter.io import read_yaml

    m = tmp_path / "masks"
    for k, mask in patterns.trial_masks(8, seed=5).items():
        write_png(m / f"{k}.png", mask)
    yy, xx = np.mgrid[:512, :512]
    one = {"block": (np.abs(xx - 250) < 150) & (np.abs(yy - 270) < 100),
           "ell": ((xx > 120) & (xx < 400) & (yy > 330) & (yy < 400)) | ((xx > 120) & (xx < 190) & (yy > 100) & (yy < 400))}
    for k, v in one.items():
        write_png(m / f"{k}.png", np.where(v, 255, 0).astype(np.uint8))
    statuses = {}
    for name, scale in (("fixed", [0.93, 0.93]), ("zoom", [0.8, 1.25])):
        batch = tmp_path / f"batch_{name}"
        print_batch(m, batch, overrides={"microscope": {"scale": scale, "rotation_deg": 10.0}}, seed=11, progress=False)
        register_batch(batch, tmp_path / f"reg_{name}", skip_failed=True, progress=False)
        errs = _pose_errors(tmp_path / f"reg_{name}", tmp_path / f"batch_{name}.truth")
        statuses[name] = {k: errs[k] for k in one}
        assert not any(st == "ok" and e > 1.5 for st, _, e in errs.values()), errs
        reg = read_yaml(tmp_path / f"reg_{name}" / "registration.yaml")
        if name == "fixed":
            assert reg["one_magnification"] is not None and abs(reg["one_magnification"]["scale"] - 0.93) < 0.002, reg
        else:
            assert reg["one_magnification"] is None, reg
    # held to the batch's scale, the block is where it is; with its scale from its size it
    # was 0.87 px off (at 0.93, as it happens)
    assert all(st == "ok" and e <= 0.3 for st, _, e in statuses["fixed"].values()), statuses


def test_batch_scale_is_one_magnification_only_when_the_prints_agree():
    from types import SimpleNamespace

    from unscatter.imaging.batch import Settings, batch_scale

    s = Settings()
    rng = np.random.default_rng(3)

    def fits(scales):
        return [SimpleNamespace(M=np.array([[c * np.cos(t), -c * np.sin(t), 5.0], [c * np.sin(t), c * np.cos(t), 7.0]]))
                for c, t in zip(scales, rng.uniform(-0.2, 0.2, len(scales)))]

    one = batch_scale(fits(1.1 * np.exp(rng.normal(0, 0.0005, 10))), s)
    assert one is not None and abs(np.exp(one[0]) - 1.1) < 0.001 and one[1] == s.min_scale_sd
    assert batch_scale(fits(1.1 * np.exp(rng.uniform(-0.03, 0.03, 10))), s) is None  # a zoom set per image
    # ... whose prints agree by chance (the log scales, in %, of seven prints of our own lab at a zoom of 1.22 to
    # 1.25 per image: a robust spread of 0.23 %, within fixed_scale_sd); one objective refocused, 0.48 % at most
    clustered = 1.238 * np.exp(np.array([0.379, 0.153, 0.064, 0.0, -0.054, -0.776, -1.202]) / 100)
    assert 1.4826 * np.median(np.abs(np.log(clustered / np.median(clustered)))) < s.fixed_scale_sd
    assert batch_scale(fits(clustered), s) is None
    refocused = 0.81 * np.exp(np.array([-0.005, 0.232, 0.005, 0.094, -0.016, -0.475]) / 100)
    assert batch_scale(fits(refocused), s) is not None
    tight = np.zeros(8)
    for off, one in ((0.7, True), (0.9, False)):  # one print that far off (%) the median of the others
        tight[-1] = off
        assert (batch_scale(fits(1.1 * np.exp(tight / 100)), s) is not None) == one
    assert batch_scale(fits([1.1] * (s.scale_min_prints - 1)), s) is None


def test_a_star_under_anisotropic_scatter_is_never_chosen_one_spoke_off():
    """36 spokes (10 deg) within a rotation range of +-12 deg, scatter 1.6 times wider one
    way: which turn of the star printed, only the scatter's direction tells, and the
    template does not hold it: the star fails as ambiguous, naming the symmetry."""
    pytest.importorskip("cv2")
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        rng = np.random.default_rng(8)
        for i in range(2):
            write_png(d / "masks" / f"star_{i}.png", patterns.siemens_star(rng, spokes=36))
        for k, mask in patterns.trial_masks(8, seed=6).items():
            write_png(d / "masks" / f"{k}.png", mask)
        over = {"microscope": {"rotation_deg": 12.0}, "printer": {"kernel": {"anisotropy": {"ratio": 1.6, "angle_deg": 30.0}}}}
        print_batch(d / "masks", d / "batch", overrides=over, seed=5, progress=False)
        rows = {r["id"]: r for r in register_batch(d / "batch", d / "reg", skip_failed=True, progress=False)}
        for k in ("star_0", "star_1"):
            assert rows[k]["status"] == "failed" and "maps onto itself rotated by" in rows[k]["reason"], rows[k]


def test_a_fine_stars_symmetry_is_found_at_half_resolution():
    """The symmetry check of a chosen pose (``choose_pose``) turns the mask, blurred by
    2 px, at 1 deg steps. At quarter resolution a fine star's spokes merge, and the
    correlation dips too little between no turn and a spoke's (seed 1269754155's lab 7:
    a 36-spoke star, its period 10 deg, found no symmetry and was `ok` 20 deg and 77 px
    off); at half resolution the turns of one and two periods are found."""
    import cv2

    from unscatter.imaging.batch import MARGIN, SYMMETRY_FACTOR, Settings
    from unscatter.imaging.pose import self_similar_moves

    s = Settings()
    star = np.pad(patterns.siemens_star(np.random.default_rng(11), spokes=36).astype(np.float32) / 255, MARGIN)
    m = cv2.GaussianBlur(star, (0, 0), 2.0)

    moves = self_similar_moves(m, rotation_span=40.0, min_corr=s.symmetric_corr, shifts=False, dip=s.symmetric_dip,
                               factor=SYMMETRY_FACTOR)
    found = sorted(round(float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))) for R in moves)
    assert {-10, 10} <= set(found) and all(abs(t) % 10 in (0, 1, 9) for t in found), found


def test_a_stars_turn_by_a_spoke_is_its_rival_whatever_its_scale(tmp_path):
    """A pose turned by a spoke about a star's hub is the chosen pose's rival when its
    rotation lies within the searched range: the turn keeps the scale, so the scale range
    cannot tell the two apart. Seed 105045948's lab 1: a 21-spoke star, chosen again
    within the scales of the batch's other prints, fitted a scale 1 % beyond them (its
    scale rests on its size); the pose turned by a spoke was then out of range, no
    rival, and the star was `ok` a spoke (17 deg, 66 px) off. Here the pose search gets a
    scale range 1.5 % below the print's own."""
    import unscatter.imaging.batch as batch
    from unscatter.imaging.pose import pose_of
    from unscatter.imaging.template import PrintTemplate

    mask = patterns.siemens_star(np.random.default_rng(21), spokes=21)
    img, Mg = _printed_alone(tmp_path, "star", mask, {"microscope": {"rotation_deg": 2.0}}, 7)
    s = batch.Settings()
    x = np.array(PrintTemplate.START)
    n = 512 + 2 * batch.MARGIN
    own = pose_of(Mg, n, img.shape)["scale"]
    for lo, hi in ((own / 1.02, own * 1.02), (own / 1.05, own / 1.015)):  # about the print's scale; below it
        ch = batch.choose_pose(mask, img, [Mg], x, s, 512, (lo, hi))
        assert ch.symmetry is not None and abs(abs(ch.symmetry) - 360 / 21) < 1.0, (lo / own, hi / own, ch.symmetry)


ANISOTROPIC_LAB = {"microscope": {"blur_px": [3.0, 3.0], "rotation_deg": 10.0},
                   "printer": {"kernel": {"sigma_um": 24.0, "heavy_tail": {"fraction": 0.04, "length_um": 80.0},
                                          "anisotropy": {"ratio": 1.7, "angle_deg": 50.0}},
                               "cure": {"threshold": 0.7, "gel_dose": 0.5}}}


@pytest.fixture(scope="module")
def anisotropic_batch(tmp_path_factory):
    """Twelve paper trial masks printed with a wide core that scatters 1.7 times wider along
    50 deg than across it, near the threshold (0.7; gel 0.5: features shrink), imaged with
    a 3 px blur: a lab like the random one whose prints' first poses, against the blurred
    mask, were 3 to 45 px off; the template fitted at them here comes out far too wide
    (sigma 14 to 25 px where the lab's is 8)."""
    root = tmp_path_factory.mktemp("aniso")
    for k, mask in patterns.trial_masks(12, seed=11).items():
        write_png(root / "masks" / f"{k}.png", mask)
    print_batch(root / "masks", root / "batch", overrides=ANISOTROPIC_LAB, seed=4, progress=False)
    register_batch(root / "batch", root / "reg", skip_failed=True, progress=False)
    return root


def test_a_small_batch_fits_its_template_again_at_the_poses_it_trusts(tmp_path):
    """Five of the anisotropic lab's prints: the template fitted at their first poses is
    too wide, and only 4 poses are uncontested. The template is fitted again at those 4
    (``template_min_prints`` 3; it was 5, and this batch kept the first template: 1 print
    ok, 1.0 px off), and 2 prints are ok, each within 1 px of its true pose."""
    for k, mask in list(patterns.trial_masks(12, seed=11).items())[:5]:
        write_png(tmp_path / "masks" / f"{k}.png", mask)
    print_batch(tmp_path / "masks", tmp_path / "batch", overrides=ANISOTROPIC_LAB, seed=4, progress=False)
    register_batch(tmp_path / "batch", tmp_path / "reg", skip_failed=True, progress=False)
    assert "first" in read_yaml(tmp_path / "reg" / "registration.yaml")["template_prints"]
    errs = _pose_errors(tmp_path / "reg", tmp_path / "batch.truth")
    ok = [e for st, _, e in errs.values() if st == "ok"]
    assert len(ok) >= 2 and max(ok) <= 1.0, errs


def test_the_batch_template_holds_anisotropic_scatter_and_no_print_is_ok_off_its_pose(anisotropic_batch):
    """The template, fitted again at the chosen poses, turns its core's long axis along the
    scatter's (within 10 deg) with a ratio above 1.3 (the ratio itself trades against the
    cure's softness and the blur: 3.3 at its bound here, 1.57 for a ratio of 1.67 in a
    random lab); no print is ok more than 1 px off its true pose, and at least 7 of 12 are
    ok. Before the template held anisotropy and was fitted again: one print ok 2.0 px off."""
    from unscatter.io import read_yaml

    root = anisotropic_batch
    t = read_yaml(root / "reg" / "registration.yaml")["print_template"]
    L = np.hypot(t["aniso_c"], t["aniso_s"])
    turn = (np.degrees(np.arctan2(t["aniso_s"], t["aniso_c"]) / 2) - 50.0 + 90) % 180 - 90
    assert np.exp(L) > 1.3 and abs(turn) < 10, t
    errs = _pose_errors(root / "reg", root / "batch.truth")
    ok = {k: e for k, (st, _, e) in errs.items() if st == "ok"}
    assert len(ok) >= 7, errs
    assert max(ok.values()) <= 1.0, errs


def test_stated_scales_are_measured_by_the_prints_that_fix_their_scale():
    from unscatter.imaging.batch import Settings, stated_scales

    s = Settings()
    priors = {k: (np.log(1.1), 0.001) for k in "abcdefgh"} | {"z": None}
    few = {k: np.log(1.1) + d for k, d in zip("abc", (0.0005, -0.001, 0.0015))}
    used, note, shift = stated_scales(priors, few, s)  # too few to measure it, and they agree: used as stated
    assert used == {k: priors[k] for k in "abcdefgh"} and note == "" and shift == 0
    used, note, shift = stated_scales(priors, {}, s)  # nothing to check it against: used as stated
    assert set(used) == set("abcdefgh") and shift == 0
    used, note, shift = stated_scales(priors, {k: np.log(1.1) + 0.02 for k in "abc"}, s)  # 2 % off a size stated within 0.2 %
    assert used == {} and "+2.0" in note and "not used" in note
    assert shift == pytest.approx(0.02)  # the range check of every print allows the offset the prints measure
    # enough prints to measure it: a stale calibration 2 % off is corrected, and the
    # spread is the prints' own (at least min_scale_sd)
    many = {k: np.log(1.1) + 0.02 + d for k, d in zip("abcdefg", (0.0, 0.003, -0.003, 0.001, -0.001, 0.002, -0.002))}
    used, note, shift = stated_scales(priors, many, s)
    assert note == "" and shift == 0 and used["h"][0] == pytest.approx(np.log(1.1) + 0.02)
    assert used["h"][1] == pytest.approx(1.4826 * 0.002) and used["h"][1] >= s.min_scale_sd
    # fewer than scale_min_prints, but at least stated_min_prints, that agree more closely
    # than a loose tolerance (0.6 %, sd 0.3 %): shifted, known within their largest
    # deviation (of five, one may be pulled off: the second largest), at least min_scale_sd
    loose = {k: (np.log(1.19), 0.003) for k in "abcdefgh"}
    five = {k: np.log(1.19) + d for k, d in zip("abcde", (-0.00216, -0.0023, -0.00247, -0.0078, -0.00244))}
    used, note, shift = stated_scales(loose, five, s)
    assert note == "" and shift == 0 and used["h"][0] == pytest.approx(np.log(1.19) - 0.00244)
    assert used["h"][1] == pytest.approx(max(s.min_scale_sd, 0.00244 - 0.00216))
    three = {k: np.log(1.19) + d for k, d in zip("abc", (-0.0022, -0.0023, -0.0078))}  # one of three far off
    used, note, shift = stated_scales(loose, three, s)
    assert used == {k: loose[k] for k in "abcdefgh"}  # its deviation (0.55 %) is over the tolerance's sd: as stated
    used, note, shift = stated_scales(loose, dict(list(five.items())[:2]), s)  # two: too few, as stated
    assert used == {k: loose[k] for k in "abcdefgh"}


def test_stated_scatter_is_what_the_prints_scatter_beyond_their_own_spreads():
    from unscatter.imaging.batch import Settings, stated_scatter
    from unscatter.imaging.pose import EDGE_SD

    s = Settings()
    stated = {k: (np.log(1.1), 0.001) for k in "abcdefgh"}
    d = (0.0, 0.006, -0.006, 0.002, -0.002, 0.004, -0.004)
    placed = {k: np.log(1.1) + v for k, v in zip("abcdefg", d)}
    sds = dict.fromkeys(placed, 0.3)
    r = stated_scatter(stated, placed, sds, 512, 1.5, s)  # a template that misplaces edges by 1.5 px
    spread = 1.4826 * 0.004  # the robust spread of the differences
    assert r["prints"] == 7 and r["spread"] == pytest.approx(spread)
    assert r["spread_px"] == pytest.approx(spread * 512 / np.sqrt(6))  # RMS over the 512 px field
    assert r["excess_px"] == pytest.approx(np.sqrt(r["spread_px"] ** 2 - 0.3**2))
    # every print is then held to its stated size within the uncertainty of the batch's median
    assert r["held_within"] == pytest.approx(np.hypot(s.min_scale_sd, spread / np.sqrt(7)))
    # prints that claim as much as they scatter leave nothing over
    assert stated_scatter(stated, placed, dict.fromkeys(placed, 2.0), 512, 1.5, s)["excess_px"] == 0.0
    # a template that places edges as closely as EDGE_SD: the fits stand, the scatter is the metadata's
    assert stated_scatter(stated, placed, sds, 512, EDGE_SD, s)["held_within"] is None
    assert stated_scatter(stated, placed, sds, 512, None, s)["excess_px"] == 0.0
    # too few prints to measure a spread; prints without a stated size do not count
    assert stated_scatter(stated, dict(list(placed.items())[:5]), sds, 512, 1.5, s) is None
    assert stated_scatter({}, placed, sds, 512, 1.5, s) is None


def test_stated_pixel_sizes_that_scatter_are_measured_and_a_good_template_keeps_its_fits(tmp_path):
    """A zoom set by image (0.8 to 1.25), each image's camera pixel stated in OME-XML,
    the ratios between images held to 0.02 % or scattered by 1 %. The batch measures how
    far its prints scatter about the stated sizes (``stated_scatter`` in registration.yaml);
    with the default lab's template, which places the prints' edges within EDGE_SD, the
    scatter is the metadata's, and the trial prints register within 1 px on their own
    scales either way (where the template misplaces edges, the stated sizes hold every
    print's scale: ``test_bench_registration.py::
    test_prints_that_scatter_about_their_stated_pixel_sizes_are_held_to_them``)."""
    m = tmp_path / "masks"
    for k, mask in patterns.trial_masks(8, seed=6).items():
        write_png(m / f"{k}.png", mask)
    mic = {"scale": [0.8, 1.25], "rotation_deg": 6.0}
    for name, jitter in (("steady", 0.0002), ("scattered", 0.01)):
        b = tmp_path / name
        md = dict(where="ome", error=0.0, tolerance=0.001, jitter=jitter)
        print_batch(m, b / "batch", overrides={"microscope": dict(mic, pixel_size_metadata=md)}, seed=17, progress=False)
        register_batch(b / "batch", b / "reg", skip_failed=True, progress=False)
        errs = _pose_errors(b / "reg", b / "batch.truth")
        sc = read_yaml(b / "reg" / "registration.yaml")["stated_scatter"]
        assert sc["misfit_px"] <= 0.4 and sc["excess_px"] == 0.0 and sc["held_within"] is None, sc
        assert (sc["spread"] > 0.005) == (name == "scattered"), sc
        assert all(st == "ok" and e <= 1.0 for st, _, e in errs.values()), errs


def _one_feature_masks(root):
    """Three trial masks and three prints that are one feature each (a block, an L, a
    triangle; not a disc, whose rotation nothing fixes): their scale only their size
    could set."""
    import cv2

    m = root / "masks"
    for k, mask in patterns.trial_masks(3, seed=4).items():
        write_png(m / f"{k}.png", mask)
    ell = np.array([[150, 150], [260, 150], [260, 190], [190, 190], [190, 300], [150, 300]], np.int32)
    tri = np.array([[300, 330], [420, 360], [330, 430]], np.int32)
    for name, draw in (("block", lambda a: cv2.rectangle(a, (200, 220), (300, 290), 255, -1)),
                       ("ell", lambda a: cv2.fillPoly(a, [ell], 255)),
                       ("triangle", lambda a: cv2.fillPoly(a, [tri], 255))):
        a = np.zeros((512, 512), np.uint8)
        draw(a)
        write_png(m / f"{name}.png", a)
    return m


def test_a_stated_pixel_size_registers_one_feature_prints_and_a_stale_one_is_caught(tmp_path):
    """A lab whose zoom differs by image (0.8 to 1.25) states each image's camera pixel in
    its OME-XML. Calibrated within 0.1 %, the prints that are one feature register
    within 1.5 px, or fail (none ok off its pose; at least two of the three ok); without
    the metadata they fail as undetermined; stated 3 % off (a stale calibration, its
    stated tolerance 0.1 %), the batch's other prints contradict it and no print is ok
    with its pose off. With the template fitted posed (``Settings.template_posed``) the
    triangle fails, 0.45 px off: its refinement does not converge and its pose spread is
    1.7 px (the template of this 6-print batch, half of whose prints are one feature, has
    the tail at 0.20 where it had 0.13); with poses held it was ok 0.13 px off."""
    m = _one_feature_masks(tmp_path)
    one = ("block", "ell", "triangle")
    mic = {"scale": [0.8, 1.25], "rotation_deg": 8.0}
    results = {}
    for name, md in (("none", None), ("good", dict(where="ome", error=0.0003, tolerance=0.001, jitter=0.0002)),
                     ("stale", dict(where="ome", error=0.03, tolerance=0.001, jitter=0.0002))):
        b = tmp_path / name
        print_batch(m, b / "batch", overrides={"microscope": dict(mic, pixel_size_metadata=md)}, seed=31, progress=False)
        register_batch(b / "batch", b / "reg", skip_failed=True, progress=False)
        results[name] = _pose_errors(b / "reg", b / "batch.truth")
    # the lab wrote what it states, and registration read it
    truth = {r["id"]: r for r in read_tsv(tmp_path / "good" / "batch.truth" / "transforms.tsv")}
    px, where = image_pixel_size_um(tmp_path / "good" / "batch" / "images" / "block.tif")
    assert "OME" in where and px == pytest.approx(2.96 / float(truth["block"]["scale"]), rel=0.002)
    assert image_pixel_size_um(tmp_path / "none" / "batch" / "images" / "block.tif")[0] is None
    assert "image_pixel_size_tolerance: 0.001" in (tmp_path / "good" / "batch" / "batch.yaml").read_text()
    assert all(results["none"][k][0] == "failed" and "not determined" in results["none"][k][1] for k in one), results["none"]
    assert all(results["good"][k][0] == "failed" or results["good"][k][2] <= 1.5 for k in one), results["good"]
    assert sum(results["good"][k][0] == "ok" for k in one) >= 2, results["good"]
    assert not [k for k, (st, _, e) in results["stale"].items() if st == "ok" and not e <= 1.5], results["stale"]
    assert all(results["stale"][k][0] == "failed" for k in one), results["stale"]


def test_a_print_held_to_its_stated_pixel_size_says_so_when_its_turn_is_still_undetermined(tmp_path):
    """Two dots close together, in a batch whose images state their camera pixel size
    (OME-XML, within 0.1 %): the stated size holds their scale, but their turn rests on
    the dots' sizes more than on where they lie. The reason says that the scale was held
    to the stated size, and within what, not that it rests on the size of a feature (the
    reason given before for such prints, which read as if no stated size had been used)."""
    import cv2

    m = tmp_path / "masks"
    for k, mask in patterns.trial_masks(4, seed=4).items():
        write_png(m / f"{k}.png", mask)
    for name, dots, r in (("pair", [(240, 250), (290, 262)], 14), ("pair2", [(300, 200), (345, 185)], 12)):
        a = np.zeros((512, 512), np.uint8)
        for c in dots:
            cv2.circle(a, c, r, 255, -1)
        write_png(m / f"{name}.png", a)
    block = np.zeros((512, 512), np.uint8)
    cv2.rectangle(block, (200, 220), (300, 290), 255, -1)
    write_png(m / "block.png", block)
    md = dict(where="ome", error=0.0003, tolerance=0.001, jitter=0.0002)
    print_batch(m, tmp_path / "batch", overrides={"microscope": {"scale": [0.8, 1.25], "rotation_deg": 8.0,
                                                               "pixel_size_metadata": md}}, seed=31, progress=False)
    register_batch(tmp_path / "batch", tmp_path / "reg", skip_failed=True, progress=False)
    errs = _pose_errors(tmp_path / "reg", tmp_path / "batch.truth")
    pairs = {k: errs[k] for k in ("pair", "pair2")}
    held = [k for k, (st, why, _) in pairs.items() if st == "failed" and "its scale held to its stated camera pixel size"
            in why]
    assert held, pairs
    assert not any("its scale rests on the size of a feature" in why for _, why, _ in pairs.values()), pairs
    assert all("px over the field), its turn or shift still rests on the sizes" in pairs[k][1] for k in held), pairs
    assert not [k for k, (st, _, e) in errs.items() if st == "ok" and not e <= 1.5], errs


def test_registration_marks_fix_the_pose_of_prints_that_cannot_fix_their_own(tmp_path):
    """One block, a Siemens star and a grey grating that does not cure (designed masks
    hold such features) fail or come out empty on a lab whose zoom differs by image; with
    the designed masks' registration marks every one registers within 1.5 px, and the
    grating's not curing is measured: its print holds the marks and nothing else."""
    import cv2

    from unscatter.masks import fiducial_marks, with_fiducials
    from unscatter.io import read_print

    rng = np.random.default_rng(5)
    block = np.zeros((512, 512), np.uint8)
    cv2.rectangle(block, (190, 230), (300, 300), 255, -1)
    content = {"block": block, "star": patterns.siemens_star(rng), "dim": patterns.grating(rng, pitch=8, duty=0.5) // 255 * 70}
    content |= patterns.trial_masks(3, seed=4)
    over = {"microscope": {"scale": [0.8, 1.25], "rotation_deg": 8.0}}
    errs = {}
    for name, marked in (("plain", False), ("marked", True)):
        for k, mask in content.items():
            write_png(tmp_path / name / "masks" / f"{k}.png", with_fiducials(mask) if marked else mask)
        print_batch(tmp_path / name / "masks", tmp_path / name / "batch", overrides=over, seed=12, progress=False)
        register_batch(tmp_path / name / "batch", tmp_path / name / "reg", skip_failed=True, progress=False)
        errs[name] = _pose_errors(tmp_path / name / "reg", tmp_path / name / "batch.truth")
    assert errs["plain"]["block"][0] == "failed" and errs["plain"]["dim"][0] in ("failed", "empty"), errs["plain"]
    assert all(st == "ok" and e <= 1.5 for st, _, e in errs["marked"].values()), errs["marked"]
    dim = read_print(tmp_path / "marked" / "reg" / "dim.png")
    marks, clear = fiducial_marks(512)
    assert dim[marks].mean() > 0.7 and dim[~clear].mean() < 0.01  # the marks printed (corners rounded), nothing else


def test_the_template_on_refinements_crop_equals_the_whole_grids():
    """Refinement computes the print template on a crop of the grid that holds every pixel
    the print can cure at: within the residual window it must equal the whole grid's
    template and derivatives, for wide haze (a reduced grid) and at half resolution, and
    a small feature's crop must be a small part of the grid."""
    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.pose import ROI_BAND_PX, _cure_crop, _prior, _window, print_template
    from unscatter.imaging.template import PrintTemplate

    rng = np.random.default_rng(7)
    dot = np.zeros((512, 512), np.uint8)
    dot[30:70, 420:470] = 255
    grating = np.zeros((512, 512), np.uint8)
    grating[:, 100:400:12] = 200
    star = patterns.siemens_star(np.random.default_rng(3), spokes=12)
    for m in (dot, grating, star):
        for f in (1, 2):
            x = np.array(PrintTemplate.START, float)
            x[1], x[8], x[9] = rng.uniform(0.2, 0.45), rng.uniform(0.1, 0.4), rng.uniform(20, 60)
            x[10], x[11], x[12] = rng.uniform(0.7, 4.0), rng.uniform(0.1, 0.4), rng.uniform(20, 80)
            t = PrintTemplate(512, MARGIN, factor=f)
            B = t.exposure(t.padded(m), x)
            q = _prior(x)[0] + rng.normal(0, 0.1, 7)
            (r0, r1), (c0, c1) = _window(B, int(np.ceil((4 * x[10] + ROI_BAND_PX) / f)))
            (a0, a1), (b0, b1) = _cure_crop(t, B, x, ((r0, r1), (c0, c1)))
            whole = print_template(t, B, x, q)
            part = print_template(t.crop((a0, a1), (b0, b1)), B[a0:a1, b0:b1], x, q)
            for W, P in zip([whole[0], *whole[1]], [part[0], *part[1]]):
                scale = float(np.abs(W).max())
                assert np.abs(W[r0:r1, c0:c1] - P[r0 - a0:r1 - a0, c0 - b0:c1 - b0]).max() <= 1e-4 * scale
            if m is dot:
                assert (a1 - a0) * (b1 - b0) < 0.15 * B.size


def test_thin_lines_that_cured_in_an_eroding_batch_are_faint_not_empty(tmp_path):
    """A batch that erodes its prints by 5 um under a microscope blur of 3 px: the lines
    of a cut-off grating that cured image below the threshold (the bare mask's lines
    would not) and must not be reported empty; gratings that did not cure stay empty."""
    from unscatter.masks import grating_cutoff, trial_masks

    m = tmp_path / "masks"
    for k, v in trial_masks(6, seed=1).items():
        write_png(m / f"{k}.png", v)
    for j in range(3):
        g = grating_cutoff(np.random.default_rng(j), pitch=8 + 2 * j, duty=0.4, variant="truncated")
        write_png(m / f"cutoff_{j}.png", g)
    over = {"printer": {"edge_offset_um": -5.1, "kernel": {"sigma_um": 7.3}},
            "microscope": {"blur_px": [2.7, 3.0], "scale": [1.2, 1.25], "rotation_deg": 5.0}}
    print_batch(m, tmp_path / "batch", overrides=over, seed=3, progress=False)
    rows = {r["id"]: r for r in register_batch(tmp_path / "batch", tmp_path / "reg", skip_failed=True, progress=False)}
    truth = {k: read_print(tmp_path / "batch.truth" / "prints" / f"{k}.png").mean() for k in rows}
    assert truth["cutoff_2"] > 0.002 and rows["cutoff_2"]["status"] == "failed"
    assert rows["cutoff_2"]["reason"].startswith("faint") and "eroded by" in rows["cutoff_2"]["reason"]
    for k in ("cutoff_0", "cutoff_1"):
        assert truth[k] == 0 and rows[k]["status"] == "empty"
    # the trial prints are `ok`, but trial_003 may fail as resting on the kernel's shape:
    # the batch's scale is free (zoom per image), and with the scale free in the kernel's
    # step (pose.kernel_spread) it is 0.29 px off at a spread of 1.53 px against 1.5
    failed = [(j, r["status"], r["reason"]) for j in range(6) if (r := rows[f"trial_{j:03d}"])["status"] != "ok"]
    assert all(j == 3 and st == "failed" and "shape of the scatter kernel" in why for j, st, why in failed), failed


def test_the_registration_marks_alone_place_a_print_whose_body_pulls_the_pose():
    """A marked mask whose body printed 2 px (each way) from where its mask puts it (a
    template that misplaces a large feature): a fit of the whole print is pulled 2.6 px
    off; refitted on the marks' cleared bands, the nuisance numbers held, it returns to
    the marks."""
    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.pose import pose_distance, refine
    from unscatter.imaging.template import PrintTemplate
    from unscatter.masks import fiducial_marks, with_fiducials

    body = np.zeros((512, 512), np.uint8)
    body[150:420, 140:430] = 255
    mask = with_fiducials(body)
    marks, clear = fiducial_marks(512)
    tmpl = PrintTemplate(512, MARGIN)
    x = np.array(PrintTemplate.START)
    n = 512 + 2 * MARGIN
    printed = np.where(marks, 255, np.where(clear, 0, np.roll(body, (2, 2), (0, 1)))).astype(np.uint8)
    img = 0.1 + 0.8 * tmpl(tmpl.padded(printed), x)
    img = (img + np.random.default_rng(1).normal(0, 0.02, img.shape)).astype(np.float32)
    eye = np.hstack([np.eye(2), np.zeros((2, 1))])
    B = tmpl.exposure(tmpl.padded(mask), x)
    whole = refine(img, eye, tmpl, B, x, iters=30)
    assert pose_distance(whole.M, eye, n, MARGIN) > 1.0
    on_marks = refine(img, whole, tmpl, B, x, iters=30, region=np.pad(clear, MARGIN), hold_nuisance=True)
    assert pose_distance(on_marks.M, eye, n, MARGIN) < 0.3 and on_marks.converged
    assert np.array_equal(on_marks.q, whole.q) and on_marks.pose_sd < 0.5


def test_every_print_of_one_magnification_is_held_within_the_medians_uncertainty():
    """The batch's median scale is known far better than a single print's (the spread
    over the root of the prints), never better than a zoom's repeatability (0.1 %)."""
    from unscatter.imaging.batch import Settings, one_magnification_held

    s = Settings()
    centre, sd = one_magnification_held((0.05, 0.0024), 9, s)
    assert centre == 0.05 and sd == pytest.approx(np.hypot(s.min_scale_sd, 0.0008))
    assert s.min_scale_sd <= one_magnification_held((0.0, 0.001), 100, s)[1] < 0.00101
    assert one_magnification_held((0.0, 0.004), 1, s)[1] > 0.004


def template_prints(tmpl, truth, mask_seed: int, rng) -> list:
    """(mask, image, dose) of 12 trial masks imaged through the print template at
    ``truth``, on a background of 0.1 with noise of 3 % of the print's contrast."""
    pairs = []
    for m in patterns.trial_masks(12, seed=mask_seed).values():
        pm = tmpl.padded(m)
        pairs.append((pm, (0.1 + tmpl(pm, truth) + rng.normal(0, 0.03, tmpl.shape)).astype(np.float32), 1.0))
    return pairs


@pytest.fixture(scope="module")
def hot_spot_prints():
    """Twelve trial masks imaged through a print template with a wide tail and a haze, and
    a lamp field whose quadratic part cannot follow a 50 % hot spot at (0.5, -0.3) of the
    half field; and the same prints with no hot spot. Noise 3 % of the print's contrast."""
    from unscatter.imaging.template import PrintTemplate

    tmpl = PrintTemplate(512, 32, factor=4)
    truth = np.array(PrintTemplate.START, float)
    truth[:13] = (5.0, 0.35, 0.15, 0.03, -0.02, -0.05, 0.0, -0.04, 0.2, 25.0, 2.0, 0.1, 40.0)
    truth[13:17] = (0.5, 0.5, -0.3, 0.35)
    rng = np.random.default_rng(3)
    out = {}
    for name, x in (("hot", truth), ("flat", np.r_[truth[:13], PrintTemplate.START[13:]])):
        pairs = []
        for m in patterns.trial_masks(12, seed=5).values():
            pm = tmpl.padded(m)
            img = 0.1 + tmpl(pm, x) + rng.normal(0, 0.03, tmpl.shape)
            pairs.append((pm, img.astype(np.float32), 1.0))
        out[name] = pairs
    return tmpl, truth, out


def test_a_lamp_hot_spot_is_found_where_the_prints_show_one(hot_spot_prints):
    """The template fit without a hot spot, then the hot-spot search: it finds the bump
    (centre within 0.1 of the half field) and the fit gains. Powell over the field and
    the bump from a grid of centres did not (80 evaluations per centre): a 50 % bump
    gains under 1e-3 of mean NCC, near Powell's tolerance."""
    from unscatter.imaging.template import PrintTemplate, fit_hot_spot, fit_template, mean_ncc

    tmpl, truth, prints = hot_spot_prints
    pairs = prints["hot"]
    x, fit = fit_template(tmpl, pairs, PrintTemplate.START)
    assert mean_ncc(tmpl, pairs, truth) - fit > 3e-4  # the quadratic field alone misses it
    x2, fit2 = fit_hot_spot(tmpl, pairs, x, fit)
    assert x2[13] > 0.2, x2[13:]
    assert np.hypot(x2[14] - 0.5, x2[15] + 0.3) < 0.1, x2[13:]
    assert fit2 > fit + 3e-4


def test_a_weak_hot_spot_near_the_limit_is_found_by_the_folds():
    """A 30 % hot spot at (0.6, -0.4) in the same template: at the truth the fit gains
    only 3.4e-4 of mean NCC over the quadratic field alone, under twice the gain a bump
    must carry to prints it was not fitted to (2e-4). Cross-validated over 4 folds the
    bump is found and put within 0.05 of the half field of its centre (measured: 0.02
    off; a 20 % spot, 2e-4 at the truth, is below what the test can take)."""
    from unscatter.imaging.template import HOT_FOLDS, PrintTemplate, fit_hot_spot, fit_template, mean_ncc

    assert HOT_FOLDS == 4
    tmpl = PrintTemplate(512, 32, factor=4)
    truth = np.array(PrintTemplate.START, float)
    truth[:13] = (5.0, 0.35, 0.15, 0.03, -0.02, -0.05, 0.0, -0.04, 0.2, 25.0, 2.0, 0.1, 40.0)
    truth[13:17] = (0.3, 0.6, -0.4, 0.4)
    pairs = template_prints(tmpl, truth, 5, np.random.default_rng(4))
    x, fit = fit_template(tmpl, pairs, PrintTemplate.START)
    assert 2e-4 < mean_ncc(tmpl, pairs, truth) - fit < 4e-4
    x2, fit2 = fit_hot_spot(tmpl, pairs, x, fit)
    assert 0.2 < x2[13] < 0.4 and np.hypot(x2[14] - 0.6, x2[15] + 0.4) < 0.05, x2[13:17]
    assert fit2 > fit + 2e-4
    # the registration runs the folds (and the centres of the search on all prints) in its threads: every fit
    # depends on its own prints and start only, so the numbers are the same as one after the other
    with ThreadPoolExecutor(2) as ex:
        x3, fit3 = fit_hot_spot(tmpl, pairs, x, fit, pool=ex.map)
    assert np.array_equal(x2, x3) and fit3 == fit2, (x2[13:17], x3[13:17])


def test_the_ncc_at_a_small_move_of_the_pose_is_the_ncc_at_the_moved_pose():
    """``_Centred.ncc_posed``: an image that is the template moved by a shift of 0.14 px of
    its grid, a turn of 0.05 deg and a scale of 0.1 % fits it nearly as the moved template
    does: to first order, it gains at least 95 % of what the plain NCC loses (98 to 99 %
    measured; 88 to 94 % at three times the move); the same with missing pixels; a
    negative image has a negative NCC."""
    import cv2

    from unscatter.imaging.template import PrintTemplate, _Centred

    tmpl = PrintTemplate(512, 32, factor=4)
    x = np.array(PrintTemplate.START, float)
    rng = np.random.default_rng(11)
    n = tmpl.shape[0]
    A = cv2.getRotationMatrix2D(((n - 1) / 2,) * 2, 0.05, 1.001)
    A[:, 2] += (0.1, -0.1)
    for m in list(patterns.trial_masks(4, seed=2).values()):
        T = tmpl(tmpl.padded(m), x)
        moved = cv2.warpAffine(T, A, (n, n), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        img = (2.0 * moved + 0.5 + rng.normal(0, 0.01, T.shape)).astype(np.float32)
        for holes in (False, True):
            if holes:
                img[:8] = np.nan
            seen = _Centred(img)
            at_moved, plain, posed = seen.ncc(moved), seen.ncc(T), seen.ncc_posed(T, tmpl.X, tmpl.Y)
            assert at_moved - plain > 4e-4, (at_moved, plain)
            assert (posed - plain) / (at_moved - plain) > 0.95, (at_moved, plain, posed)
        assert _Centred(-img).ncc_posed(T, tmpl.X, tmpl.Y) < -0.99


def test_the_templates_field_does_not_take_up_a_common_scale_error_of_the_poses():
    """Eight prints of a template with no lamp field, warped into the template's grid at
    poses 0.4 % too large (each 0.1 % either way besides): held at those poses, the fit
    makes up for the scale with a lamp field that rises outward (fxx + fyy 0.09 at the
    test's draw), which moves every feature outward as the scale did and would keep the
    next poses 0.4 % off. With the poses' small moves fitted (``posed``) the field stays
    within 0.03 of flat (0.017 at the draw)."""
    import cv2

    from unscatter.imaging.template import PrintTemplate, fit_template

    tmpl = PrintTemplate(512, 32, factor=4)
    truth = np.array(PrintTemplate.START, float)
    truth[8], truth[11] = 0.0, 0.0  # no tail, no haze
    rng = np.random.default_rng(1)
    n = tmpl.shape[0]
    pairs = []
    for m in list(patterns.trial_masks(12, seed=5).values())[:8]:
        pm = tmpl.padded(m)
        A = cv2.getRotationMatrix2D(((n - 1) / 2,) * 2, 0.0, 1.004 + rng.normal(0, 0.001))
        img = cv2.warpAffine(tmpl(pm, truth).astype(np.float32), A, (n, n), flags=cv2.INTER_LINEAR)
        pairs.append((pm, (3 * img + 0.5 + rng.normal(0, 0.01, img.shape)).astype(np.float32), 1.0))
    radial = {}
    for posed in (False, True):
        x, _ = fit_template(tmpl, pairs, PrintTemplate.START, 300, posed=posed)
        radial[posed] = x[5] + x[7]  # fxx + fyy
    assert radial[False] > 0.05, radial
    assert abs(radial[True]) < 0.03, radial


def test_the_posed_nccs_gradient_is_numpys_to_the_last_digit():
    """``template._gradient``: np.gradient's numbers along either axis of a float32 image
    (central differences, one-sided at the borders), written in place."""
    from unscatter.imaging.template import _gradient

    f = np.random.default_rng(4).normal(0, 1, (37, 23)).astype(np.float32) ** 3
    gy, gx = np.gradient(f)
    out = np.empty((2, *f.shape), np.float32)
    _gradient(f, out[0], 0)
    _gradient(f, out[1], 1)
    assert np.array_equal(out[0], gy) and np.array_equal(out[1], gx)


def test_refines_jacobian_and_edge_basis_written_in_place_give_the_lists_numbers():
    """``pose._jacobian`` (rows written into one array) and ``edge_shifted`` (its squares
    taken once): the numbers, to the last digit, of the per-row arrays they replace, in
    either mode; a row that differs in the last digit
    would send refine's steps elsewhere."""
    from unscatter.imaging.pose import _jacobian, edge_shifted

    rng = np.random.default_rng(11)
    shape = (29, 41)
    T = (rng.normal(0, 1, shape) ** 3).astype(np.float32)
    dq = [rng.normal(0, 1, shape).astype(np.float32) for _ in range(7)]
    g = np.arange(64, dtype=np.float32) - np.float32(31.5)
    Xg, Yg = np.meshgrid(g[3 : 3 + shape[1]], g[5 : 5 + shape[0]])
    for mode in ("similarity", "affine"):
        for gain in (0.7318, 1.9):
            gy, gx = np.gradient(gain * T)
            cols = [gx * Xg, gx * Yg, gy * Xg, gy * Yg, gx, gy] if mode == "affine" else [gx * Xg + gy * Yg, gy * Xg - gx * Yg, gx, gy]
            cols += [-T, -np.ones_like(T)] + [-gain * d for d in dq]
            want = np.stack([c.astype(np.float32) for c in cols])
            J = np.full_like(want, np.nan)
            _jacobian(J, gain, T, dq, Xg, Yg, mode)
            assert np.array_equal(J, want), mode
    edge = (0.4, -0.3, 0.25)
    gy, gx = np.gradient(T)
    gm = np.sqrt(gx * gx + gy * gy)
    inv = 1.0 / np.maximum(gm, 1e-12 + 1e-6 * float(gm.max()))
    basis = [gm / 2, (gx * gx - gy * gy) * inv / 2, 2 * gx * gy * inv / 2]
    T_e, got = edge_shifted(T, edge, 2)
    assert np.array_equal(T_e, T + 0.4 * basis[0] + -0.3 * basis[1] + 0.25 * basis[2])
    assert all(np.array_equal(a, b) for a, b in zip(got, basis))


def test_the_template_fit_in_forked_processes_gives_the_numbers_of_threads():
    """``fit_template(processes=2)``: each half of the prints in a forked process that
    lives through the search (``parallel.ForkedParts``) gives the numbers, to the last
    digit, that the same halves on two threads give (registration.yaml of a lab of the
    registration benchmark is byte for byte the same either way)."""
    from concurrent.futures import ThreadPoolExecutor

    import cv2

    from unscatter.imaging.template import PrintTemplate, fit_template

    tmpl = PrintTemplate(256, 16, factor=4)
    truth = np.array(PrintTemplate.START, float)
    rng = np.random.default_rng(3)
    n = tmpl.shape[0]
    pairs = []
    for m in list(patterns.trial_masks(8, seed=7, size=256).values())[:8]:
        pm = tmpl.padded(m)
        A = cv2.getRotationMatrix2D(((n - 1) / 2,) * 2, 0.0, 1.0 + rng.normal(0, 0.002))
        img = cv2.warpAffine(tmpl(pm, truth).astype(np.float32), A, (n, n), flags=cv2.INTER_LINEAR)
        pairs.append((pm, (3 * img + 0.5 + rng.normal(0, 0.02, img.shape)).astype(np.float32), 1.0))
    with ThreadPoolExecutor(2) as ex:
        threads = fit_template(tmpl, pairs, PrintTemplate.START, 120, pool=ex.map, posed=True)
    forked = fit_template(tmpl, pairs, PrintTemplate.START, 120, posed=True, processes=2)
    assert np.array_equal(threads[0], forked[0]) and threads[1] == forked[1], (threads, forked)


def test_lamp_fields_that_fit_as_well_are_those_of_a_spot_the_prints_do_not_fix(hot_spot_prints):
    """``field_alternatives``: the field fitted again with every number free, then with the
    spot's width halved and doubled and held. Twelve prints of a 50 % spot rule both out
    (measured: the mean NCC 2.6e-4 and 2.3e-4 below the best, beyond the 2e-4 a spot must
    gain); five prints of a 15 % spot do not (1.7e-5 and 3e-6 below), and both come back,
    each at its width (the second at the width's bound, 0.8); a template without a spot
    has none."""
    from unscatter.imaging.template import PrintTemplate, field_alternatives

    tmpl, truth, prints = hot_spot_prints
    assert field_alternatives(tmpl, prints["hot"], truth) == []
    every = field_alternatives(tmpl, prints["hot"], truth, tol=np.inf)
    assert [w for _, _, w in every] == pytest.approx([0.175, 0.7], abs=0.01) and all(g < -2e-4 for _, g, _ in every)
    weak = truth.copy()
    weak[13], weak[16] = 0.15, 0.5
    alts = field_alternatives(tmpl, template_prints(tmpl, weak, 5, np.random.default_rng(4)), weak)
    assert [w for _, _, w in alts] == pytest.approx([0.23, 0.8], abs=0.01), [(w, g) for _, g, w in alts]
    assert all(xa[16] == w and xa[13] > 0 for xa, _, w in alts)
    assert field_alternatives(tmpl, prints["hot"], np.r_[truth[:13], PrintTemplate.START[13:]]) == []


def test_a_print_that_fails_anyway_is_known_before_the_last_refits():
    """``batch.fails_anyway``, which spares the field alternatives' refits (step 5d) the
    prints that QC fails already: a converged pose with no rival and small spreads passes;
    each of QC's reasons on the chosen pose alone (not converged, the mask's symmetry, a
    rival close, the pose's spread, the spread from the feature sizes, that with the
    kernel's, an unknown size) fails it."""
    from dataclasses import replace

    from unscatter.imaging.batch import PoseChoice, Settings, fails_anyway
    from unscatter.imaging.pose import Fit

    s = Settings()
    good = Fit(np.eye(2, 3), 1.0, 0.0, np.zeros(7), 0.1, 0.2, True, 5, size_sd=0.3, model_sd=0.1)
    ch = PoseChoice(good, evidence=9.0)
    assert not fails_anyway(ch, s)
    assert fails_anyway(PoseChoice(None), s)
    assert fails_anyway(replace(ch, symmetry=90.0), s)
    assert fails_anyway(replace(ch, evidence=s.min_evidence / 2), s)
    assert not fails_anyway(replace(ch, aside=0.0), s)  # a rival set aside by a contradiction is no reason of its own
    for change in (dict(converged=False), dict(pose_sd=2 * s.max_pose_sd), dict(size_sd=1.1 * s.max_size_sd),
                   dict(model_sd=s.max_size_sd), dict(size_sd=float("nan"))):
        assert fails_anyway(replace(ch, fit=replace(good, **change)), s), change


def test_no_hot_spot_is_found_where_the_field_is_smooth(hot_spot_prints):
    """The same prints with a smooth field: the search's best bump does not carry over to
    the prints it was not fitted to, and the template keeps none."""
    from unscatter.imaging.template import PrintTemplate, fit_hot_spot, fit_template

    tmpl, _, prints = hot_spot_prints
    pairs = prints["flat"]
    x, fit = fit_template(tmpl, pairs, PrintTemplate.START)
    x2, fit2 = fit_hot_spot(tmpl, pairs, x, fit)
    assert x2[13] == 0.0 and fit2 == fit, x2[13:]


def test_a_print_far_worse_fitted_than_the_others_is_left_out_of_the_templates_fit(hot_spot_prints):
    """A print whose image is turned a quarter off its mask (a first pose that is wrong)
    is left out of the template's second fit; at the true numbers none of the noisy
    prints is, small and faint ones included (their misfit is their noise's)."""
    from unscatter.imaging.template import fit_template, misfit_beyond_noise, well_fitted

    tmpl, truth, prints = hot_spot_prints
    pairs = list(prints["hot"])
    assert well_fitted(tmpl, pairs, truth) is pairs
    assert max(misfit_beyond_noise(reg, tmpl(m, truth, d)) for m, reg, d in pairs) < 0.05
    m, img, d = pairs[5]
    pairs[5] = (m, np.ascontiguousarray(np.rot90(img)), d)
    x, _ = fit_template(tmpl, pairs, truth, max_evals=200)
    assert misfit_beyond_noise(pairs[5][1], tmpl(m, x, d)) > 0.5
    kept = well_fitted(tmpl, pairs, x)
    assert len(kept) == 11 and all(p[0] is not m for p in kept)


@pytest.mark.parametrize("ratio, angle", [(1.0, 0.0), (1.5, 30.0), (1.7, -60.0)])
def test_the_template_fit_finds_the_batchs_anisotropic_scatter(ratio, angle):
    """Twelve trial masks through a template whose scatter is 1.5 or 1.7 times wider along
    one direction (or round), with a tail and a haze, noise 3 %: the fit from the round
    start finds the ratio within 6 % and its direction within 5 deg, and sigma within 8 %;
    a round batch gets a ratio under 1.03."""
    from unscatter.imaging.template import PrintTemplate, fit_template

    tmpl = PrintTemplate(512, 32, factor=4)
    truth = np.array(PrintTemplate.START, float)
    truth[:13] = (4.0, 0.4, 0.15, 0.03, -0.02, -0.05, 0.0, -0.04, 0.15, 25.0, 2.0, 0.05, 40.0)
    L, a = np.log(ratio), np.radians(angle)
    truth[17:19] = L * np.cos(2 * a), L * np.sin(2 * a)
    pairs = template_prints(tmpl, truth, 9, np.random.default_rng(4))
    x, _ = fit_template(tmpl, pairs, PrintTemplate.START)
    L_fit = np.hypot(x[17], x[18])
    assert abs(np.exp(L_fit) / ratio - 1) < 0.06, (np.exp(L_fit), x)
    if ratio > 1:
        turn = (np.degrees(np.arctan2(x[18], x[17]) / 2) - angle + 90) % 180 - 90
        assert abs(turn) < 5, (turn, x)
    assert abs(x[0] / truth[0] - 1) < 0.08, x


def test_the_elliptical_core_is_the_kernels_convolution():
    """``core_blur`` against OpenCV's filter2D with the elliptical kernel drawn out (axes
    sigma e^(L/2) along a, sigma e^(-L/2) across), and OpenCV's Gaussian where it is round."""
    import cv2

    from unscatter.imaging.template import core_blur

    e = np.zeros((144, 144), np.float32)
    e[40:100, 50:60], e[70:75, 20:120] = 1.0, 0.5
    sigma, L, a = 2.0, 0.5, np.radians(30)
    y, x = np.mgrid[-20:21, -20:21].astype(float)
    u, v = np.cos(a) * x + np.sin(a) * y, -np.sin(a) * x + np.cos(a) * y
    k = np.exp(-0.5 * ((u / (sigma * np.exp(L / 2))) ** 2 + (v / (sigma * np.exp(-L / 2))) ** 2))
    ref = cv2.filter2D(e, -1, (k / k.sum()).astype(np.float32), borderType=cv2.BORDER_CONSTANT)
    assert np.abs(core_blur(e, sigma, L * np.cos(2 * a), L * np.sin(2 * a)) - ref).max() < 1e-5
    assert np.array_equal(core_blur(e, sigma), cv2.GaussianBlur(e, (0, 0), sigma))


def test_an_image_may_be_as_much_dimmer_as_the_batchs_prints_vary():
    """Gains of the determined prints whose logs lie 0.1 apart (a median absolute
    deviation of 0.1, a robust sd of 0.148): an image may be exp(-faint_sigmas x 0.148)
    as bright as the median; an outlier does not widen it; with fewer than three prints,
    no allowance."""
    from unscatter.imaging.batch import Settings, dimmest

    s = Settings()
    g = list(np.exp([-0.2, -0.1, 0.0, 0.1, 0.2]))
    assert dimmest(g, s) == pytest.approx(np.exp(-s.faint_sigmas * 0.14826))
    assert dimmest(g + [50.0], s) > np.exp(-s.faint_sigmas * 0.3)  # its log, 3.9, would give an sd of 1.5
    assert dimmest([1.0, 2.0], s) == 1.0 and dimmest([], s) == 1.0


def _dot_grid(q, seed=0, columns=(290, 345, 400, 455)):
    """Dots in two rows, 55 px apart (a repeat of isolated dots, under 1 % of the field),
    imaged as the print template at nuisance numbers ``q``, gain 2, noise 0.01."""
    from unscatter.imaging.batch import MARGIN
    from unscatter.imaging.pose import print_template
    from unscatter.imaging.template import PrintTemplate

    mask = np.zeros((512, 512), np.uint8)
    yy, xx = np.mgrid[:512, :512]
    for cx in columns:
        for cy, r in ((90, 10), (145, 6)):
            mask[np.hypot(xx - cx, yy - cy) <= r] = 255
    tmpl = PrintTemplate(512, MARGIN)
    x = np.array(PrintTemplate.START)
    B = tmpl.exposure(tmpl.padded(mask), x)
    T = print_template(tmpl, B, x, np.array(q, float), derivatives=False)[0]
    img = 0.05 + 2.0 * T + np.random.default_rng(seed).normal(0, 0.01, T.shape).astype(np.float32)
    return img.astype(np.float32), tmpl, B, x


@pytest.mark.parametrize("seed", [0, 1])
def test_a_dim_print_refined_from_the_prior_dose_does_not_run_off(seed):
    """A dim print (dose 0.45: the small dots do not cure) refined from the prior's dose
    at its true pose. Gauss-Newton alone overshot to a dose that cures nothing, the priors
    then pulled every nuisance number back, and the pose walked 13 px off with a residual
    17 times the noise, called settled. Steps that raise the objective are now refused and
    damped: the fit stays on the print, and what it cannot settle its spread says."""
    from unscatter.imaging.pose import refine

    img, tmpl, B, x = _dot_grid((0.45, 1.2, 0.0, 0.0, 0.0, 0.0, 0.0), seed)
    fit = refine(img, np.hstack([np.eye(2), np.zeros((2, 1))]), tmpl, B, x, iters=30, tol=1e-3)
    err = float(np.hypot(*fit.M[:, 2]))  # identity linear part: the shift is the pose error
    assert fit.sigma < 0.015, fit.sigma
    assert err <= max(0.5, 3 * fit.pose_sd), (err, fit.pose_sd)


def test_the_evidence_clips_at_the_level_of_the_print_not_of_its_area():
    """The evidence clips squared residuals at half the print's level above its offset.
    Taken as the template's 99th percentile, that level was the faint halo of a print
    covering under 1 % of the field, 20 times below its dots: a dot present or absent then
    counted no more than a halo slightly off, and a pose one dot pitch away, with the lamp
    field bent to dim the column it added, won (a dots print 55 px off passed as ok)."""
    from unscatter.imaging.pose import Fit, print_level, print_template

    q = np.array((0.9, 1.2, 0.0, 0.0, 0.0, 0.0, 0.0))
    levels = []
    for columns in ((290, 345, 400, 455), (290,)):
        _, tmpl, B, x = _dot_grid(q, columns=columns)
        T = print_template(tmpl, B, x, q, derivatives=False)[0]
        fit = Fit(np.zeros((2, 3)), 2.0, 0.05, q, 0.01, 0.1, True, 1)
        assert float(np.percentile(T, 99)) < 0.1 * float(T.max())  # the old level: the halo
        levels.append(print_level(fit, T))
        assert 0.5 * 2.0 * T.max() < levels[-1] <= 2.0 * T.max()
    assert abs(levels[0] / levels[1] - 1) < 0.1, levels


def test_a_batch_too_small_to_measure_its_size_error_says_so(tmp_path, trial_dir, caplog):
    """A batch measures how far its template's feature sizes are off on its prints whose
    features' places fix their pose; with fewer than ``size_min_prints`` of them it can
    only assume it, and says so (docs/registration.md, "Small registration batches")."""
    from unscatter.imaging.batch import Settings

    masks = tmp_path / "masks"
    masks.mkdir()
    for name in ("trial_000.png", "trial_001.png"):
        shutil.copy(trial_dir / name, masks / name)
    print_batch(masks, tmp_path / "batch", seed=4, progress=False)
    with caplog.at_level("WARNING", logger="unscatter.imaging.batch"):
        register_batch(tmp_path / "batch", tmp_path / "reg", skip_failed=True, progress=False)
    s = Settings()
    measured = read_yaml(tmp_path / "reg" / "registration.yaml")["feature_sizes"]["prints"]
    assert f"prints whose pose their features' places fix: {measured} of 2, fewer than the {s.size_min_prints} needed" in caplog.text
    assert f"assumed right within {s.size_sd:.1f} px" in caplog.text
    assert "Register the prints of one printer and microscope together, or state the camera pixel size" in caplog.text


def test_an_uneven_stain_is_divided_out_of_the_images_the_poses_are_fitted_to(tmp_path):
    """Ten paper trial masks on a lab whose polymer fluorescence varies by 25 % over about
    100 image px (uneven staining), imaged with a 1.5 to 2.5 px blur. With one gain per
    print the dim part's edges are fitted inside the bright part's: registered with the
    stain left in (``stain_min_sd`` inf) the median pose error is 0.98 px and a print is ok
    1.78 px off. Divided out (``stain_field``; qc.tsv's ``stain``, the field's spread): 0.38
    px, no print ok more than 1.01 px off.

    The prints are thresholded on the divided images too (``stain_threshold``), at a dense
    level taken from them. Thresholded on the images as they are (``stain_threshold``
    False), the batch's brightest polymer is where the stain is brightest, and the ok
    prints' edges were a median 3.4 px per edge px off the lab's true prints (all too
    small, up to 7.7 px; 1.1 with the stain not measured at all); divided, 0.46."""
    for k, mask in patterns.trial_masks(10, seed=11).items():
        write_png(tmp_path / "masks" / f"{k}.png", mask)
    over = {"microscope": {"staining": {"variation": 0.25, "length_px": 100.0}, "blur_px": [1.5, 2.5]}}
    print_batch(tmp_path / "masks", tmp_path / "batch", overrides=over, seed=4, progress=False)
    med, edge = {}, {}
    for name, kw in (("divided", {}), ("left", {"stain_min_sd": float("inf")}), ("imaged", {"stain_threshold": False})):
        register_batch(tmp_path / "batch", tmp_path / name, skip_failed=True, progress=False, **kw)
        errs = _pose_errors(tmp_path / name, tmp_path / "batch.truth")
        med[name] = float(np.nanmedian([e for _, _, e in errs.values()]))
        rows = read_tsv(tmp_path / name / "qc.tsv")
        stains = [r["stain"] for r in rows]
        edge[name] = float(np.median([_edge_error_px(tmp_path / name, tmp_path / "batch.truth", r["id"]) for r in rows
                                      if r["status"] == "ok"]))
        stain = read_yaml(tmp_path / name / "registration.yaml")["stain"]
        if name == "divided":
            assert sum(v != "" for v in stains) >= 6, stains
            assert stain["prints"] >= 6 and stain["thresholded_divided"] >= 6, stain
            assert len(list((tmp_path / name / "stain").glob("*.tif"))) == stain["thresholded_divided"]
            assert max((e for st, _, e in errs.values() if st == "ok"), default=np.inf) <= 1.5, errs
        elif name == "left":
            assert all(v == "" for v in stains)
        if name != "divided":
            assert stain["thresholded_divided"] == 0 and not (tmp_path / name / "stain").exists()
    assert med["divided"] <= 0.5 and med["left"] >= 0.8, med
    assert edge["divided"] <= 0.8 and edge["imaged"] >= 2.0, edge


def test_the_half_cure_level_undoes_the_blur_of_a_polymer_that_rises_unevenly(tmp_path):
    """A lab whose gel dose is close to its cure threshold (0.42 against 0.48: the polymer
    rises steeply from nothing, then saturates slowly), imaged with a 3 px blur. Cut at half
    of the dense polymer, every print comes out too small (the image at the half cure's
    place is below half of the plateau: the blur averages the slow rise inside with the
    nothing outside); cut where the batch's template crosses its half cure
    (``half_cure``, ``template.half_cure_level``), the prints' edges move toward the lab's
    true ones: a median -0.29 px per edge px of the ok prints against -0.03."""
    from unscatter.imaging.template import PrintTemplate, half_cure_level

    for k, mask in patterns.trial_masks(10, seed=12).items():
        write_png(tmp_path / "masks" / f"{k}.png", mask)
    over = {"printer": {"cure": {"threshold": 0.48, "gel_dose": 0.42}, "kernel": {"heavy_tail": None}},
            "microscope": {"blur_px": [3.0, 3.0]}}
    print_batch(tmp_path / "masks", tmp_path / "batch", overrides=over, seed=5, progress=False)
    bias = {}
    for name, kw in (("half", {"half_cure": True}), ("plain", {})):
        register_batch(tmp_path / "batch", tmp_path / name, skip_failed=True, progress=False, **kw)
        rows = [r for r in read_tsv(tmp_path / name / "qc.tsv") if r["status"] == "ok"]
        assert len(rows) >= 8, [(r["id"], r["status"], r["reason"]) for r in read_tsv(tmp_path / name / "qc.tsv")]
        bias[name] = float(np.median([_edge_bias_px(tmp_path / name, tmp_path / "batch.truth", r["id"]) for r in rows]))
        reg = read_yaml(tmp_path / name / "registration.yaml")
        if name == "half":
            x = [reg["print_template"][n] for n in PrintTemplate.NAMES]
            assert reg["half_cure"]["level"] == pytest.approx(half_cure_level(x, reg["half_cure"]["smoothing_px"]), abs=1e-3)
            assert reg["half_cure"]["level"] < 0.5 and reg["measurement"] is None
            # over full cure (a declared or reference dense level), not a large area's image, which cures below it
            assert half_cure_level(x, reg["half_cure"]["smoothing_px"], full=True) < reg["half_cure"]["level"]
            assert float(rows[0]["threshold"]) == pytest.approx(reg["half_cure"]["threshold"], rel=1e-3)
        else:
            assert reg["half_cure"] is None and reg["measurement"]["level"] == 0.5
    assert bias["plain"] <= -0.2, bias
    assert abs(bias["half"]) <= 0.5 * abs(bias["plain"]), bias


def _edge_bias_px(reg_dir, truth_dir, mid: str) -> float:
    """A registered print's area less the lab's true print's, per edge pixel of the true
    print (a signed mean edge displacement, px: > 0 too large)."""
    P, T = read_print(reg_dir / f"{mid}.png"), read_print(truth_dir / "prints" / f"{mid}.png")
    edges = np.count_nonzero(T[1:] != T[:-1]) + np.count_nonzero(T[:, 1:] != T[:, :-1])
    return float((np.count_nonzero(P) - np.count_nonzero(T)) / max(edges, 1))


def _edge_error_px(reg_dir, truth_dir, mid: str) -> float:
    """A registered print's area that differs from the lab's true print, per edge pixel of
    the true print (a mean edge displacement, px)."""
    P, T = read_print(reg_dir / f"{mid}.png"), read_print(truth_dir / "prints" / f"{mid}.png")
    edges = np.count_nonzero(T[1:] != T[:-1]) + np.count_nonzero(T[:, 1:] != T[:, :-1])
    return float(np.count_nonzero(P ^ T) / max(edges, 1))


def test_a_speck_as_small_as_the_least_print_images_dimmer_the_wider_the_blur():
    """``batch.speck_peak``: a disc of 30 px (radius 3.1 px) images at 1 - exp(-r^2 / 2 b^2)
    of its density at its centre, to the sampling's 2 per cent."""
    from unscatter.imaging.batch import speck_peak

    r2 = 30 / np.pi
    for b in (0.8, 1.5, 2.5, 3.7):
        assert speck_peak(30, b) == pytest.approx(1 - np.exp(-r2 / (2 * b * b)), abs=0.02), b
    assert speck_peak(30, 3.7) < 0.35 < 0.95 < speck_peak(30, 0.8)


def test_a_pitch_along_a_grating_that_cured_in_part_of_the_field_lays_the_same_mask_on_the_print():
    """A grating across the whole field of which only the middle cures, under a lamp hot
    spot; the batch's template has the hot spot a pitch to one side. The pose a pitch the
    other way then predicts the image best, and the evidence prefers it clearly to the true
    pose: only the template's field, placed with the pose, sets the two apart, and the two
    lay the same mask over every part that cured (``mask_apart`` near 0). A grating that
    cures to its mask's ends is told from its pose a pitch off by its end lines: they lay
    different masks over a share of the cured part some hundred times larger, and the
    evidence prefers the true pose. A pose two pixels along moves every edge: with the
    blur that ``choose_pose`` gives the comparison (a quarter of the poses' distance), the
    two lay different masks over a large share, where the blur kept for poses a pitch
    apart (2 px) would hide it."""
    from unscatter.imaging.batch import MARGIN, Settings, mask_apart, predicted_print
    from unscatter.imaging.pose import NUISANCE, Fit, evidence, predicted_image
    from unscatter.imaging.template import PrintTemplate

    tmpl = PrintTemplate(512, MARGIN)
    pitch = 24
    mask = np.zeros((512, 512), np.uint8)
    for c in range(16, 496, pitch):
        mask[40:472, c : c + 12] = 255
    m = tmpl.padded(mask)
    shape = tmpl.shape
    rng = np.random.default_rng(5)

    def z_apart(x_true, x_model, dose, shift=pitch, blur=2.0):
        q = np.array([dose] + [m_ if m_ is not None else 1.0 for _, m_, _ in NUISANCE[1:]], float)
        a = Fit(np.array([[1.0, 0, 0], [0, 1.0, 0]]), 100.0, 0.0, q, 1.0, 0.1, True, 0)
        b = Fit(np.array([[1.0, 0, -shift], [0, 1.0, 0]]), 100.0, 0.0, q, 1.0, 0.1, True, 0)
        img = predicted_image(a, predicted_print(tmpl, tmpl.exposure(m, x_true), x_true, a), shape)[0]
        img = (img + rng.normal(0.0, 1.0, shape)).astype(np.float32)
        B = tmpl.exposure(m, x_model)
        fa, fb = (a, predicted_print(tmpl, B, x_model, a)), (b, predicted_print(tmpl, B, x_model, b))
        share, moved = mask_apart(m, fa, fb, shape, blur=blur)
        assert abs(moved - shift) < 0.01, (moved, shift)  # the cured part moves by the shift
        return evidence(img, fa, fb), share

    x_true = np.array(PrintTemplate.START, float)
    x_true[13:17] = (1.0, 0.0, 0.0, 0.3)  # a hot spot of twice the field's dose in the middle
    x_model = x_true.copy()
    x_model[14] += pitch * float(tmpl.X[0, 1] - tmpl.X[0, 0])  # the template's, a pitch to the right
    z, apart = z_apart(x_true, x_model, 0.3)  # only where the hot spot doubles the dose does the grating cure
    assert z < -8, z  # the image prefers the pose a pitch off
    assert apart < 0.2 * Settings.field_set_share, apart  # the same mask over every part that cured
    flat = np.array(PrintTemplate.START, float)
    z, apart = z_apart(flat, flat, 1.0)  # cured to the mask's ends: they set the pose
    assert z > 8 and apart > 5 * Settings.field_set_share, (z, apart)
    _, hidden = z_apart(x_true, x_model, 0.3, shift=2)  # two pixels along, blurred as for a pitch
    _, apart = z_apart(x_true, x_model, 0.3, shift=2, blur=2 / 4)  # blurred as choose_pose does
    assert hidden < Settings.field_set_share < apart / 20, (hidden, apart)


def test_a_dot_that_only_one_pose_explains_sets_a_rival_aside_where_the_evidence_cannot():
    """Three dots of a dot array printed (its largest column): a rival a row along leaves
    one printed dot unexplained and predicts one where the image shows none. The blocks
    of ``evidence`` are too few to reach its bar (z < 4), but ``contradicted`` finds the
    dot; not where the two poses differ by less than its widening (2 px), not where the
    rival explains everything the best pose does (the rival is then the best pose), and
    not in an image whose noise reaches the print's level."""
    from unscatter.imaging.batch import MARGIN, Settings, predicted_print
    from unscatter.imaging.pose import NUISANCE, Fit, contradicted, evidence, predicted_image
    from unscatter.imaging.template import PrintTemplate

    tmpl = PrintTemplate(512, MARGIN)
    mask = np.zeros((512, 512), np.uint8)
    yy, xx = np.mgrid[:512, :512]
    spacing = 54
    for row in range(3):
        for col, r in enumerate((10, 5.5, 3.2)):
            cy, cx = 280 + row * spacing, 140 + col * spacing
            mask[(yy - cy) ** 2 + (xx - cx) ** 2 <= r * r] = 255
    m = tmpl.padded(mask)
    shape = tmpl.shape
    x = np.array(PrintTemplate.START, float)
    B = tmpl.exposure(m, x)
    # a dose at which only the largest dots cure
    q = np.array([0.6] + [m_ if m_ is not None else 1.0 for _, m_, _ in NUISANCE[1:]], float)
    rng = np.random.default_rng(11)

    def fit(dy, dx=0.0, sigma=1.0):
        f = Fit(np.array([[1.0, 0, dx], [0, 1.0, dy]]), 100.0, 0.0, q, sigma, 0.1, True, 0)
        return f, predicted_print(tmpl, B, x, f)

    a = fit(0.0)
    assert ndimage.label(a[1] >= 0.5 * a[1].max())[1] == 3  # the largest column of dots
    clean = predicted_image(a[0], a[1], shape)[0]
    img = (clean + rng.normal(0.0, 1.0, shape)).astype(np.float32)
    b = fit(-spacing)  # a row along
    assert 0 < evidence(img, a, b) < Settings.min_evidence  # the evidence cannot decide
    for_a, for_b = contradicted(img, a, b, Settings.min_print_px)
    assert for_a > 100  # a whole dot only ``a`` explains
    assert for_b == 0  # nothing that only the rival explains
    near = fit(0.0, 2.0)  # two pixels along: the widening forgives the edges that move
    assert contradicted(img, a, near, Settings.min_print_px)[0] == 0
    noisy = (clean + rng.normal(0.0, 40.0, shape)).astype(np.float32)
    a_noisy, b_noisy = fit(0.0, sigma=40.0), fit(-spacing, sigma=40.0)
    assert contradicted(noisy, (a_noisy[0], a[1]), (b_noisy[0], b[1]), Settings.min_print_px)[0] == 0
