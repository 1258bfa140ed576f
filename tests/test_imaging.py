"""Registration and thresholding against the virtual lab's truth."""

import logging
import shutil

import numpy as np
import pytest

from unscatter.imaging import RegistrationError, register_batch, transform_rms_px
from unscatter.io import read_print, read_tsv, read_yaml
from unscatter.lab import print_batch
from unscatter.metrics import iou


def _truth_matrix(row):
    return np.array([[float(row[f"m{a}{b}"]) for b in range(3)] for a in range(2)])


def _ok_pose_errors(reg_dir, truth_dir) -> dict:
    """id -> pose error (mask px, RMS over the field) of each `ok` print against the lab's truth."""
    qc = {r["id"]: r for r in read_tsv(reg_dir / "qc.tsv")}
    return {t["id"]: transform_rms_px(_truth_matrix(qc[t["id"]]), _truth_matrix(t), 512)
            for t in read_tsv(truth_dir / "transforms.tsv") if qc[t["id"]]["status"] == "ok"}


def _evaluate(reg_dir, truth_dir, may_fail=()):
    qc = {r["id"]: r for r in read_tsv(reg_dir / "qc.tsv")}
    rms, ious = list(_ok_pose_errors(reg_dir, truth_dir).values()), []
    for t in read_tsv(truth_dir / "transforms.tsv"):
        q = qc[t["id"]]
        truth = read_print(truth_dir / "prints" / f"{t['id']}.png")
        if truth.any() and not (t["id"] in may_fail and q["status"] == "failed"):
            assert q["status"] == "ok", f"{t['id']}: {q['status']} {q['reason']}"
            ious.append(iou(read_print(reg_dir / f"{t['id']}.png"), truth))
    return np.array(rms), np.array(ious)


# The four corners of the microscope's range (item 4 of the issue): rotation +-10 deg,
# scale 0.8 and 1.25, shift up to 15 % of the field, vignetting up to 30 %.
EXTREMES = {
    "small_rotated_shifted": dict(scale=[0.8, 0.82], rotation_deg=10.0, shift_frac=0.15, vignetting=[0.25, 0.3], image_size=[720, 720]),
    "large": dict(scale=[1.22, 1.25], rotation_deg=10.0, shift_frac=0.15, vignetting=[0.25, 0.3], image_size=[960, 960]),
}


@pytest.mark.parametrize("case", sorted(EXTREMES))
def test_registration_accuracy_over_the_microscope_range(tmp_path, trial_dir, case):
    batch = tmp_path / "batch"
    rows = print_batch(trial_dir, batch, overrides={"microscope": EXTREMES[case]}, seed=3, progress=False)
    lo, hi = EXTREMES[case]["scale"]
    assert all(lo <= r["scale"] <= hi for r in rows)
    register_batch(batch, tmp_path / "reg", progress=False)
    rms, ious = _evaluate(tmp_path / "reg", tmp_path / "batch.truth")
    # issue 2: 0.5 px RMS over the mask field, IoU 0.97 against the noise-free print
    assert rms.mean() <= 0.5, rms
    assert ious.mean() >= 0.97, ious


def test_a_zoom_whose_prints_agree_by_chance_is_not_one_magnification_at_a_dose_gamma(tmp_path, trial_dir):
    """A batch whose prints agree on a scale by chance is not held to it (``batch_scale``).
    Our own lab's nine trial prints at the large end of the microscope's range (a zoom
    of 1.22 to 1.25 set per image), printed with a dose gamma of 1.15 (the dose of a grey
    level g, 0 to 255, is (g / 255)^1.15; the randomized labs draw 0.9 to 1.15). Seven
    of them fix their own scale, and by chance four of those agree within 0.2 % (a robust
    spread of 0.23 %): the batch took that for one magnification and held every print to
    it, and three prints were `ok` 1.70, 2.54 and 3.16 px off, QC blind to it (one of the
    seven is 1.20 % off their median, which no refocusing does). Every `ok` print within
    1 px, no one magnification held (0.37 px at most when measured, one failed)."""
    batch = tmp_path / "batch"
    overrides = {"microscope": EXTREMES["large"], "printer": {"dose_gamma": 1.15}}
    print_batch(trial_dir, batch, overrides=overrides, seed=3, progress=False)
    register_batch(batch, tmp_path / "reg", progress=False, skip_failed=True)
    assert read_yaml(tmp_path / "reg" / "registration.yaml")["one_magnification"] is None
    err = _ok_pose_errors(tmp_path / "reg", tmp_path / "batch.truth")
    assert len(err) >= 8 and max(err.values()) <= 1.0, err


def test_round_trip_empty_and_faint_prints(lab_batch, tmp_path):
    out = tmp_path / "reg"
    rows = {r["id"]: r for r in register_batch(lab_batch, out, progress=False)}
    truth_dir = lab_batch.with_name(lab_batch.name + ".truth")
    # the under-dosed square: background only, reported as an empty print, all void
    assert rows["underdosed"]["status"] == "empty"
    assert not read_print(out / "underdosed.png").any()
    # the faint block gels (visible fluorescence) but stays below the print level: the batch's
    # one threshold keeps it void, where a per-image threshold would call it solid
    faint = read_print(out / "faint.png")
    truth = read_print(truth_dir / "prints" / "faint.png")
    assert not faint[110:390, 130:290].any() and not truth[110:390, 130:290].any()
    density = np.load(truth_dir / "density" / "faint.npy")
    assert density[110:390, 130:290].mean() > 0.15  # there is polymer to see
    assert iou(faint, truth) > 0.9
    # outputs of the contract
    qc = read_tsv(out / "qc.tsv")
    assert {r["status"] for r in qc} <= {"ok", "empty"}
    assert all((out / "overlays" / f"{r['id']}.png").is_file() for r in qc)
    rms, ious = _evaluate(out, truth_dir)
    assert rms.mean() <= 0.5 and ious.mean() >= 0.97
    # what a calibration needs to fit through this measurement (unscatter.measurement)
    meas = read_yaml(out / "registration.yaml")["measurement"]
    assert meas["level"] == 0.5 and 0.5 <= meas["smoothing_px"] <= 1.0 and 0 < meas["gel_share"] < 1
    assert 0.3 <= meas["blur_px"] <= 4.0


def test_a_batch_registers_alike_at_any_thread_count(lab_batch, tmp_path, caplog):
    """One thread or two, the same poses, verdicts and prints, to the last digit written:
    OpenBLAS and OpenCV run on one thread either way (``batch.one_library_thread``).
    With BLAS at two threads for one registration thread, a batch's template fit came to
    another optimum, and a cut-off grating was `ok` a pitch off that two threads placed
    right (seed 1985358721's lab 6); with OpenCV's own threads, two runs at two threads
    could differ in the last digits. At two, the pose searches run in two forked
    processes (``imaging.parallel``), which must not have fallen back to threads."""
    with caplog.at_level(logging.WARNING, logger="unscatter.imaging.parallel"):
        for n in (1, 2):
            register_batch(lab_batch, tmp_path / f"reg{n}", progress=False, skip_failed=True, threads=n)
    assert "worker processes" not in caplog.text
    one, two = tmp_path / "reg1", tmp_path / "reg2"
    assert (one / "qc.tsv").read_bytes() == (two / "qc.tsv").read_bytes()
    assert read_yaml(one / "registration.yaml") == read_yaml(two / "registration.yaml")
    ids = [r["id"] for r in read_tsv(one / "qc.tsv") if r["status"] != "failed"]
    assert ids and all(np.array_equal(read_print(one / f"{i}.png"), read_print(two / f"{i}.png")) for i in ids)


def test_print_that_fails_qc_is_never_passed_on(lab_batch, tmp_path):
    batch = tmp_path / "batch"
    shutil.copytree(lab_batch, batch)
    # the image of a rectangles mask handed in for a circles mask: registration cannot agree
    shutil.copyfile(batch / "images" / "trial_001.tif", batch / "images" / "trial_002.tif")
    with pytest.raises(RegistrationError, match="trial_002"):
        register_batch(batch, tmp_path / "reg", progress=False)
    rows = {r["id"]: r for r in register_batch(batch, tmp_path / "reg2", skip_failed=True, progress=False)}
    assert rows["trial_002"]["status"] == "failed" and rows["trial_002"]["reason"]
    assert not (tmp_path / "reg2" / "trial_002.png").exists()
    assert (tmp_path / "reg2" / "trial_001.png").exists()


def test_affine_mode_registers_as_well(lab_batch, tmp_path):
    register_batch(lab_batch, tmp_path / "reg", mode="affine", skip_failed=True, progress=False)
    # an affine pose has a scale along each axis: a print may have them from its features'
    # sizes and fail for that, for no other reason, where it is the faint print (one block
    # that prints) or where its pose is in fact well off (trial_006's is 1.48 px, at a size
    # spread of 1.13 to 1.65 px as its grey features' edges count for more or less); the
    # faint print may instead fail on the kernel's shape, which with its scales free
    # (pose.kernel_spread) moves it 0.44 px besides its size spread of 1.48 px (0.78 px off)
    truth_dir = lab_batch.with_name(lab_batch.name + ".truth")
    truth = {t["id"]: t for t in read_tsv(truth_dir / "transforms.tsv")}
    failed = [r for r in read_tsv(tmp_path / "reg" / "qc.tsv") if r["status"] == "failed"]
    assert all("size of a feature" in r["reason"] or (r["id"] == "faint" and "shape of the scatter kernel" in r["reason"])
               for r in failed), failed
    for r in failed:
        assert r["id"] == "faint" or transform_rms_px(_truth_matrix(r), _truth_matrix(truth[r["id"]]), 512) > 1.0, r
    rms, ious = _evaluate(tmp_path / "reg", truth_dir, may_fail=tuple(r["id"] for r in failed))
    assert rms.mean() <= 0.6 and ious.mean() >= 0.97


def test_stain_field_measures_an_uneven_stain_from_the_interiors_and_not_from_edges_or_background():
    """A print whose polymer is brighter in one part (a smooth stain, 15 % across it) under
    a fit with one gain: the field from its interiors matches the stain there within 3 %,
    and its spread says so; the same print evenly stained gives a spread under 1 %, and a
    print whose edges are 2 px off the prediction (a pose off) is not read as a stain."""
    import cv2
    from unscatter.imaging.flatfield import stain_field, stain_ratio

    rng = np.random.default_rng(5)
    H = W = 400
    m = np.zeros((H, W), np.float32)
    for r0 in range(40, 360, 80):  # blocks 50 px wide, 30 px apart
        for c0 in range(40, 360, 80):
            m[r0:r0 + 50, c0:c0 + 50] = 1
    T = cv2.GaussianBlur(m, (0, 0), 2.0)
    yy, xx = np.mgrid[0:H, 0:W] / H
    stain = (1 + 0.2 * np.sin(2 * np.pi * (xx + 0.5 * yy))).astype(np.float32)
    offset, gain = 0.1, 3.0
    noise = rng.normal(0, 0.05, (H, W)).astype(np.float32)
    img = offset + gain * stain * T + noise
    f, sd = stain_field(*stain_ratio(img, offset + gain * T, offset, gain), 16.0)
    inner = cv2.erode((T >= 0.85).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    rel = stain / np.median(stain[inner])
    assert np.max(np.abs(f[inner] - rel[inner])) < 0.03
    assert 0.08 < sd < 0.2
    assert 0.7 < f.min() and f.max() < 1.4  # no blow-up where the interiors are few or to one side (the corners)
    _, sd_even = stain_field(*stain_ratio(offset + gain * T + noise, offset + gain * T, offset, gain), 16.0)
    assert sd_even < 0.01
    shifted = offset + gain * np.roll(T, 2, axis=1) + noise  # the edges 2 px off, the brightness even
    _, sd_off = stain_field(*stain_ratio(shifted, offset + gain * T, offset, gain), 16.0)
    assert sd_off < 0.02


def test_the_template_numbers_its_fit_left_on_a_bound_are_named():
    """``PrintTemplate.on_bounds``: the numbers a feature's cure rests on that sit on a bound
    of the fit (the empty cure test then also takes them back toward where the fit began,
    ``toward_start``); a share of nothing (no gel dose, no tail, no haze) is a value, and
    the width of a term with no share is not counted."""
    from unscatter.imaging.template import PrintTemplate as P

    x = np.array(P.START, float)
    assert P.on_bounds(x) == []
    y = x.copy()
    y[P.NAMES.index("k")], y[P.NAMES.index("tail_sigma")] = 3.0, 100.0
    assert P.on_bounds(y) == ["k", "tail_sigma"]
    y[P.NAMES.index("k")] = 2.99
    assert P.on_bounds(y) == ["tail_sigma"]
    y[P.NAMES.index("tail")] = 0.0  # no tail: its width is no number of the template
    assert P.on_bounds(y) == []
    y[P.NAMES.index("sigma")] = 0.3
    y[P.NAMES.index("gel")] = 0.0
    assert P.on_bounds(y) == ["sigma"]
    y[P.NAMES.index("aniso_c")], y[P.NAMES.index("aniso_s")] = 0.72, 0.96  # |L| = 1.2, the ellipse's bound
    assert P.on_bounds(y) == ["sigma", "aniso"]
    assert P.on_bounds(y, names=("k",)) == []
    z = P.toward_start(y, ["sigma", "aniso"], 0.5)  # halfway back to where the fit began, the ellipse halfway to round
    assert z[P.NAMES.index("sigma")] == 0.5 * (0.3 + P.START[P.NAMES.index("sigma")])
    assert np.allclose(z[[P.NAMES.index("aniso_c"), P.NAMES.index("aniso_s")]], [0.36, 0.48])
    assert np.array_equal(np.delete(z, [0, 17, 18]), np.delete(y, [0, 17, 18]))


def test_the_template_s_kept_field_and_kernel_are_those_of_its_numbers_and_grid():
    """The lamp's field and the elliptical core's transfer function are kept for the last
    numbers: what comes back must be what the numbers give on the template's own grid
    (another field, a crop of the grid, another kernel), never a kept one of other numbers."""
    from unscatter.imaging.template import PrintTemplate, _ellipse_transfer, core_blur

    tmpl = PrintTemplate(64, 8, factor=2)
    x = np.array(PrintTemplate.START, float)
    x[3:8] = (0.1, -0.05, 0.02, 0.0, -0.03)
    X, Y = tmpl.X, tmpl.Y
    f1 = tmpl.field(x)
    assert np.allclose(f1, 1 + 0.1 * X - 0.05 * Y + 0.02 * X * X - 0.03 * Y * Y)
    x2 = x.copy()
    x2[13:17] = (0.3, 0.2, -0.1, 0.4)
    f2 = tmpl.field(x2)
    assert np.allclose(f2, f1 + 0.3 * np.exp(-((X - 0.2) ** 2 + (Y + 0.1) ** 2) / (2 * 0.4**2)), atol=1e-6)
    assert tmpl.field(x) is not f2 and np.array_equal(tmpl.field(x), f1)
    sub = tmpl.crop((4, 20), (6, 30))
    assert sub.field(x).shape == (16, 24) and np.array_equal(sub.field(x), f1[4:20, 6:30])
    with pytest.raises(ValueError):
        tmpl.field(x)[0, 0] = 5.0  # read-only: a caller cannot change the kept one
    rng = np.random.default_rng(0)
    e = rng.random((40, 48)).astype(np.float32)
    first = core_blur(e, 2.0, 0.3, 0.1)
    other = core_blur(e, 2.0, 0.1, 0.3)
    _ellipse_transfer.cache_clear()
    assert np.array_equal(core_blur(e, 2.0, 0.3, 0.1), first) and not np.allclose(first, other)
    assert np.isclose(first.sum(), e.sum(), rtol=1e-4)  # a blur keeps the dose


def test_a_fitted_pose_survives_pickle_and_copy():
    """A Fit names its nuisance numbers through ``__getattr__``; pickle and copy look up
    methods on an instance whose fields are not back yet, which must not recurse."""
    import copy
    import pickle

    from unscatter.imaging.pose import Fit

    f = Fit(M=np.eye(2, 3), gain=1.0, offset=0.0, q=np.array([1.1, 2.0, 0.0, 0.0, -0.5]), sigma=0.1, pose_sd=0.2,
            converged=True, iterations=3)
    for g in (pickle.loads(pickle.dumps(f)), copy.deepcopy(f)):
        assert g.dose == 1.1 and g.edge == -0.5 and np.array_equal(g.M, f.M)
    with pytest.raises(AttributeError):
        f.edge_c2  # not among its numbers
