"""The multi-layer printer model (unscatter.model.layer_dose): one layer is the 2-D model
exactly; attenuation and depth blur against closed forms; gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from unscatter.model import (DEPTH_PARAMS, default_params, extend_params, get_model, layer_dose, layer_prints,
                             masks_to_tensor)

torch.set_num_threads(1)
PX, DZ = 3.0, 25.0


def _masks(L, n=64, seed=0):
    rng = np.random.default_rng(seed)
    m = np.zeros((L, n, n), np.uint8)
    for i in range(L):
        r0, c0 = rng.integers(4, n // 2, size=2)
        m[i, r0:r0 + n // 3, c0:c0 + n // 4] = rng.integers(120, 256)
    return m


@pytest.mark.parametrize("effects", [[], ["heavy_tail", "edge_offset", "dose_nonlinearity"]])
def test_one_layer_is_the_2d_model(effects):
    p = extend_params(default_params(), effects)
    values = dict(p.values, sigma_px=2.5, c1=-0.05, **({"tail_fraction": 0.2, "edge_offset_px": 0.7, "dose_gamma": 1.2}
                                                        if effects else {}))
    m = get_model(p.model)
    th = m.theta(values)
    masks = masks_to_tensor(_masks(1))
    d3 = layer_dose(m, masks, th, {"att_length_um": 50.0, "diffusion_um": 8.0}, DZ, PX)
    d2 = m.dose(masks, th)
    assert d3.shape == d2.shape
    assert torch.allclose(d3, d2, atol=1e-6, rtol=1e-5)
    assert torch.equal(layer_prints(m, masks, th, {"att_length_um": 50.0, "diffusion_um": 8.0}, DZ, PX), m.prints(masks, th))


def test_without_diffusion_each_layer_is_an_attenuated_sum_of_2d_doses():
    m = get_model("eq1")
    th = m.theta(dict(default_params().values, sigma_px=2.0))
    masks = masks_to_tensor(_masks(4, seed=1))
    att = 40.0
    d3 = layer_dose(m, masks, th, {"att_length_um": att, "diffusion_um": 0.0}, DZ, PX)[0]
    d2 = m.dose(masks, th)[0]
    for j in range(4):
        want = sum(math.exp(-k * DZ / att) * d2[j + k] for k in range(4 - j))
        assert torch.allclose(d3[j], want, atol=1e-5), j


def test_uniform_exposure_is_a_geometric_series():
    m = get_model("eq1")
    th = m.theta(dict(default_params().values, sigma_px=1.5))
    L, att = 6, 60.0
    masks = torch.ones(L, 96, 96)
    d = layer_dose(m, masks, th, {"att_length_um": att, "diffusion_um": 4.0}, DZ, PX)[0]
    q = math.exp(-DZ / att)
    for j in range(L):
        assert float(d[j, 48, 48]) == pytest.approx((1 - q ** (L - j)) / (1 - q), rel=1e-4)


def test_depth_widens_the_kernel_as_stated():
    m = get_model("eq1")
    sigma0, diffusion, att, L = 2.0, 6.0, 80.0, 3
    th = m.theta(dict(default_params().values, sigma_px=sigma0))
    masks = torch.zeros(L, 129, 129)
    masks[L - 1, 64, 64] = 1.0  # a point of light in the top layer only
    d = layer_dose(m, masks, th, {"att_length_um": att, "diffusion_um": diffusion}, DZ, PX)[0].double()
    ax = torch.arange(129, dtype=torch.float64) - 64
    for k in range(L):
        j = L - 1 - k
        total = float(d[j].sum())
        assert total == pytest.approx(math.exp(-k * DZ / att), rel=1e-4)
        var = float((d[j].sum(0) * ax**2).sum()) / total
        assert var == pytest.approx(sigma0**2 + diffusion * k * DZ / PX**2, rel=0.01), k


def test_gradients_of_the_depth_parameters_match_finite_differences():
    """In double precision, with steps where the central difference has converged (the
    diffusion's at 0.2 um in single precision was 2 % off from truncation and 3 % from
    rounding, so that a 5 % bound failed on one machine and not on another)."""
    m = get_model("eq1")
    dt = torch.float64
    th = {k: v.to(dt) for k, v in m.theta(dict(default_params().values, sigma_px=2.0)).items()}
    masks = masks_to_tensor(_masks(3, n=48, seed=2)).to(dt)
    target = torch.rand(3, 48, 48, generator=torch.Generator().manual_seed(0)).to(dt)

    def loss(att, diffusion):
        p = layer_prints(m, masks, th, {"att_length_um": att, "diffusion_um": diffusion}, DZ, PX, temperature=0.2)
        return ((p[0] - target) ** 2).mean()

    att = torch.tensor([60.0], dtype=dt, requires_grad=True)
    spread = torch.tensor([8.0], dtype=dt, requires_grad=True)
    loss(att, spread).backward()
    for t, h, g in ((att, 0.1, att.grad), (spread, 0.04, spread.grad)):
        with torch.no_grad():
            base = t.detach().clone()
            up = loss(base + h if t is att else att.detach(), spread.detach() if t is att else base + h)
            dn = loss(base - h if t is att else att.detach(), spread.detach() if t is att else base - h)
        fd = float(up - dn) / (2 * h)
        assert float(g) == pytest.approx(fd, rel=0.01, abs=1e-9)


def test_depth_parameters_have_bounds_and_batch():
    assert {p.name for p in DEPTH_PARAMS} == {"att_length_um", "diffusion_um"}
    assert all(p.bounds[0] <= p.default <= p.bounds[1] for p in DEPTH_PARAMS)
    m = get_model("eq1")
    th = m.theta({**default_params().values, "sigma_px": [1.5, 3.0]})
    d = layer_dose(m, masks_to_tensor(_masks(3)), th, {"att_length_um": [30.0, 300.0], "diffusion_um": 2.0}, DZ, PX)
    assert d.shape == (2, 3, 64, 64)
    one = layer_dose(m, masks_to_tensor(_masks(3)), m.theta({**default_params().values, "sigma_px": 3.0}),
                     {"att_length_um": 300.0, "diffusion_um": 2.0}, DZ, PX)
    assert torch.allclose(d[1], one[0], atol=1e-5)
