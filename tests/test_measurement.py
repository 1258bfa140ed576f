"""The measurement stage of the calibration (unscatter.measurement): a print measured
through a blurring microscope is fitted without putting the blur into the printer's
scattering kernel."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from unscatter.calibration import calibrate
from unscatter.io import read_mask, read_yaml, write_png, write_tsv, write_yaml
from unscatter.masks import trial_masks
from unscatter.measurement import Measurement, MeasuredMasks, blur, density, measured
from unscatter.model import FixedMasks, default_params, eq1, masks_to_tensor


def test_without_blur_the_measured_print_is_eq1s():
    """No blur and no haze: density >= level exactly where the dose reaches T."""
    rng = np.random.default_rng(0)
    dose = torch.from_numpy(rng.uniform(0, 1, (2, 3, 40, 40)).astype(np.float32))
    theta = {"T": torch.tensor([0.45, 0.6])}
    for g in (0.3, 0.7):
        got = measured(dose, theta, Measurement(blur_px=0.0, smoothing_px=0.0, gel_share=g))
        want = dose >= theta["T"][:, None, None, None]
        assert (got != want).float().mean() < 1e-3  # only doses within rounding of T may differ
        rho = density(dose, theta["T"], g)
        assert float(rho.min()) >= 0 and float(rho.max()) < 1
        assert torch.all(rho[dose < g * theta["T"][:, None, None, None]] == 0)  # nothing below the gel dose


def test_blur_is_scipys_gaussian_and_differentiable():
    rng = np.random.default_rng(1)
    # 124 + the padding of a 1.5 px blur is 131, a prime: the FFT runs on a larger fast size
    for shape in ((50, 60), (124, 60)):
        img = rng.uniform(0, 1, (1, 2, *shape)).astype(np.float32)
        for s in (0.7, 1.5, 3.0):
            got = blur(torch.from_numpy(img), s).numpy()
            want = np.stack([ndimage.gaussian_filter(x, s, mode="constant", truncate=6.0) for x in img[0]])[None]
            assert got.shape == img.shape and np.abs(got - want).max() < 2e-3
    sig = torch.tensor([1.2], requires_grad=True)
    blur(torch.from_numpy(img), sig).sum().backward()
    assert sig.grad is not None and torch.isfinite(sig.grad).all()


def test_decimated_evaluator_samples_the_full_one():
    """``decimated(f)`` compares the same pixels as the full evaluator's every f-th."""
    masks = trial_masks(3, seed=2, size=128)
    m = eq1()
    p = default_params("eq1").with_values(sigma_px=3.0, T=0.5)
    sim = MeasuredMasks(FixedMasks(m, masks_to_tensor(np.stack(list(masks.values()))), support_px=48), Measurement(blur_px=1.5))
    theta = m.theta(p)
    full = sim.prints(theta)
    assert sim.decimated(2).prints(theta).shape == full[..., ::2, ::2].shape
    agree = (sim.decimated(2).prints(theta) == full[..., ::2, ::2]).float().mean()
    assert agree > 0.99  # the coarse grid is the search's approximation, close to the full one
    sub = sim.subset([2, 0])
    assert torch.equal(sub.prints(theta), full[:, [2, 0]])


@pytest.fixture(scope="module")
def blurred_lab(tmp_path_factory):
    """Prints of a small-kernel lab (paper physics) measured through a microscope blur
    comparable to its scattering: the lab's density, blurred (scipy), at half of saturation."""
    root = tmp_path_factory.mktemp("blurred")
    _, sigma_px = _measured_lab(root, 7.4, 1.6, size=192, seeds=(3, 7))
    return root, dict(sigma_px=sigma_px, T=0.5, blur_px=1.6)


FIT = dict(population=16, generations=8, folds=0, bootstrap=0, residual_maps=False, figure=False, progress=False, threads=1)


def _record(root, gel_share, **extra):
    """registration.yaml's measurement: the blur's start is off (0.8 px); the calibration fits it."""
    write_yaml(root / "registration.yaml", dict(measurement=dict(blur_px=0.8, smoothing_px=0.0, gel_share=gel_share, level=0.5,
                                                                 **extra)))


def test_fitting_through_the_measurement_recovers_sigma(blurred_lab, tmp_path):
    root, truth = blurred_lab
    try:
        _record(root, 0.6)  # the lab's gel share
        through = calibrate(root, tmp_path / "through", seed=0, measurement="registration", **FIT)
        _record(root, 0.45)  # a print template's estimate can be this far off
        off = calibrate(root, tmp_path / "off", seed=0, measurement="registration", **FIT)
        _record(root, 0.6, dense_level_from="reference")
        default = calibrate(root, tmp_path / "default", seed=0, **FIT)  # the default ("auto") ignores a record that
        # states no blur, for prints that resolve the scattering, whatever set the registration's dense level
    finally:
        (root / "registration.yaml").unlink()
    plain = calibrate(root, tmp_path / "plain", seed=0, measurement="registration", **FIT)  # no registration.yaml: none
    assert default.values == plain.values
    rel, rel_off, rel_plain = (p.values["sigma_px"] / truth["sigma_px"] - 1 for p in (through, off, plain))
    assert rel_plain > 0.1  # the bias: without the measurement the blur goes into sigma
    assert abs(rel) < 0.05, (rel, rel_plain)
    assert abs(through.values["T"] / truth["T"] - 1) < 0.05
    assert abs(rel_off) < 0.5 * rel_plain, (rel_off, rel_plain)  # a wrong gel share: less, but still an error
    meas = read_yaml(tmp_path / "through" / "params.yaml")["measurement"]
    assert abs(meas["blur_px"] - truth["blur_px"]) < 0.4
    assert meas["blur_fitted"] and len(meas["profile"]) >= 5
    assert read_yaml(tmp_path / "plain" / "params.yaml").get("measurement") is None
    # the calibrated printer model is Eq. 1's: params.yaml holds no measurement parameter
    assert set(through.values) == set(default_params("eq1").values)


def test_prints_without_a_registration_are_fitted_as_before(blurred_lab, tmp_path):
    root, _ = blurred_lab
    a = calibrate(root, tmp_path / "a", seed=1, measurement="registration", **FIT)
    b = calibrate(root, tmp_path / "b", seed=1, measurement="none", **FIT)
    assert a.values == b.values
    with pytest.raises(ValueError):
        calibrate(root, tmp_path / "c", seed=1, measurement="microscope", **FIT)


def test_a_stated_microscope_blur_is_held(blurred_lab, tmp_path):
    """batch.yaml's microscope_blur_um, recorded by the registration as declared_blur_px:
    the calibration through the measurement holds it (no profile); the template's own
    blur guess (0.8 px) is not used."""
    from unscatter.imaging.batch import measurement_record
    from unscatter.io import check_batch_meta

    root, truth = blurred_lab
    meta = check_batch_meta(dict(pixel_size_um=2.0, exposure_s=20, max_intensity_mw_cm2=20.0, material="ink",
                                 microscope_blur_um=3.2), "batch.yaml")
    rec = measurement_record(dict(blur=0.8, gel=0.3, k=0.2), [], 0.5, meta)
    assert rec["declared_blur_px"] == pytest.approx(1.6) and rec["blur_px"] == 0.8
    with pytest.raises(Exception, match="microscope_blur_um"):
        check_batch_meta(dict(pixel_size_um=2.0, exposure_s=20, max_intensity_mw_cm2=20.0, material="ink",
                              microscope_blur_um="wide"), "batch.yaml")
    try:
        write_yaml(root / "registration.yaml", dict(measurement=dict(blur_px=0.8, smoothing_px=0.0, gel_share=0.6,
                                                                     level=0.5, declared_blur_px=truth["blur_px"])))
        held = calibrate(root, tmp_path / "held", seed=0, measurement="registration", **FIT)
        default = calibrate(root, tmp_path / "default", seed=0, **FIT)  # resolved: the default fits as before
    finally:
        (root / "registration.yaml").unlink()
    meas = read_yaml(tmp_path / "held" / "params.yaml")["measurement"]
    assert meas["blur_px"] == pytest.approx(truth["blur_px"]) and not meas["blur_fitted"] and meas["profile"] == []
    assert abs(held.values["sigma_px"] / truth["sigma_px"] - 1) < 0.05, held.values
    assert abs(held.values["T"] / truth["T"] - 1) < 0.05
    assert set(held.values) == set(default_params("eq1").values)
    assert read_yaml(tmp_path / "default" / "params.yaml").get("measurement") is None


def _measured_lab(root, sigma_um, blur_px, n=16, size=160, seeds=(5, 9)):
    """Prints of a lab of paper physics (scattering ``sigma_um``) measured through a
    microscope blur (the density blurred, at half of saturation), written as a prints
    folder; returns the cure itself (id -> print) and the lab's sigma in px. ``seeds``:
    the trial masks' and the cells'."""
    from unscatter.lab import Printer, load_config

    over = {"printer": {"kernel": {"sigma_um": sigma_um, "heavy_tail": None, "anisotropy": {"ratio": 1.0, "angle_deg": 0.0}},
                        "illumination": {"quartic": 0.0, "hotspot": None}, "dose_gamma": 1.0, "edge_offset_um": 0.0,
                        "cure": {"threshold": 0.5, "gel_dose": 0.3}}}
    cfg = load_config(overrides=over)
    px = cfg["batch"]["pixel_size_um"]
    printer = Printer(cfg["printer"], size, px)
    rows, cured = [], {}
    for i, (mid, mask) in enumerate(trial_masks(n, seed=seeds[0], size=size).items()):
        rho = printer.crop(printer.density(mask, np.random.default_rng([seeds[1], i])))
        pr = ndimage.gaussian_filter(rho, blur_px) >= 0.5
        cured[mid] = rho >= 0.5
        write_png(root / "masks" / f"{mid}.png", mask)
        write_png(root / f"{mid}.png", pr)
        rows.append(dict(id=mid, status="ok" if pr.any() else "empty", reason="", mask=f"masks/{mid}.png"))
    write_tsv(root / "qc.tsv", rows, ["id", "status", "reason", "mask"])
    write_yaml(root / "batch.yaml", dict(pixel_size_um=px))
    return cured, sigma_um / px


def test_prints_that_do_not_resolve_the_scattering_are_fitted_through_the_stated_blur(tmp_path):
    """A printer of sigma 0.3 px seen through a microscope blur of 2 px: fitted as the cure,
    Eq. 1 takes the blur for scattering (sigma near 2 px) and predicts the cure itself
    worse; the default ('auto') sees that its sigma is within the stated blur, fits again
    through the measurement with that blur held, and says so in params.yaml."""
    from unscatter import metrics
    from unscatter.model import simulate

    root = tmp_path / "prints"
    cured, sigma_px = _measured_lab(root, 0.9, 2.0)
    write_yaml(root / "registration.yaml", dict(measurement=dict(blur_px=2.6, smoothing_px=0.5, gel_share=0.6, level=0.5,
                                                                 declared_blur_px=2.0)))
    plain = calibrate(root, tmp_path / "plain", seed=0, measurement="none", **FIT)
    auto = calibrate(root, tmp_path / "auto", seed=0, **FIT)
    assert plain.values["sigma_px"] > 1.5, plain.values  # the microscope's blur taken for scattering
    assert auto.values["sigma_px"] < 1.0, auto.values
    rec = read_yaml(tmp_path / "auto" / "params.yaml")
    assert rec["measurement"]["switched"]["first_sigma_px"] > 1.5 and not rec["measurement"]["blur_fitted"]
    assert rec["measurement"]["blur_px"] == pytest.approx(2.0)
    assert rec["validation"]["resolution"]["switched"] and any("do not resolve" in w for w in rec["warnings"])
    masks = np.stack([read_mask(root / "masks" / f"{mid}.png") for mid in cured])
    truth = [cured[mid] for mid in cured]
    iou_plain, iou_auto = (metrics.pooled_iou(simulate(p, masks), truth) for p in (plain, auto))
    assert iou_auto > iou_plain + 0.02, (iou_auto, iou_plain)


def test_the_diagnosis_fits_through_the_calibrations_measurement(blurred_lab, tmp_path):
    """A calibration through the measurement (the stated blur held): the diagnosis refits
    the printer through the same stage, so its base model keeps the printer's sigma
    (without it the refit puts the microscope's blur back into sigma), and model.yaml
    records the stage and holds the printer's parameters only."""
    from unscatter.diagnosis import diagnose

    root, truth = blurred_lab
    try:
        write_yaml(root / "registration.yaml", dict(measurement=dict(blur_px=0.8, smoothing_px=0.0, gel_share=0.6,
                                                                     level=0.5, declared_blur_px=truth["blur_px"])))
        calibrate(root, tmp_path / "cal", seed=0, measurement="registration", **FIT)
        r = diagnose(root, tmp_path / "cal" / "params.yaml", tmp_path / "diag", quick=True, candidates=["edge_offset"],
                     progress=False, figures=False, workers=1, seed=0)
    finally:
        (root / "registration.yaml").unlink()
    model = read_yaml(tmp_path / "diag" / "model.yaml")
    sigma = model["parameters"]["sigma_px"]["value"]
    assert abs(sigma / truth["sigma_px"] - 1) < 0.1, (sigma, truth["sigma_px"], r["effects"])
    assert model["diagnosis"]["measurement"]["blur_px"] == pytest.approx(truth["blur_px"])
    assert "meas_blur_px" not in model["parameters"]
