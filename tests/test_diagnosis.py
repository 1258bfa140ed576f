"""Residual diagnosis and the effect library: each effect of the library, printed by the
virtual lab (its heavy tail off, that one effect on), is named by the loop and lowers
the held-out error; Eq. 1-like prints get nothing added. Plus the effect components
against the lab's printer, extended params files through simulate / augment / ILT, and
the CLI."""

from __future__ import annotations

import copy
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from unscatter import metrics
from unscatter.calibration import calibrate
from unscatter.diagnosis import (DEFAULTS, GAIN_TESTS, accepted, diagnose, fold_spread, paired_bootstrap, sign_flip_p,
                                 structure_significant, structure_test)
from unscatter.fitting import on_bounds
from unscatter.io import read_tsv, read_yaml, write_png, write_tsv, write_yaml
from unscatter.masks import trial_masks
from unscatter.model import (
    EFFECTS,
    FixedMasks,
    default_params,
    effect_names,
    extend_params,
    get_model,
    load_params,
    masks_to_tensor,
    model_with_effects,
    save_params,
    simulate,
)

CPU = torch.device("cpu")
PX = 2.96
SIZE = 256
# the lab with every effect beyond Eq. 1 switched off (its default heavy tail included)
EQ1_LAB = {"printer": {"kernel": {"heavy_tail": None, "anisotropy": {"ratio": 1.0, "angle_deg": 0.0}},
                       "illumination": {"quartic": 0.0, "hotspot": None}, "dose_gamma": 1.0, "edge_offset_um": 0.0}}
# one effect on, strong enough to matter at 256 x 256
LAB_EFFECTS = {
    "heavy_tail": {"printer": {"kernel": {"heavy_tail": {"fraction": 0.25, "length_um": 60.0}}}},
    "anisotropy": {"printer": {"kernel": {"anisotropy": {"ratio": 1.8, "angle_deg": 30.0}}}},
    "dose_nonlinearity": {"printer": {"dose_gamma": 1.8}},
    "illumination_field": {"printer": {"illumination": {"quartic": -0.22}}},
    "edge_offset": {"printer": {"edge_offset_um": 6.0}},
}
# outside the library: a lamp hot spot, which the low-order illumination terms only partly describe
OUTSIDE_EFFECTS = {"hotspot": {"printer": {"illumination": {"hotspot": {"amplitude": 0.3, "x0": 0.35, "y0": -0.3,
                                                                        "width": 0.2}}}}}
# the same effects as model parameters (the lab's truth in the model's units)
TRUE_EFFECT_PARAMS = {
    "heavy_tail": dict(tail_fraction=0.25, tail_length_px=60.0 / PX),
    "anisotropy": dict(aniso_ratio=1.8, aniso_angle_deg=30.0),
    "dose_nonlinearity": dict(dose_gamma=1.8),
    "illumination_field": dict(ill_r4=-0.22),
    "edge_offset": dict(edge_offset_px=6.0 / PX),
}
QUIET = dict(progress=False)


def _merge(a: dict, b: dict) -> dict:
    out = copy.deepcopy(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def lab_config(effect: str | None, noise: bool = True) -> dict:
    from unscatter.lab import load_config

    over = _merge(EQ1_LAB, {**LAB_EFFECTS, **OUTSIDE_EFFECTS}[effect]) if effect else EQ1_LAB
    if not noise:
        over = _merge(over, {"printer": {"cells": {"dose_noise": 0.0, "print_to_print": 0.0}}})
    return load_config(overrides=over)


def eq1_truth(cfg: dict) -> dict:
    il, pc = cfg["printer"]["illumination"], cfg["printer"]
    return dict(c0=1.0, c1=il["cx2"], c2=il["cy2"], c3=il["cx"], c4=il["cy"], sigma_px=pc["kernel"]["sigma_um"] / PX,
                T=pc["cure"]["threshold"])


def lab_prints(root: Path, effect: str | None, count: int = 20) -> Path:
    """The lab's prints (its noise-free-microscope truth: the print in mask coordinates)
    of ``count`` trial masks, as a registration output."""
    from unscatter.lab import Printer

    cfg = lab_config(effect)
    printer = Printer(cfg["printer"], SIZE, PX)
    rows = []
    for i, (mid, m) in enumerate(trial_masks(count, seed=0, size=SIZE).items()):
        pr = printer.crop(printer.density(m, np.random.default_rng([1, i]))) >= cfg["microscope"]["level"]
        write_png(root / "masks" / f"{mid}.png", m)
        write_png(root / f"{mid}.png", pr)
        rows.append(dict(id=mid, status="ok" if pr.any() else "empty", reason="", mask=f"masks/{mid}.png"))
    write_tsv(root / "qc.tsv", rows, ["id", "status", "reason", "mask"])
    write_yaml(root / "batch.yaml", dict(pixel_size_um=PX))
    return root


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """Lab prints with one effect (or none) and the Eq. 1 calibration on them; cached."""
    made = {}

    def make(effect):
        if effect not in made:
            root = tmp_path_factory.mktemp(f"lab_{effect or 'none'}")
            prints = lab_prints(root / "prints", effect)
            calibrate([prints], root / "cal", seed=0, population=24, generations=10, folds=0, bootstrap=0,
                      residual_maps=False, figure=False, progress=False)
            made[effect] = SimpleNamespace(root=root, prints=prints, params=root / "cal" / "params.yaml")
        return made[effect]

    return make


# ------------------------------------------------------------------ effect components


@pytest.mark.parametrize("effect", list(LAB_EFFECTS))
def test_each_effect_reproduces_the_lab_printer(effect):
    """With the lab's parameters the extended model prints what the lab prints (noise off);
    at the effect's neutral defaults it is Eq. 1 exactly."""
    from unscatter.lab import Printer

    cfg = lab_config(effect, noise=False)
    printer = Printer(cfg["printer"], SIZE, PX)
    masks = list(trial_masks(4, seed=3, size=SIZE).values())
    t = masks_to_tensor(np.stack(masks), CPU)
    base = eq1_truth(cfg)
    m = get_model(model_with_effects("eq1", [effect]))
    neutral = {k: s.default for k, s in m.specs.items()} | base
    true = neutral | TRUE_EFFECT_PARAMS[effect]
    with torch.no_grad():
        d_neutral = m.dose(t, m.theta(neutral, CPU))[0]
        d_eq1 = get_model("eq1").dose(t, get_model("eq1").theta(base, CPU))[0]
        prints = m.prints(t, m.theta(true, CPU))[0].numpy()
        eq1_prints = (d_eq1 >= base["T"]).numpy()
    torch.testing.assert_close(d_neutral, d_eq1, atol=1e-5, rtol=0)
    ious, ious_eq1 = [], []
    for i, mk in enumerate(masks):
        truth = printer.crop(printer.density(mk, np.random.default_rng(0))) >= cfg["microscope"]["level"]
        ious.append(metrics.iou(prints[i], truth))
        ious_eq1.append(metrics.iou(eq1_prints[i], truth))
    # exact but for float precision; edge_offset is first order in the offset (0.97 here)
    assert np.mean(ious) > (0.96 if effect == "edge_offset" else 0.995), ious
    assert np.mean(ious) > np.mean(ious_eq1) + 0.01  # and the effect matters at this strength


def test_fixed_masks_evaluator_matches_the_model_with_every_effect():
    name = model_with_effects("eq1", effect_names())
    m = get_model(name)
    v = {k: s.default for k, s in m.specs.items()} | dict(c1=-0.07, c2=-0.05, sigma_px=3.5, T=0.5)
    for extra in TRUE_EFFECT_PARAMS.values():
        v |= extra
    masks = masks_to_tensor(np.stack(list(trial_masks(3, seed=2, size=128).values())), CPU)
    fm = FixedMasks(m, masks, support_px=m.support_px(v) + 1)
    assert fm.fast  # the gamma response is expanded, the extra field terms are linear
    th = m.theta(v, CPU)
    with torch.no_grad():
        ref = m.dose(masks, th)
        torch.testing.assert_close(fm.dose(th), ref, atol=2e-4, rtol=0)
        torch.testing.assert_close(fm.decimated(2).dose(th), ref[..., ::2, ::2], atol=2e-4, rtol=0)


def test_gradients_reach_every_effect_parameter():
    name = model_with_effects("eq1", effect_names())
    m = get_model(name)
    v = {k: s.default for k, s in m.specs.items()} | dict(sigma_px=3.0, T=0.5, tail_fraction=0.2, aniso_ratio=1.3,
                                                          aniso_angle_deg=10.0, dose_gamma=1.3, edge_offset_px=1.0,
                                                          ill_r4=0.05, ill_xy=0.05)
    th = {k: t.clone().requires_grad_(True) for k, t in m.theta(v, CPU).items()}
    masks = masks_to_tensor(np.stack(list(trial_masks(2, seed=1, size=96).values())), CPU)
    m.prints(masks, th, temperature=0.1).mean().backward()
    for e in effect_names():
        for p in EFFECTS[e].params:
            g = th[p.name].grad
            assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0, p.name


def test_extended_params_file_round_trips_and_serves_simulate_augment_and_ilt(tmp_path):
    from unscatter.augment import augment
    from unscatter.calibration import simulate_dir
    from unscatter.compensation import optimise_mask

    name = model_with_effects("eq1", ["edge_offset", "heavy_tail"])
    assert name == "eq1+heavy_tail+edge_offset"  # canonical: the library's order
    p = extend_params(default_params(pixel_size_um=PX), ["heavy_tail", "edge_offset"])
    assert p.model == name
    p = p.with_values(sigma_px=3.0, tail_fraction=0.2, tail_length_px=12.0, edge_offset_px=1.5)
    path = tmp_path / "model.yaml"
    save_params(path, p, effects=["heavy_tail", "edge_offset"], unexplained_residual=False)
    q = load_params(path)
    assert q.model == name and q.values == pytest.approx(p.values) and q.info["effects"] == ["heavy_tail", "edge_offset"]
    d = read_yaml(path)
    assert d["derived"]["edge_offset_um"] == pytest.approx(1.5 * PX) and "tail_fraction" in d["equation"]

    masks = tmp_path / "masks"
    for mid, mk in trial_masks(2, seed=0, size=128).items():
        write_png(masks / f"{mid}.png", mk)
    out = simulate_dir(path, masks, tmp_path / "sim")
    assert len(out) == 2
    sim = simulate(q, list(trial_masks(2, seed=0, size=128).values()))
    eq1_sim = simulate(default_params().with_values(sigma_px=3.0), list(trial_masks(2, seed=0, size=128).values()))
    assert sim.sum() > eq1_sim.sum()  # swelling plus the tail's extra light: bigger prints

    summary = augment(path, tmp_path / "aug.zarr", count=4, seed=0, size=128, workers=1, progress=False)
    assert summary["count"] == 4

    design = np.zeros((128, 128), bool)
    design[40:90, 30:100] = True
    mask, info = optimise_mask(design, q, schedule=((2, 10), (1, 5)))
    assert mask.shape == design.shape and np.isfinite(info["loss"]).all()
    assert info["model_iou"] >= info["identical_model_iou"]


def test_unknown_effects_and_models_are_rejected(tmp_path):
    with pytest.raises(KeyError):
        get_model("eq1+glow")
    with pytest.raises(KeyError):
        model_with_effects("eq1", ["glow"])
    p = default_params()
    save_params(tmp_path / "p.yaml", p)
    text = (tmp_path / "p.yaml").read_text().replace("model: eq1", "model: eq1+glow")
    (tmp_path / "p.yaml").write_text(text)
    from unscatter.io import InputError

    with pytest.raises(InputError, match="unknown effect 'glow' .*known: .*heavy_tail"):
        load_params(tmp_path / "p.yaml")


# ---------------------------------------------------------------------- statistics


def test_paired_bootstrap_separates_real_improvements_from_noise():
    rng = np.random.default_rng(0)
    before = rng.uniform(0.004, 0.006, 24)
    better = paired_bootstrap(before, before * 0.8 + rng.normal(0, 1e-5, 24), 2000, 0)
    assert better["ci_lo"] > 0 and better["relative"] == pytest.approx(0.2, abs=0.01)
    noise = paired_bootstrap(before, before + rng.normal(0, 3e-4, 24), 2000, 0)
    assert noise["ci_lo"] < 0 < noise["ci_hi"]
    assert better["p_value"] < 1e-6 and noise["p_value"] > 0.025


def test_a_gain_on_few_prints_needs_a_paired_test_as_well():
    """8 prints of a random lab with no effect (bench_diagnosis, seed 79055443, lab 9, a
    design of 8 masks): a dose nonlinearity lowered the held-out mismatch by 3.1 %, most
    of it on two prints. The percentile bootstrap's 2.5 % quantile is above 0; neither the
    paired t-test's p-value (0.06) nor the sign-flip test's (12 / 256) is below 0.025, so
    the gain is not accepted."""
    before = np.array([0.01491, 0.01596, 0.03198, 0.00914, 0.00383, 0.00607, 0.01089, 0.01186])
    after = np.array([0.01477, 0.01555, 0.03006, 0.00934, 0.00385, 0.00613, 0.01035, 0.01131])
    st = paired_bootstrap(before, after, 2000, 0)
    assert st["ci_lo"] > 0 and st["relative"] > DEFAULTS["min_improvement"]
    t_test = dict(DEFAULTS, gain_test="t")
    assert 0.04 < st["p_value"] < 0.1
    assert not accepted(st, t_test)
    assert accepted(dict(st, p_value=0.01), t_test)  # the same gain, with the t-test's support
    assert paired_bootstrap(before, before, 100, 0)["p_value"] == 1.0
    # the sign-flip test (the default) refuses it too: the gain rests on two prints (p 12 / 256)
    assert DEFAULTS["gain_test"] == "sign_flip"
    assert st["p_sign_flip"] == pytest.approx(12 / 256)
    assert not accepted(st, DEFAULTS)
    assert accepted(dict(st, p_sign_flip=0.01), DEFAULTS)


def test_a_gain_every_print_shares_unevenly_is_proven_by_the_sign_flip_test_not_the_t_test():
    """16 designed prints of a lab with an anisotropy of 1.78 (bench_print_budget, seed
    649474598, lab 0): the anisotropy lowered every print's held-out mismatch, by 0.002 to
    0.110 (66 % of the error). The bootstrap interval is above 0, but the t-test's p-value
    is 0.029, the gains' spread being that large: refused. Under the sign-flip test no
    sign pattern but all positive reaches the gain (p = 2^-16), and it is accepted."""
    before = np.array([0.0085678, 0.015347, 0.012371, 0.017624, 0.019611, 0.0075378, 0.019615, 0.012646, 0.010033,
                       0.010769, 0.12554, 0.016933, 0.013069, 0.014816, 0.011753, 0.010246])
    after = np.array([0.005043, 0.0054627, 0.0053101, 0.008255, 0.009285, 0.0055199, 0.0052147, 0.0048065, 0.0055695,
                      0.0057526, 0.015095, 0.010857, 0.0068779, 0.0059967, 0.0074043, 0.0052643])
    st = paired_bootstrap(before, after, 2000, 0)
    assert st["ci_lo"] > 0 and st["relative"] > 0.6
    assert 0.025 < st["p_value"] < 0.035 and not accepted(st, dict(DEFAULTS, gain_test="t"))
    assert st["p_sign_flip"] == pytest.approx(2.0**-16)
    assert accepted(st, DEFAULTS)


def test_every_gain_test_the_setting_offers_is_one_the_acceptance_knows():
    from unscatter.settings import DIAGNOSIS

    assert set(DIAGNOSIS["gain_test"].choices) == set(GAIN_TESTS)


def test_the_sign_flip_test_is_exact_for_few_prints_and_keeps_its_level_for_many():
    """Exact over every sign pattern up to 16 prints (one print gaining, the rest nothing:
    the half of the patterns that keep its sign reach its sum); beyond, random patterns whose p-values keep the
    test's level: under the null (gains as likely negative as positive) p < 0.025 in
    about 2.5 % of draws, and one print's gain among 32 whose others gain nothing on the
    whole is not proven (its sign and the others' give p of about a quarter)."""
    assert sign_flip_p(np.array([1.0, 0, 0, 0]), 0) == pytest.approx(0.5)  # ties count: the 8 patterns with the 1 kept
    assert sign_flip_p(np.array([1.0, 1e-3, -1e-3]), 0) == pytest.approx(3 / 8)
    assert sign_flip_p(np.ones(8), 0) == pytest.approx(1 / 256)
    assert sign_flip_p(np.array([]), 0) == 1.0
    rng = np.random.default_rng(3)
    ps = np.array([sign_flip_p(rng.standard_t(2, 32) * rng.uniform(0.1, 10, 32), k, flips=4000) for k in range(400)])
    assert 0.005 < np.mean(ps < 0.025) < 0.05
    rest = rng.normal(0, 0.01, 15)
    one = np.r_[5.0, rest, -rest, 0.0]  # one print's gain, the others' nothing on the whole
    assert 0.25 < sign_flip_p(one, 0) < 0.3
    assert sign_flip_p(np.abs(rng.normal(0, 1, 32)), 0) < 1e-3


def test_fold_spread_is_the_grouped_jackknife():
    folds = [dict(a=1.0, b=5.0), dict(a=2.0, b=5.0), dict(a=3.0, b=5.0)]
    s = fold_spread(folds, ["a", "b"])
    assert s["a"] == pytest.approx(np.sqrt(2 / 3 * 2.0)) and s["b"] == 0.0
    assert np.isnan(fold_spread(folds[:1], ["a"])["a"])


def test_a_parameter_whose_fit_or_fold_fits_reach_a_bound_is_flagged():
    bounds = {"a": (0.0, 1.0), "b": (2.0, 40.0)}
    folds = [dict(a=0.5, b=38.0), dict(a=0.6, b=40.0), dict(a=0.55, b=39.9)]
    assert on_bounds([dict(a=0.55, b=39.5), *folds], bounds, ["a", "b"]) == {"b": "upper"}
    assert on_bounds([dict(a=0.004, b=20.0), *folds[:1]], bounds, ["a", "b"]) == {"a": "lower"}
    assert on_bounds([dict(a=0.5, b=20.0), *folds[:1]], bounds, ["a", "b"]) == {}


class _Prints(SimpleNamespace):
    """Masks and prints as ``_Context`` takes them."""

    def __len__(self):
        return len(self.prints)


def test_a_fold_fit_that_keeps_its_start_gives_its_own_optimum_to_the_spread():
    """A fold fit starts from the fit on all prints, and keeps that start wherever nothing
    it finds beats it on the fold's prints (the GA's population holds it): its values are
    then the fit on all prints, and a spread taken over them shrinks toward 0. On the
    prints of a heavy-tail draw whose tail was not accepted, Eq. 1's c2 had a spread of
    0.0002 and sigma 0.013 px; from the fold fits' own optima, 0.0097 and 0.032 px. Here
    two of four folds keep the start, and the spread comes from the refinement's own
    optima, which move with each fold's prints."""
    from unscatter.diagnosis import QUICK, _Context

    p = default_params("eq1")
    truth = p.values | dict(c1=-0.05, c3=0.03, sigma_px=2.5, T=0.45)
    masks = np.stack(list(trial_masks(12, seed=0, size=96).values()))
    data = _Prints(masks=masks, prints=simulate(p.with_values(**truth), masks, dose_noise=0.03,
                                                rng=np.random.default_rng(0)))
    s = {**DEFAULTS, **QUICK, "objective": "mismatch", "area_floor": 0.02}
    ctx = _Context(p, data, CPU, s, {})
    full = ctx.fit(truth, None, 0, s, set(p.free), "all prints")
    fits = [ctx.fit_own(full, np.setdiff1d(np.arange(12), np.arange(12)[i::4]), i, s, set(p.free), f"fold {i}")
            for i in range(4)]
    kept, own = [f[0] for f in fits], [f[1] for f in fits]
    assert sum(v == full for v in kept) >= 1  # the fold fits that kept their start
    assert all(o != full for o in own)
    before, after = fold_spread(kept, p.free), fold_spread(own, p.free)
    for k in ("c1", "sigma_px", "T"):
        assert after[k] > before[k], (k, before, after)
    # the own optima are fits of the same prints: near the truth, not anywhere
    assert all(abs(o["sigma_px"] - 2.5) < 0.1 and abs(o["T"] - 0.45) < 0.01 for o in own), own


def test_structure_test_flags_a_common_trend_but_not_noise():
    rng = np.random.default_rng(1)
    B, nb = 20, 10
    N = np.full((B, nb), 1000.0)
    A = np.full((B, nb), 30.0)
    noise = rng.normal(0, 5, (B, nb))
    trend = noise + np.linspace(-20, 20, nb)[None]  # every print: too small on the left, too big on the right
    t = structure_test(trend, A, N, 999, 0)
    assert t["p_value"] < 0.01 and t["excess"] > 0.15
    t0 = structure_test(noise, A, N, 999, 0)
    assert t0["p_value"] > 0.01 and t0["excess"] < 0.15


def test_a_trend_under_each_prints_own_dose_error_is_found_once_the_dose_is_profiled():
    """Every print dosed off the fit by its own amount (a multiple of its bins' dose
    response R, of either sign) hides a trend across the bins from the plain sign flip;
    with each print's multiple of R taken out, the trend stands out, and without a trend
    the profiled test finds nothing."""
    rng = np.random.default_rng(0)
    B, nb = 16, 10
    N = np.full((B, nb), 1000.0)
    A = np.full((B, nb), 40.0)
    R = rng.uniform(20, 60, (B, nb))
    dosed = rng.normal(0, 0.6, B)[:, None] * R + rng.normal(0, 4, (B, nb))
    t = structure_test(dosed + np.linspace(-6, 6, nb)[None], A, N, 999, 0, R)
    assert t["p_value"] > 0.05 and t["p_dose_profiled"] < 0.01, t
    t0 = structure_test(dosed, A, N, 999, 0, R)
    assert t0["p_dose_profiled"] > 0.01, t0
    t["predictive_gain"] = t0["predictive_gain"] = 2 * DEFAULTS["structure_gain"]  # as if it predicted held-out prints
    profiled = dict(DEFAULTS, dose_profiled=True)
    assert structure_significant(t, profiled) and not structure_significant(t, DEFAULTS)  # the default: plain
    assert not structure_significant(t0, profiled)
    nulls = [structure_test(np.random.default_rng(s).normal(0, 0.6, B)[:, None] * R + np.random.default_rng(s + 1000).normal(0, 4, (B, nb)),
                            A, N, 199, s, R)["p_dose_profiled"] for s in range(100)]
    assert np.mean(np.array(nulls) < 0.05) <= 0.1  # the null keeps its level


def _quarters_geometry(B: int, n: int):
    """One diagnostic whose four bins are the quadrants of an n x n field."""
    q = np.zeros((n, n), np.int16)
    q[:, n // 2:] += 1
    q[n // 2:, :] += 2
    return SimpleNamespace(names=["quadrant"], labels={"quadrant": list("abcd")}, bins=[{"quadrant": q}] * B)


def test_predictive_gain_needs_a_correction_that_carries_to_new_prints():
    from scipy import ndimage

    from unscatter.diagnosis import predictive_gain

    rng = np.random.default_rng(3)
    B, n = 16, 64
    geo = _quarters_geometry(B, n)
    # each fold's fit: the true margin, its threshold a little off (fit noise)
    margin = np.stack([ndimage.gaussian_filter(rng.standard_normal((n, n)), 4) for _ in range(B)])
    margin = 0.3 * margin / margin.std()
    folds = [np.arange(i, B, 4) for i in range(4)]
    margins = np.stack([margin + rng.normal(0, 0.01) for _ in folds]).astype(np.float16)
    sims = np.zeros((B, n, n), bool)
    for f, idx in enumerate(folds):
        sims[idx] = margins[f, idx] >= 0
    quad = geo.bins[0]["quadrant"]
    # every print prints more in quadrant a than the model says: a missing effect
    common = np.stack([m + 0.1 * (quad == 0) + 0.02 * rng.standard_normal((n, n)) >= 0 for m in margin])
    # each print's quadrants off by its own amount, of random sign: noise no model predicts
    own = np.stack([m + rng.normal(0, 0.1, 4)[quad] >= 0 for m in margin])
    g_common = predictive_gain(geo, common, sims, margins, folds)["quadrant"]
    g_own = predictive_gain(geo, own, sims, margins, folds)["quadrant"]
    assert g_common > 0.2, g_common
    assert g_own < 0.02, g_own



def _hot_spot_prints(width: float) -> SimpleNamespace:
    """16 prints of 96 x 96 whose every fold's fit is the true margin, with the position's
    8 x 8 cells near an edge, printed three ways: a hot spot of 0.15 (relative dose) and
    this width (field units, -1..1) at one place in every print (``common``), at each
    print's own place and of its own sign (``own``), or none; cell-like noise in all."""
    from scipy import ndimage

    rng = np.random.default_rng(5)
    B, n, cells = 16, 96, 8

    def smooth(s):
        x = ndimage.gaussian_filter(rng.standard_normal((n, n)), s)
        return x / x.std()

    margin = np.stack([0.3 * smooth(3) for _ in range(B)])  # every fold's fit: the true margin
    r = np.minimum(np.arange(n) * cells // n, cells - 1)
    cell = (r[:, None] * cells + r[None, :]).astype(np.int16)
    geo = SimpleNamespace(names=["position"], labels={"position": [str(i) for i in range(cells * cells)]},
                          bins=[{"position": np.where(np.abs(m) < 0.15, cell, -1).astype(np.int16)} for m in margin])
    folds = [np.arange(i, B, 4) for i in range(4)]
    margins = np.stack([margin] * len(folds)).astype(np.float16)
    c = (np.arange(n) + 0.5) / n * 2 - 1
    X, Y = np.meshgrid(c, c)

    def spot(x0, y0):
        return 0.15 * np.exp(-((X - x0) ** 2 + (Y - y0) ** 2) / (2 * width**2))

    noise = [0.03 * smooth(2) for _ in range(B)]
    prints = dict(common=np.stack([m + spot(0.25, -0.25) + e >= 0 for m, e in zip(margin, noise)]),
                  own=np.stack([m + rng.choice([-1, 1]) * spot(*rng.uniform(-0.8, 0.8, 2)) + e >= 0
                                for m, e in zip(margin, noise)]),
                  none=np.stack([m + e >= 0 for m, e in zip(margin, noise)]))
    return SimpleNamespace(geo=geo, margins=margins, folds=folds, sims=margin >= 0, prints=prints, axis=c, rng=rng)


def test_the_position_field_from_its_factors_is_the_basis_times_the_weights():
    """field_gain builds the bumps' rows at the pixels it fits on, and the field, from the
    two 1-D factors: the same numbers as the (H*W, n*n) basis (not built there)."""
    from unscatter.diagnosis import _field_rows, field_factors

    rng = np.random.default_rng(2)
    shape, n = (37, 53), 7
    gy, gx = field_factors(shape, n)
    # the basis itself, bump (a, b) in column a*n + b, every pixel a row
    Phi = (gy[:, None, :, None] * gx[None, :, None, :]).reshape(shape[0] * shape[1], n * n)
    idx = rng.integers(0, shape[0] * shape[1], 300)
    np.testing.assert_array_equal(_field_rows(gy, gx, idx), Phi[idx])
    c = rng.standard_normal(n * n).astype(np.float32)
    np.testing.assert_allclose((gy @ c.reshape(n, n) @ gx.T).ravel(), Phi @ c, atol=1e-5)
    # a bump's peak sits at its grid point: the middle bump peaks at the field's centre
    mid = (Phi[:, (n // 2) * n + n // 2]).reshape(shape)
    assert np.unravel_index(mid.argmax(), shape) == (shape[0] // 2, shape[1] // 2)


def test_field_gain_finds_a_hot_spot_common_to_the_prints_but_not_one_of_their_own():
    """The position's predictive test (a smooth field of the margin fitted on training
    prints) gains where every print has the same hot spot and loses where each print has
    its own, of random place and sign, or none (cell-like noise alone)."""
    from unscatter.diagnosis import field_gain

    h = _hot_spot_prints(0.2)
    geo, sims, margins, folds, c = h.geo, h.sims, h.margins, h.folds, h.axis
    common, own, none = h.prints["common"], h.prints["own"], h.prints["none"]
    rng, B = h.rng, len(sims)  # the helper's generator, drawn on as before
    g = {k: field_gain(geo, p, sims, margins, folds) for k, p in (("common", common), ("own", own), ("none", none))}
    assert g["common"] > 0.1, g
    assert g["own"] < 0.005 and g["none"] < 0.005, g
    # the same with uneven print weights and the fit on every 3rd pixel near an edge (about 42,000 of them, a third kept)
    w = rng.uniform(0.5, 2.0, B)
    sub = {k: field_gain(geo, p, sims, margins, folds, w, max_pixels=20_000) for k, p in (("common", common), ("own", own),
                                                                                      ("none", none))}
    assert sub["common"] > 0.1 and sub["own"] < 0.005 and sub["none"] < 0.005, sub
    # the fitted field (for the figure) peaks at the hot spot
    gain, field = field_gain(geo, common, sims, margins, folds, return_field=True)
    assert gain == g["common"] and field.shape == sims.shape[1:]
    r, col = np.unravel_index(np.argmax(field), field.shape)
    assert np.hypot(c[col] - 0.25, c[r] + 0.25) < 0.15, (c[col], c[r])
    assert field.max() > 0.05


def test_a_hot_spot_in_a_few_cells_is_structure_though_the_cells_dilute_its_excess():
    """A hot spot common to every print, small against the position's 8 x 8 cells: the
    sign flip finds it and the smooth field predicts held-out prints, but the cells it
    misses dilute the excess below the 0.15 the gate asked before. It is structure (the
    held-out gain gates its size); spots of each print's own place and sign, or none, are
    not."""
    from unscatter.diagnosis import DEFAULTS, field_gain, residual_sums, structure_significant, structure_test

    h = _hot_spot_prints(0.14)
    tests = {}
    for k, p in h.prints.items():
        t = structure_test(*residual_sums(h.geo, p, h.sims)["position"], 999, 0)
        t["predictive_gain"] = field_gain(h.geo, p, h.sims, h.margins, h.folds)
        tests[k] = t
    t = tests["common"]
    assert t["p_value"] < DEFAULTS["alpha"] and t["predictive_gain"] >= 2 * DEFAULTS["structure_gain"], t
    assert t["excess"] < 0.15, t  # diluted by the cells the spot misses
    assert structure_significant(t, DEFAULTS)
    assert not structure_significant(t, dict(DEFAULTS, structure_min=0.15))  # the gate before
    for k in ("own", "none"):
        assert not structure_significant(tests[k], DEFAULTS), (k, tests[k])


# ------------------------------------------------------------------------- the loop


def _check_outputs(out: Path, r: dict):
    for f in ("model.yaml", "ranking.tsv", "before_after.tsv", "diagnostics.tsv", "structure.tsv", "diagnostics.png",
              "residual_maps.png", "report.md"):
        assert (out / f).is_file(), f
    d = read_yaml(out / "model.yaml")
    assert d["effects"] == r["effects"] and d["unexplained_residual"] == r["unexplained_residual"]
    p = load_params(out / "model.yaml")
    assert p.model == model_with_effects("eq1", r["effects"])
    # every fitted parameter carries its spread over the fold fits, in the file and report.md
    for k in p.free:
        std = d["parameters"][k]["std"]
        assert np.isfinite(std) and std >= 0, (k, std)
        assert f"| {k} |" in (out / "report.md").read_text()
    ba = {row["model"]: row for row in read_tsv(out / "before_after.tsv")}
    assert set(ba) == {"base", "selected", "mask itself"}
    # the mask itself, chosen per fold on the training prints, is the baseline: these prints scatter, a model beats it
    assert d["diagnosis"]["selected_beats_mask"]
    assert float(ba["selected"]["heldout_error"]) < float(ba["mask itself"]["heldout_error"])
    assert float(ba["selected"]["heldout_iou"]) > float(ba["mask itself"]["heldout_iou"])
    assert "the mask itself (grey level >= " in (out / "report.md").read_text()
    diags = {row["diagnostic"] for row in read_tsv(out / "diagnostics.tsv")}
    assert {"signed_distance", "density_10um", "density_300um", "grey_level", "position", "orientation", "spectrum"} <= diags
    # every print's held-out error, per round's control and candidate: their means are ranking.tsv's
    per = read_tsv(out / "heldout_errors.tsv")
    ranked = {(row["round"], row["candidate"]): float(row["heldout_mismatch"]) for row in read_tsv(out / "ranking.tsv")}
    assert per[0]["candidate"] == "(base)" and len(per) == len(ranked) + 1
    for row in per[1:]:
        errs = [float(v) for k, v in row.items() if k not in ("round", "candidate")]
        assert np.mean(errs) == pytest.approx(ranked[(row["round"], row["candidate"])], rel=1e-4)


@pytest.mark.slow
def test_full_library_names_the_heavy_tail_and_lowers_heldout_error(case, tmp_path):
    c = case("heavy_tail")
    r = diagnose([c.prints], c.params, tmp_path / "d", quick=True, seed=0, **QUIET)
    _check_outputs(tmp_path / "d", r)
    assert r["effects"][:1] == ["heavy_tail"]
    assert r["after"]["heldout_mismatch"] < 0.85 * r["before"]["heldout_mismatch"]
    assert r["after"]["heldout_iou"] > r["before"]["heldout_iou"]
    rows = read_tsv(tmp_path / "d" / "ranking.tsv")
    first = [row for row in rows if row["round"] == "1" and row["candidate"] != "(control)"]
    assert {row["candidate"] for row in first} == set(effect_names())  # every candidate was tried
    best = max(first, key=lambda row: float(row["improvement"]))
    assert best["candidate"] == "heavy_tail" and best["selected"] == "True"
    # before: the residual trends with the density at large radii; the tail explains it
    before = {t["diagnostic"]: t for t in r["structure_before"]}
    assert before["density_300um"]["significant"]
    assert not r["unexplained_residual"]


@pytest.mark.slow
def test_eq1_like_prints_get_no_effect(case, tmp_path):
    c = case(None)
    r = diagnose([c.prints], c.params, tmp_path / "d", quick=True, seed=0, **QUIET)
    _check_outputs(tmp_path / "d", r)
    assert r["effects"] == []
    assert r["after"] == r["before"]
    assert not r["unexplained_residual"]
    assert load_params(tmp_path / "d" / "model.yaml").model == "eq1"


@pytest.mark.slow
def test_an_effect_outside_the_library_is_flagged_unexplained(case, tmp_path):
    """A hot spot: the library's illumination field takes part of it; what is left trends
    with the position in the field in every print, and a per-cell correction fitted on
    training prints predicts the held-out ones."""
    c = case("hotspot")
    r = diagnose([c.prints], c.params, tmp_path / "d", quick=True, seed=0, candidates=["illumination_field"], **QUIET)
    assert r["unexplained_residual"]
    flagged = {t["diagnostic"]: t for t in r["structure_after"] if t["significant"]}
    assert "position" in flagged, r["structure_after"]
    assert flagged["position"]["predictive_gain"] >= 0.03


# the effect and a decoy whose signature differs; the full list runs on the heavy tail above
DECOYS = {"anisotropy": ["heavy_tail", "anisotropy"], "dose_nonlinearity": ["edge_offset", "dose_nonlinearity"],
          "illumination_field": ["illumination_field", "anisotropy"], "edge_offset": ["heavy_tail", "edge_offset"]}


@pytest.mark.slow
@pytest.mark.parametrize("effect", list(DECOYS))
def test_the_loop_names_the_lab_effect(case, tmp_path, effect):
    c = case(effect)
    r = diagnose([c.prints], c.params, tmp_path / "d", quick=True, seed=0, candidates=DECOYS[effect], **QUIET)
    assert r["effects"][:1] == [effect]
    assert r["after"]["heldout_mismatch"] < 0.97 * r["before"]["heldout_mismatch"]
    assert r["after"]["heldout_pixel_error"] < r["before"]["heldout_pixel_error"]
    p = load_params(tmp_path / "d" / "model.yaml")
    neutral = {s.name: s.default for s in EFFECTS[effect].params}
    for k, v in TRUE_EFFECT_PARAMS[effect].items():  # the fitted effect goes the lab's way
        if k != "aniso_angle_deg":
            assert np.sign(p.values[k] - neutral[k]) == np.sign(v - neutral[k]), (k, p.values[k])


def test_fits_in_worker_processes_give_the_same_diagnosis_as_in_one(case, tmp_path, caplog):
    """The fits of a round run in worker processes (``workers``); each depends only on its
    start, prints and seed, so the selected model, every candidate's held-out errors and
    fitted parameters are the same as in one process, to the last digit; also where the
    folds of a candidate with spectra of its own (illumination_field) run as one task."""
    c = case("edge_offset")
    runs = {}
    for w in (1, 2):
        caplog.clear()
        with caplog.at_level("INFO", logger="unscatter.diagnosis"):
            r = diagnose([c.prints], c.params, tmp_path / f"w{w}", quick=True, seed=0,
                         candidates=["edge_offset", "heavy_tail", "illumination_field"], figures=False, workers=w, **QUIET)
        assert ("the fits run in 2 worker processes" in caplog.text) == (w == 2)
        grouped = [line for line in caplog.text.splitlines() if "run as one task each" in line]
        assert any("+illumination_field" in line for line in grouped) == (w == 2), grouped
        assert "worker processes stopped" not in caplog.text
        rows = read_tsv(tmp_path / f"w{w}" / "ranking.tsv")
        runs[w] = (r["effects"], [(x["round"], x["candidate"], x["heldout_mismatch"], x["effect_params"]) for x in rows],
                   load_params(tmp_path / f"w{w}" / "model.yaml").values,
                   read_tsv(tmp_path / f"w{w}" / "heldout_errors.tsv"))
    assert runs[1][0] == ["edge_offset"]  # a round that accepts, a full-data fit, and a round that does not
    assert runs[2] == runs[1]


def test_cli_diagnose(case, tmp_path):
    from unscatter.cli import main

    c = case(None)
    out = tmp_path / "cli"
    res = CliRunner().invoke(main, ["diagnose", str(c.prints), "--base", str(c.params), "--out", str(out), "--quick",
                                    "--candidates", "edge_offset", "--folds", "2", "--no-progress"])
    assert res.exit_code == 0, res.output
    assert "effects added: none" in res.output and (out / "model.yaml").is_file()
    assert "(the mask itself 0." in res.output and "no better than the mask" not in res.output
    bad = CliRunner().invoke(main, ["diagnose", str(c.prints), "--base", str(c.params), "--out", str(out),
                                    "--candidates", "glow"])
    assert bad.exit_code == 2 and "glow" in bad.output
    bad = CliRunner().invoke(main, ["diagnose", str(c.prints), "--base", str(c.params), "--out", str(out),
                                    "--gain-test", "wilcoxon"])
    assert bad.exit_code == 2 and "wilcoxon" in bad.output and "sign_flip" in bad.output


def test_too_few_prints_or_folds_are_rejected(tmp_path):
    from unscatter.io import InputError

    prints = lab_prints(tmp_path / "prints", None, count=3)
    save_params(tmp_path / "p.yaml", default_params(pixel_size_um=PX))
    with pytest.raises(InputError, match="too few"):
        diagnose([prints], tmp_path / "p.yaml", tmp_path / "d", quick=True, **QUIET)
    with pytest.raises(ValueError, match="folds"):
        diagnose([prints], tmp_path / "p.yaml", tmp_path / "d", folds=1, **QUIET)
    with pytest.raises(ValueError, match="diagnosis.candidates item: 'glow' is not one of"):
        diagnose([prints], tmp_path / "p.yaml", tmp_path / "d", candidates=["glow"], **QUIET)
    with pytest.raises(ValueError, match="diagnosis.gain_test: 'z' is not one of sign_flip, t"):
        diagnose([prints], tmp_path / "p.yaml", tmp_path / "d", gain_test="z", **QUIET)


# ------------------------------------------------------------------- candidate fits


def test_candidate_fit_reaches_the_true_parameters_error():
    """A heavy tail fitted from the Eq. 1 fit (its tail at 0, where the gradient does not
    reach the tail's length) must reach, on held-out prints, the error of the true
    parameters: the multi-start over the effect's own parameters. Without it the fit
    stayed near Eq. 1 (held-out error 26 % above the truth's here)."""
    from unscatter.diagnosis import DEFAULTS, QUICK, _Context

    rng = np.random.default_rng(0)
    p = extend_params(default_params("eq1"), ["heavy_tail"])
    m = get_model(p.model)
    truth = p.values | dict(c1=-0.06, c2=-0.03, c3=0.03, c4=-0.02, sigma_px=2.5, T=0.4, tail_fraction=0.3,
                            tail_length_px=12.0)
    masks = np.stack(list(trial_masks(12, seed=0, size=96).values()))
    held = np.stack(list(trial_masks(8, seed=5, size=96).values()))
    # prints of the library model with a dose noise correlated over 2 px, as cells give
    data = SimpleNamespace(masks=masks, prints=simulate(p.with_values(**truth), masks, dose_noise=0.03, rng=rng))
    held_data = SimpleNamespace(masks=held, prints=simulate(p.with_values(**truth), held, dose_noise=0.03, rng=rng))
    s = {**DEFAULTS, **QUICK, "objective": "mismatch", "area_floor": 0.02}
    # the warm start the diagnosis gives: Eq. 1's fit (here: Eq. 1 with the truth's field
    # and a wider kernel, lower threshold), the tail at its neutral 0
    start = p.values | {k: truth[k] for k in ("c1", "c2", "c3", "c4")} | dict(sigma_px=3.4, T=0.36)
    fit = _Context(p, data, CPU, s, {}).fit(start, None, 0, s, set(default_params("eq1").free), "test")
    ctx = _Context(p, held_data, CPU, s, {})
    err = lambda v: float(np.mean(ctx.predict(v, np.arange(len(held))) != held_data.prints))  # noqa: E731
    assert err(start) > 1.3 * err(truth)  # the tail matters at this strength
    assert err(fit) < 1.05 * err(truth), (err(fit), err(truth), fit)
    assert fit["tail_fraction"] == pytest.approx(0.3, abs=0.1)


def test_refinement_keeps_kernel_parameters_inside_the_padding():
    """The L-BFGS refinement may step outside the bounds, but never with a kernel
    parameter: the evaluator's padding is made for the bounds (a multi-start
    near a tail's longest length stopped the diagnosis with 'a kernel is wider than this
    evaluator's padding')."""
    from unscatter.fitting import Space, refine

    p = extend_params(default_params("eq1"), ["heavy_tail"])
    m = get_model(p.model)
    seen = []

    class Longer:  # an objective that always wants a longer tail and a larger threshold
        def smooth(self, theta, temperature):
            seen.append({k: float(v.detach()[0]) for k, v in theta.items()})
            return -(theta["tail_length_px"] / 40 + theta["T"] / 1.5 + theta["sigma_px"] / 12)

    refine(Space(p), Longer(), m, p.values | dict(tail_length_px=38.0, sigma_px=11.0), CPU, (0.1,), 5)
    assert max(v["tail_length_px"] for v in seen) <= p.bounds["tail_length_px"][1] + 1e-4
    assert max(v["sigma_px"] for v in seen) <= p.bounds["sigma_px"][1] + 1e-4
    assert max(v["T"] for v in seen) > p.bounds["T"][1]  # the others may step outside (clipped at the end)
    # an aspect ratio below its lower bound widens the kernel as much as one above the upper
    pa = extend_params(default_params("eq1"), ["anisotropy"])
    seen.clear()

    class Rounder:
        def smooth(self, theta, temperature):
            seen.append({k: float(v.detach()[0]) for k, v in theta.items()})
            return theta["aniso_ratio"] / 2

    refine(Space(pa), Rounder(), get_model(pa.model), pa.values | dict(aniso_ratio=0.6, sigma_px=11.0), CPU, (0.1,), 5)
    assert min(v["aniso_ratio"] for v in seen) >= pa.bounds["aniso_ratio"][0] - 1e-4


def test_an_ellipse_s_angle_wraps_instead_of_stopping_at_a_bound():
    """An elliptical kernel repeats every 180 deg of its angle. With the angle bounded to
    -45..45 deg (and the ratio either side of 1), a fold fit whose ellipse lay near 45 deg
    stopped on the bound, cut off from the same kernel a step away (bench_fit_recovery seed
    607314319, case 6: a fold fit at -45 deg, the angle's spread 55 deg, the candidate's
    held-out error 13.5 % above the truth's). Now the angle runs -90..90 deg and wraps: the
    refinement crosses +-90, the spread and the mean are taken across it, and it is never
    flagged on a bound. The ratio still runs either side of 1, so that a fit can pass
    through a round kernel; ``canonical`` writes each kernel once."""
    from unscatter.fitting import Space, on_bounds, refine
    from unscatter.model import canonical, periods

    pa = extend_params(default_params("eq1"), ["anisotropy"])
    assert periods(pa) == {"aniso_angle_deg": 180.0}
    space = Space(pa)
    i = space.names.index("aniso_angle_deg")
    g = space.encode(pa.values | dict(aniso_angle_deg=100.0))
    assert g[i] == pytest.approx((-80.0 + 90.0) / 180.0)  # 100 deg is -80 deg
    g[i] = 1.25
    assert space.decode(g)["aniso_angle_deg"][0] == pytest.approx(-45.0)  # wrapped, not clipped to 90

    class Towards85:  # a kernel whose best angle is 85 deg, started at -85 deg: 10 deg away across the wrap
        def smooth(self, theta, temperature):
            a = theta["aniso_angle_deg"] * (np.pi / 180)
            return 1 - torch.cos(2 * (a - np.radians(85.0))) + 0 * theta["aniso_ratio"]

    end = refine(space, Towards85(), get_model(pa.model), pa.values | dict(aniso_angle_deg=-85.0, aniso_ratio=1.5), CPU,
                 (0.1,), 20)
    assert end["aniso_angle_deg"] == pytest.approx(85.0, abs=0.5)
    # bounded as before, it stops on the bound at -90 deg
    narrow = pa.with_values()
    narrow.bounds["aniso_angle_deg"] = (-90.0, 0.0)
    assert periods(narrow) == {}
    end = refine(Space(narrow), Towards85(), get_model(pa.model), pa.values | dict(aniso_angle_deg=-85.0, aniso_ratio=1.5),
                 CPU, (0.1,), 20)
    assert end["aniso_angle_deg"] == pytest.approx(-90.0, abs=1e-3)

    class Across:  # the kernel's second moments against those of a ratio of 1.5 at 80 deg, started 90 deg off
        def smooth(self, theta, temperature):
            r, a = theta["aniso_ratio"], theta["aniso_angle_deg"] * (np.pi / 180)

            def moments(r, a):
                c, s = torch.cos(a), torch.sin(a)
                return torch.stack([r * c * c + s * s / r, (r - 1 / r) * c * s, r * s * s + c * c / r])

            target = moments(torch.tensor([1.5]), torch.tensor([np.radians(80.0)], dtype=torch.float32))
            return ((moments(r, a) - target) ** 2).sum(0)

    # the ratio passes through 1 (a round kernel) to the other writing of the same kernel, 1 / 1.5 at -10 deg (with
    # the ratio bounded at 1, a fold fit of bench_fit_recovery seed 20261201's case 2 stopped there, round)
    end = canonical(refine(space, Across(), get_model(pa.model), pa.values | dict(aniso_angle_deg=-10.0, aniso_ratio=1.5),
                           CPU, (0.1,), 30))
    assert end["aniso_ratio"] == pytest.approx(1.5, abs=0.01) and end["aniso_angle_deg"] == pytest.approx(80.0, abs=0.5)
    assert canonical(dict(aniso_ratio=0.5, aniso_angle_deg=30.0)) == dict(aniso_ratio=2.0, aniso_angle_deg=-60.0)

    folds = [dict(aniso_angle_deg=a) for a in (89.5, -89.0, 88.0, -87.5)]
    s = fold_spread(folds, ["aniso_angle_deg"], periods(pa))["aniso_angle_deg"]
    unrolled = [dict(aniso_angle_deg=a) for a in (89.5, 91.0, 88.0, 92.5)]  # the same angles, 1 to 4 deg apart
    assert s == pytest.approx(fold_spread(unrolled, ["aniso_angle_deg"])["aniso_angle_deg"])
    assert fold_spread(folds, ["aniso_angle_deg"])["aniso_angle_deg"] > 80  # not 180 deg apart
    assert on_bounds(folds, pa.bounds, ["aniso_angle_deg"], periods(pa)) == {}
    assert on_bounds(folds, pa.bounds, ["aniso_angle_deg"]) == {"aniso_angle_deg": "upper"}


def _bench(name: str):
    """A benchmark script as a module (benchmarks/<name>.py)."""
    import importlib.util
    import sys

    root = Path(__file__).resolve().parents[1] / "benchmarks"
    sys.path.insert(0, str(root))  # bench_fit_recovery imports its sibling bench_diagnosis
    try:
        spec = importlib.util.spec_from_file_location(name, root / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(root))
    return mod


# (effect, seed of the parameter draw): the benchmark's draw (bench_fit_recovery.draw_truth)
RECOVERY_CASES = [pytest.param("heavy_tail", 11, marks=pytest.mark.xfail(
                      strict=False, reason="The fitted tail (share 0.191 over 39.6 px, the truth's 0.145 over 28.8 px) is "
                      "the optimum of these prints: fitted from the truth it ends there too, with the same objective. But "
                      "the prints do not bound the tail's length from above: the fit stops on its 40 px bound (model.yaml "
                      "flags it, on_bound). Measured 2026-12-03: the test passes (XPASS on two machines): with fold spreads "
                      "(grouped jackknife) of 0.023 and 7.2 px the parameters are 2.0 and 1.5 spreads off (limit 3.18; they "
                      "were 3.9 and 10), and fresh prints are predicted at 1.018 of the truth's error, against the limit of 1.02. "
                      "Kept as a non-strict xfail while the fit lies on a bound with that little margin. With the bound at "
                      "80 px the fold fits scattered from 30 to 67 px and the truth lay 0.8 spreads off, but a wider bound "
                      "costs every heavy-tail fit a larger padding and was not measured on the power study. Left open in #12.")),
                  ("anisotropy", 12), ("dose_nonlinearity", 13), ("illumination_field", 14), ("edge_offset", 15)]


@pytest.mark.slow
@pytest.mark.parametrize("effect, seed", RECOVERY_CASES)
def test_a_candidate_fit_reaches_the_optimum_of_its_family(effect, seed, tmp_path):
    """Prints of Eq. 1 plus one library effect at random parameters, through a dose noise
    correlated over 2 px (as cells give); Eq. 1 calibrated on them, then the diagnosis with
    that one candidate, both with their defaults. The truth is a point of the fitted
    family, so the fit must reach its objective on the prints it was fitted to (above it,
    the fit stopped short of the optimum: with the refinement ending at temperature 0.03
    and a fixed 20 iterations, 5 of 10 fits of bench_fit_recovery's seed 146219 did, up to
    2.6 % above); it must predict fresh prints within 2 % of the truth's error, and its
    parameters must lie within the reported spread of the truth (3.18 spreads: the 95 %
    point of a t with the k - 1 = 3 degrees of freedom of the 4 fold fits)."""
    bench = _bench("bench_fit_recovery")
    rng = np.random.default_rng(seed)
    truth = bench.draw_truth(rng, effect)
    base = default_params("eq1", pixel_size_um=5.0)
    p_true = extend_params(base, [effect]).with_values(**truth)
    masks = trial_masks(24, seed=0, size=160)
    M = np.stack(list(masks.values()))
    prints = simulate(p_true, M, dose_noise=0.03, rng=rng)
    batch = bench._write_batch(tmp_path / "prints", masks, dict(zip(masks, prints)), 5.0)
    calibrate([batch], tmp_path / "cal", seed=0, folds=0, bootstrap=0, residual_maps=False, figure=False, progress=False)
    # the acceptance takes any held-out gain its bootstrap puts above 0: this judges the fit, while the test's
    # power is the power study's (bench_diagnosis); heavy_tail's draw here gains 4.1 % at p 0.028, above max_p
    r = diagnose([batch], tmp_path / "cal" / "params.yaml", tmp_path / "diag", candidates=[effect], figures=False,
                 max_p=1.0, min_improvement=0.0, **QUIET)
    assert r["effects"] == [effect]
    sel = load_params(tmp_path / "diag" / "model.yaml")
    train = float(np.mean(simulate(sel, M) != prints)) / float(np.mean(simulate(p_true, M) != prints))
    assert train <= 1.01, (train, sel.values, truth)
    H = np.stack(list(trial_masks(24, seed=seed + 100, size=160).values()))
    held = simulate(p_true, H, dose_noise=0.03, rng=rng)
    ratio = float(np.mean(simulate(sel, H) != held)) / float(np.mean(simulate(p_true, H) != held))
    assert ratio <= 1.02, (ratio, sel.values, truth)
    tv, fv = bench.canonical(truth), bench.canonical(sel.values)
    spread = sel.info["parameter_extras"]
    for k in (sp.name for sp in EFFECTS[effect].params):
        z = abs(bench.param_error(k, fv[k], tv[k])) / spread[k]["std"]
        assert z <= 3.18, (k, fv[k], tv[k], spread[k]["std"])


def test_power_study_splits_outside_effects_by_what_eq1_leaves_to_find():
    """The power study's outside-effect table: flagged / named / neither, by Eq. 1's pooled
    held-out gap to the floor (an effect that Eq. 1 predicts at the floor leaves nothing to flag)."""
    bench = _bench("bench_diagnosis")

    def lab(gap, unexplained="-", named="-"):
        return dict(effect="outside", named=named, unexplained=unexplained, verdict="x", pooled_iou_eq1=0.9 - gap,
                    pooled_iou_floor=0.9, iou_eq1=0.0, iou_floor=0.0)

    rows = [lab(-0.003), lab(-0.001, named="dose_nonlinearity"), lab(0.002, unexplained="position"), lab(0.015),
            lab(0.012, named="heavy_tail"), lab(0.03, unexplained="grey_level")]
    out = bench.power(rows)
    assert "outside effects flagged unexplained: 2 of 6 (33 %)" in out
    table = {ln.split(":")[0].strip(): ln.split(":")[1].strip() for ln in out if ln.startswith("  ") and ".." in ln}
    assert table == {"-1.000..+0.000": "0 / 1 / 1 of 2", "+0.000..+0.005": "1 / 0 / 0 of 1",
                     "+0.010..+0.020": "0 / 1 / 1 of 2", "+0.020..+1.000": "1 / 0 / 0 of 1"}


def test_held_out_scores_are_means_over_independent_prints_of_each_mask():
    """The power study scores every model against several noisy prints of each held-out
    mask (one print a mask left a lab's gap to the floor a draw): the first is the one print
    of before, the others are other prints, and a model's IoU is the mean over them."""
    from unscatter import metrics
    from unscatter.lab import Printer, load_config

    bench = _bench("bench_diagnosis")
    cfg = load_config()
    printer = Printer(cfg["printer"], 96, float(cfg["batch"]["pixel_size_um"]))
    yy, xx = np.mgrid[:96, :96]
    masks = {"block": np.where((abs(yy - 48) < 20) & (abs(xx - 48) < 20), 255, 0).astype(np.uint8),
             "faint": np.where((xx // 4) % 2 == 0, 150, 0).astype(np.uint8)}
    level = cfg["microscope"]["level"]
    truth, floor = bench.held_out_truth(printer, level, masks, 5, draws=3, votes=5)
    first = bench._lab_truth(printer, level, masks, 5)
    assert all(len(v) == 3 for v in truth.values())
    assert all(np.array_equal(truth[k][0], first[k]) for k in masks)
    assert not np.array_equal(truth["block"][0], truth["block"][1])  # other noise, not the same print again
    ids = list(masks)
    sims = {"first": np.stack([truth[k][0] for k in ids]), "floor": np.stack([floor[k] for k in ids])}
    per_mask, pooled = bench.scored(sims, truth, ids)
    for k in ids:
        assert per_mask[k]["first"] == pytest.approx(np.mean([1.0] + [metrics.iou(truth[k][0], t) for t in truth[k][1:]]))
    assert pooled["floor"] == pytest.approx(np.mean([metrics.pooled_iou(list(sims["floor"]), [truth[k][d] for k in ids])
                                                     for d in range(3)]))
    assert pooled["first"] < 1.0
    # the floor's prints are at the quantiles of the print-to-print dose factor, not at drawn ones: with no other
    # noise its majority is the noise-free print (the middle quantile is the factor 1)
    still = load_config(overrides={"printer": {"cells": {"dose_noise": 0.0}}})
    quiet = load_config(overrides={"printer": {"cells": {"dose_noise": 0.0, "print_to_print": 0.0}}})
    _, floor = bench.held_out_truth(Printer(still["printer"], 96, float(still["batch"]["pixel_size_um"])), level, masks, 5,
                                    draws=1, votes=7)
    noise_free = bench._lab_truth(Printer(quiet["printer"], 96, float(quiet["batch"]["pixel_size_um"])), level, masks, 5)
    assert still["printer"]["cells"]["print_to_print"] > 0.01
    assert all(np.array_equal(floor[k], noise_free[k]) for k in masks)


def _kernel_prints(seed: int = 1) -> SimpleNamespace:
    """16 trial-like masks of 128 x 128 (rectangles at two grey levels) whose every fold's fit
    is a Gaussian kernel of 2 px at a threshold of half the full grey, printed through
    smooth dose noise three ways: with a kernel 30 % wider in every print (``common``), each
    print's kernel 0 to 30 % wider or narrower (``own``; as many of each in every fold), or the fit's kernel
    (``none``)."""
    from scipy import ndimage

    from unscatter.diagnosis import DEFAULTS, geometry

    rng = np.random.default_rng(seed)
    B, n, px = 16, 128, 2.0
    masks = np.zeros((B, n, n), np.uint8)
    for m in masks:
        for _ in range(6):
            y, x = rng.integers(0, n - 20, 2)
            h, w = rng.integers(3, 30, 2)
            m[y:y + h, x:x + w] = rng.choice([160, 255])

    def margin(m, s):
        return ndimage.gaussian_filter(m / 255.0, s) / 0.5 - 1

    def noise():
        e = ndimage.gaussian_filter(rng.standard_normal((n, n)), 1.5)
        return 0.03 * e / e.std()

    fit = np.stack([margin(m, 2.0) for m in masks])
    folds = [np.arange(i, B, 4) for i in range(4)]
    prints = dict(common=np.stack([margin(m, 2.6) + noise() >= 0 for m in masks]),
                  own=np.stack([margin(m, 2.0 * (1 + (-1) ** (i // 4) * rng.uniform(0, 0.3))) + noise() >= 0
                                for i, m in enumerate(masks)]),
                  none=np.stack([f + noise() >= 0 for f in fit]))
    return SimpleNamespace(masks=masks, px=px, geo=geometry(masks, px, DEFAULTS), sims=fit >= 0,
                           margins=np.stack([fit] * len(folds)).astype(np.float16), folds=folds, prints=prints)


def test_kernel_gain_finds_a_kernel_wider_in_every_print_but_not_one_of_each_print_s_own():
    """The kernel's predictive test (the margin corrected by the mask's grey and its means at
    several radii, fitted on training prints) gains where every print was made with a wider
    kernel than the fit's, and not where each print's kernel differs its own way, or not at
    all (its size then the noise of a held-out score: a few per cent of an error that is
    the dose noise alone)."""
    from unscatter.diagnosis import kernel_gain

    for seed in (1, 2):
        k = _kernel_prints(seed)
        g = {name: kernel_gain(k.geo, p, k.sims, k.margins, k.folds) for name, p in k.prints.items()}
        assert g["common"] > 0.3, g
        assert g["own"] < 0.05 and g["none"] < 0.05, g


def test_the_kernel_gain_counts_for_every_diagnostic_but_the_position():
    from unscatter.diagnosis import DEFAULTS, structure_gain, structure_significant

    g = DEFAULTS["structure_gain"]
    t = dict(p_value=0.002, p_dose_profiled=0.5, excess=0.01, predictive_gain=-0.01, kernel_gain=2 * g)
    on, off = dict(DEFAULTS, kernel_correction=True), dict(DEFAULTS, kernel_correction=False)
    assert structure_significant(t, on) and not structure_significant(t, off)
    assert structure_gain(t, on) == 2 * g and structure_gain(t, off) == -0.01
    # the position has no kernel gain (NaN): its own field's gain alone
    pos = dict(t, kernel_gain=float("nan"))
    assert not structure_significant(pos, on)
    # the plain p still gates it
    assert not structure_significant(dict(t, p_value=0.2), on)
