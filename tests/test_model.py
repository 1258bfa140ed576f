"""The printer simulator (Guan et al. 2022, Eq. 1): convolution, threshold, gradients,
batching, the fast fixed-masks evaluator, parameters on disk, and its extension points."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from unscatter.io import InputError, read_yaml, write_yaml
from unscatter.model import (
    FieldTerm,
    FixedMasks,
    GaussianKernel,
    LinearDose,
    ParamSpec,
    PrinterModel,
    QuadraticField,
    Threshold,
    default_params,
    design_coords,
    eq1,
    load_params,
    masks_to_tensor,
    save_params,
    simulate,
)

CPU = torch.device("cpu")
TRUTHY = dict(c0=1.0, c1=-0.07, c2=-0.05, c3=0.03, c4=-0.02, sigma_px=4.05, T=0.5)


def _theta(model, **over):
    return model.theta({**TRUTHY, **over}, CPU)


def _field(shape, v):
    H, W = shape
    X = design_coords(W).double().numpy()[None, :]
    Y = design_coords(H).double().numpy()[:, None]
    return np.maximum(v["c0"] + v["c1"] * X**2 + v["c2"] * Y**2 + v["c3"] * X + v["c4"] * Y, 0)


@pytest.fixture
def border_mask():
    m = np.zeros((96, 120), np.uint8)
    m[:, :12] = 255  # touches the left border over its whole height
    m[30:50, 60:90] = 140
    m[0:8, 100:120] = 255  # and the top-right corner
    return m


@pytest.mark.parametrize("sigma", [0.3, 0.8, 2.0, 6.5])
def test_fft_convolution_equals_spatial_gaussian_with_zero_padding(border_mask, sigma):
    m = eq1()
    v = dict(TRUTHY, sigma_px=sigma)
    dose = m.dose(masks_to_tensor(border_mask, CPU), _theta(m, sigma_px=sigma))[0, 0].double().numpy()
    exposure = _field(border_mask.shape, v) * border_mask / 255.0
    ref = ndimage.gaussian_filter(exposure, sigma, mode="constant", cval=0.0, truncate=12)
    np.testing.assert_allclose(dose, ref, atol=2e-6)


def test_no_wrap_around(border_mask):
    m = eq1()
    mask = np.zeros_like(border_mask)
    mask[:, :4] = 255  # light only along the left border
    dose = m.dose(masks_to_tensor(mask, CPU), _theta(m, sigma_px=8.0))[0, 0].numpy()
    assert dose[:, 0].min() > 0.05
    # a periodic convolution would put ~ the same light on the right border
    assert dose[:, -1].max() < 1e-6
    assert dose[:, -20:].max() < 1e-6


def test_model_matches_the_lab_printer_without_its_extra_effects():
    from unscatter.lab import Printer, load_config
    from unscatter.masks import trial_masks

    cfg = load_config(overrides={"printer": {
        "kernel": {"heavy_tail": None, "anisotropy": {"ratio": 1.0, "angle_deg": 0.0}},
        "illumination": {"quartic": 0.0, "hotspot": None}, "dose_gamma": 1.0, "edge_offset_um": 0.0,
        "cells": {"dose_noise": 0.0, "print_to_print": 0.0}}})
    pc = cfg["printer"]
    size = 128
    printer = Printer(pc, size, cfg["batch"]["pixel_size_um"])
    il = pc["illumination"]
    v = dict(c0=il["c0"], c1=il["cx2"], c2=il["cy2"], c3=il["cx"], c4=il["cy"],
             sigma_px=pc["kernel"]["sigma_um"] / cfg["batch"]["pixel_size_um"], T=pc["cure"]["threshold"])
    m = eq1()
    for mask in list(trial_masks(3, seed=5, size=size).values()):
        lab = printer.crop(printer.dose(mask, np.random.default_rng(0)))
        ours = m.dose(masks_to_tensor(mask, CPU), m.theta(v, CPU))[0, 0].numpy()
        np.testing.assert_allclose(ours, lab, atol=2e-6)


def test_coordinates_are_minus_one_to_one_over_pixel_centres():
    x = design_coords(512).double()
    assert x[0] == -1 and x[-1] == 1
    # a coarse grid's pixel centres are the means of the design pixels it covers
    np.testing.assert_allclose(design_coords(128, scale=4.0).numpy(), x.reshape(128, 4).mean(1).numpy(), atol=1e-6)
    m = eq1()
    X, Y = m.coords(3, 5)
    f = m.field(X, Y, m.theta(dict(TRUTHY, c1=0.0, c2=0.0, c3=0.1, c4=0.0), CPU))[0]
    assert torch.allclose(f[:, 0], torch.tensor(0.9)) and torch.allclose(f[:, -1], torch.tensor(1.1))  # X along columns


def test_relu_zeroes_negative_field():
    m = eq1()
    mask = np.full((32, 32), 255, np.uint8)
    th = _theta(m, c1=-1.5, sigma_px=0.25)
    e = m.exposure(masks_to_tensor(mask, CPU), th)[0, 0]
    assert e.min() == 0 and (e == 0).any()


def test_smooth_threshold_converges_to_hard(border_mask):
    m = eq1()
    M = masks_to_tensor(border_mask, CPU)
    th = _theta(m, sigma_px=3.0, T=0.3)
    hard = m.prints(M, th).float()
    errs = [(m.prints(M, th, temperature=t) - hard).abs().mean().item() for t in (0.3, 0.1, 0.03, 0.01, 1e-3, 1e-5)]
    assert all(a > b for a, b in zip(errs, errs[1:]))
    assert errs[-1] < 1e-3
    with pytest.raises(ValueError):
        m.prints(M, th, temperature=0.0)


def test_gradients_flow_to_mask_and_parameters(border_mask):
    m = eq1()
    M = masks_to_tensor(border_mask, CPU).requires_grad_(True)
    raw = {k: torch.tensor([v], requires_grad=True) for k, v in dict(TRUTHY, T=0.3, sigma_px=3.0).items()}
    p = m.prints(M, m.theta(raw, CPU), temperature=0.1)
    target = torch.zeros_like(p)
    ((p - target) ** 2).mean().backward()
    assert M.grad is not None and torch.isfinite(M.grad).all() and M.grad.abs().sum() > 0
    for k, t in raw.items():
        assert t.grad is not None and torch.isfinite(t.grad).all(), k
        assert t.grad.abs().item() > 0, k


def test_gradient_in_sigma_matches_finite_difference():
    m = eq1()
    mask = np.zeros((40, 40), np.uint8)
    mask[10:30, 12:25] = 255
    M = masks_to_tensor(mask, CPU).double()

    def loss(s):
        th = {k: torch.tensor([v], dtype=torch.float64) for k, v in TRUTHY.items()}
        th["sigma_px"] = s
        return m.dose(M, th)[0, 0, 5:35, 5:35].pow(2).sum()

    s = torch.tensor([2.3], dtype=torch.float64, requires_grad=True)
    loss(s).backward()
    h = 1e-3
    fd = (loss(torch.tensor([2.3 + h], dtype=torch.float64)) - loss(torch.tensor([2.3 - h], dtype=torch.float64))) / (2 * h)
    # the model runs in float32 internally: agree to float32 precision
    assert abs(s.grad.item() - fd.item()) <= 2e-3 * abs(fd.item())


def test_batched_equals_one_by_one():
    from unscatter.masks import trial_masks

    m = eq1()
    masks = np.stack(list(trial_masks(4, seed=3, size=96).values()))
    vals = dict(c0=[1.0, 1.0, 0.9], c1=[-0.07, 0.1, 0.0], c2=[-0.05, 0.0, 0.2], c3=[0.03, -0.1, 0.0], c4=[-0.02, 0.0, 0.05],
                sigma_px=[1.5, 4.0, 2.5], T=[0.5, 0.4, 0.6])
    M = masks_to_tensor(masks, CPU)
    batched = m.dose(M, m.theta(vals, CPU))
    for p in range(3):
        th = m.theta({k: v[p] for k, v in vals.items()}, CPU)
        for b in range(4):
            one = m.dose(M[b : b + 1], th)[0, 0]
            torch.testing.assert_close(batched[p, b], one, atol=2e-6, rtol=0)


def test_fixed_masks_evaluator_equals_model():
    from unscatter.masks import trial_masks

    m = eq1()
    masks = np.stack(list(trial_masks(3, seed=1, size=128).values()))
    M = masks_to_tensor(masks, CPU)
    # the second set drives the field negative in a corner (the ReLU acts: direct path)
    vals = dict(c0=[1.0, 1.0], c1=[-0.07, -0.9], c2=[-0.05, -0.3], c3=[0.03, 0.0], c4=[-0.02, 0.0], sigma_px=[4.0, 3.0], T=[0.5, 0.4])
    th = m.theta(vals, CPU)
    fm = FixedMasks(m, M, support_px=24.0)
    assert fm.fast
    ref = m.dose(M, th)
    torch.testing.assert_close(fm.dose(th), ref, atol=2e-6, rtol=0)
    assert torch.equal(fm.subset([2, 0]).prints(th), fm.prints(th)[:, [2, 0]])
    # every 2nd pixel from the low-frequency band: exact for a kernel this wide
    assert fm.dropped(th, 2) < 1e-4
    torch.testing.assert_close(fm.decimated(2).dose(th), ref[..., ::2, ::2], atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="wider than"):
        fm.dose(m.theta(dict(TRUTHY, sigma_px=9.0), CPU))


def test_evaluators_sharing_a_cache_share_decimations_and_subsets_and_compute_the_same():
    """Evaluators of the same masks that share a spectra cache (the diagnosis's candidates
    and folds) take the decimated and subset spectra from it, keyed by how they derive,
    and compute what an evaluator without a cache computes; another subset, another
    factor or another basis is not confused with them."""
    from unscatter.masks import trial_masks
    from unscatter.model import extend_params, get_model

    m = eq1()
    M = masks_to_tensor(np.stack(list(trial_masks(4, seed=2, size=96).values())), CPU)
    th = m.theta(TRUTHY, CPU)
    cache: dict = {}
    a, b, plain = FixedMasks(m, M, 24.0, cache=cache), FixedMasks(m, M, 24.0, cache=cache), FixedMasks(m, M, 24.0)
    assert a.spectra is b.spectra
    assert a.decimated(2).spectra is b.decimated(2).spectra
    assert a.decimated(2).subset([3, 1]).spectra is b.decimated(2).subset([3, 1]).spectra
    assert a.decimated(2).subset([1, 3]).spectra is not a.decimated(2).subset([3, 1]).spectra
    assert a.decimated(4).spectra.shape != a.decimated(2).spectra.shape
    for f, idx in ((2, [3, 1]), (2, [1, 3]), (4, [0, 2, 3]), (1, [2])):
        got = (b.decimated(f) if f > 1 else b).subset(idx).dose(th)
        torch.testing.assert_close(got, (plain.decimated(f) if f > 1 else plain).subset(idx).dose(th), atol=0, rtol=0)
    assert torch.equal(b.subset([1, 2]).decimated(2).dose(th), plain.subset([1, 2]).decimated(2).dose(th))
    # full-resolution subsets (used once: predictions) are not kept, nor anything derived from them
    kept = len(cache)
    b.subset([0, 1]).decimated(2)
    assert len(cache) == kept
    # another padding is another grid: its own spectra
    assert FixedMasks(m, M, 40.0, cache=cache).spectra.shape != a.spectra.shape and len(cache) == kept + 1
    # a model with other field terms has other spectra: its own entries in the same cache
    tilted = get_model(extend_params(default_params("eq1"), ["illumination_field"]).model)
    c = FixedMasks(tilted, M, 24.0, cache=cache)
    assert c.spectra.shape[0] != a.spectra.shape[0] and c.decimated(2).spectra.shape[0] != a.decimated(2).spectra.shape[0]


def test_params_round_trip(tmp_path):
    p = default_params(pixel_size_um=2.96).with_values(c1=-0.07, c3=0.03, sigma_px=4.1, T=0.48)
    assert p.fixed == ("c0",) and "c0" not in p.free and p.values["c0"] == 1.0
    p.info["parameter_extras"] = {"T": {"std": 0.01, "q05": 0.47, "q95": 0.49}}
    save_params(tmp_path / "params.yaml", p, objective=dict(value=0.01))
    d = read_yaml(tmp_path / "params.yaml")
    assert "c0 is fixed to 1" in d["gauge"] and "Eq. 1" in d["equation"]
    assert d["parameters"]["c0"]["fixed"] is True and d["parameters"]["sigma_px"]["fixed"] is False
    assert d["derived"]["sigma_um"] == pytest.approx(4.1 * 2.96)
    q = load_params(tmp_path / "params.yaml")
    assert q.values == pytest.approx(p.values) and q.fixed == p.fixed and q.bounds == p.bounds
    assert q.pixel_size_um == 2.96 and q.info["objective"]["value"] == 0.01
    assert d["parameters"]["T"]["std"] == 0.01 and q.info["parameter_extras"] == p.info["parameter_extras"]
    free = default_params(free_c0=True)
    save_params(tmp_path / "free.yaml", free)
    r = load_params(tmp_path / "free.yaml")
    assert r.fixed == () and "c0" in r.free and "free" in read_yaml(tmp_path / "free.yaml")["gauge"]


def test_load_params_rejects_bad_files(tmp_path):
    good = default_params().to_dict()
    bad = dict(good, parameters={k: v for k, v in good["parameters"].items() if k != "T"})
    write_yaml(tmp_path / "a.yaml", bad)
    with pytest.raises(InputError, match="'T' missing"):
        load_params(tmp_path / "a.yaml")
    write_yaml(tmp_path / "b.yaml", dict(good, model="nope"))
    with pytest.raises(InputError, match="unknown model"):
        load_params(tmp_path / "b.yaml")
    with pytest.raises(InputError, match="does not exist"):
        load_params(tmp_path / "missing.yaml")
    with pytest.raises(ValueError, match="unknown parameter 'sigma'"):
        default_params(bounds={"sigma": (1, 2)})
    with pytest.raises(ValueError, match="lower < upper"):
        default_params(bounds={"sigma_px": (2, 1)})


def test_a_model_folder_loads_its_params_file(tmp_path):
    """A calibration folder (params.yaml) and a diagnosis folder (model.yaml) both name a
    model; a folder with neither is an error that names it."""
    p = default_params(pixel_size_um=2.96).with_values(sigma_px=4.1)
    (tmp_path / "cal").mkdir()
    save_params(tmp_path / "cal" / "params.yaml", p)
    (tmp_path / "diag").mkdir()
    save_params(tmp_path / "diag" / "model.yaml", p.with_values(sigma_px=5.2), effects=[])
    assert load_params(tmp_path / "cal").values["sigma_px"] == pytest.approx(4.1)
    assert load_params(tmp_path / "diag").values["sigma_px"] == pytest.approx(5.2)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="params.yaml or model.yaml") as e:
        load_params(tmp_path / "empty")
    assert "empty" in str(e.value)


def test_simulate_returns_binary_prints(tmp_path, border_mask):
    p = default_params().with_values(sigma_px=2.0, T=0.5)
    out = simulate(p, border_mask, device=CPU)
    assert out.dtype == bool and out.shape == border_mask.shape
    assert out[20:80, 2:9].all() and not out[20:, -3:].any()
    many = simulate(p, [border_mask, 255 - border_mask], device=CPU)
    assert many.shape == (2,) + border_mask.shape and np.array_equal(many[0], out)
    save_params(tmp_path / "p.yaml", p)
    assert np.array_equal(simulate(tmp_path / "p.yaml", border_mask, device=CPU), out)
    grey = simulate(p, border_mask, device=CPU, temperature=0.05)
    assert grey.dtype == np.float32 and 0 <= grey.min() and grey.max() <= 1


# ------------------------------------------------------------ extension points


class QuarticField(FieldTerm):
    """An illumination term beyond Eq. 1's quadratic: q (X^2 + Y^2)^2."""

    name = "quartic_field"
    params = (ParamSpec("q", 0.0, (-0.2, 0.2), "relative dose", "quartic fall-off"),)

    def basis(self, X, Y):
        return {"q": ((X**2 + Y**2) ** 2).expand(Y.shape[0], X.shape[1])}

    def field(self, X, Y, theta):
        return theta["q"][:, None, None] * self.basis(X, Y)["q"]


class WideGaussian(GaussianKernel):
    """A second, wider kernel term with its own weight (heavy-tail stand-in)."""

    name = "wide_gaussian"
    params = (ParamSpec("sigma2_px", 10.0, (2.0, 30.0), "design pixels", "wide term"),
              ParamSpec("w2", 0.2, (0.0, 1.0), "", "weight of the wide term"))

    def weight(self, theta):
        return theta["w2"]

    def transfer(self, fy, fx, theta):
        return super().transfer(fy, fx, {"sigma_px": theta["sigma2_px"]})

    def support_px(self, values):
        return 4.0 * float(values["sigma2_px"])


def test_components_compose_without_copying_the_model(border_mask):
    m = PrinterModel([QuadraticField(), QuarticField(), LinearDose(), GaussianKernel(), WideGaussian(), Threshold()], name="ext")
    assert {"q", "sigma2_px", "w2"} <= set(m.specs)
    v = dict(TRUTHY, q=-0.1, sigma_px=1.5, sigma2_px=5.0, w2=0.25)
    dose = m.dose(masks_to_tensor(border_mask, CPU), m.theta(v, CPU))[0, 0].double().numpy()
    H, W = border_mask.shape
    X = design_coords(W).double().numpy()[None, :]
    Y = design_coords(H).double().numpy()[:, None]
    e = (_field(border_mask.shape, v) - 0.1 * (X**2 + Y**2) ** 2) * border_mask / 255.0
    ref = (ndimage.gaussian_filter(e, 1.5, mode="constant", truncate=12)
           + 0.25 * ndimage.gaussian_filter(e, 5.0, mode="constant", truncate=12)) / 1.25
    np.testing.assert_allclose(dose, ref, atol=2e-6)
    fm = FixedMasks(m, masks_to_tensor(border_mask, CPU), support_px=20.0)
    assert fm.fast and "q" in fm.basis_names  # a linear field term keeps the fast path
    torch.testing.assert_close(fm.dose(m.theta(v, CPU))[0, 0].double(), torch.from_numpy(ref), atol=2e-6, rtol=0)
    with pytest.raises(ValueError, match="two components"):
        PrinterModel([QuadraticField(), QuadraticField(), LinearDose(), GaussianKernel(), Threshold()])


def test_dose_gradient_is_the_returned_doses_own_edge_offset_included():
    """``FixedMasks.dose(gradient=True)``: the gradient of the dose it returns, the edge
    offset's term included (chain rule through the blurred dose's Hessian), on the full
    grid and on every 2nd pixel; the blurred dose's gradient alone is off by e |H n|."""
    from unscatter.model import FixedMasks, extend_params, get_model, masks_to_tensor, default_params

    params = extend_params(default_params("eq1"), ["edge_offset"])
    model = get_model(params.model)
    yy, xx = np.mgrid[0:128, 0:128]
    mask = ((((xx - 64) ** 2 / 900 + (yy - 60) ** 2 / 400) < 1) * 255).astype(np.uint8)
    v = {**params.values, "sigma_px": 4.0, "edge_offset_px": 2.0}
    theta = model.theta({k: [v[k]] for k in model.names}, "cpu")
    sim = FixedMasks(model, masks_to_tensor(mask[None], "cpu"), support_px=18)
    dose, gy, gx = sim.dose(theta, gradient=True)
    fy, fx = torch.gradient(dose[0, 0].double(), dim=(0, 1))
    inner = (slice(20, 108), slice(20, 108))
    err = torch.hypot(gy[0, 0].double() - fy, gx[0, 0].double() - fx)[inner].max()
    top = torch.hypot(fy, fx)[inner].max()
    assert err < 0.02 * top  # the central difference's own error
    plain = get_model("eq1")
    d0 = plain.dose(masks_to_tensor(mask[None], "cpu"), plain.theta({k: [v[k]] for k in plain.names}, "cpu"))[0, 0].double()
    oy, ox = torch.gradient(d0, dim=(0, 1))
    assert torch.hypot(oy - fy, ox - fx)[inner].max() > 0.2 * top
    half, hy, hx = sim.decimated(2).dose(theta, gradient=True)
    assert torch.allclose(half, dose[..., ::2, ::2], atol=1e-4)
    assert torch.allclose(hy, gy[..., ::2, ::2], atol=1e-4) and torch.allclose(hx, gx[..., ::2, ::2], atol=1e-4)
    assert torch.equal(sim.dose(theta), dose)
