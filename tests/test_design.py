"""Designed trial masks (unscatter.design): the pool, the information, the greedy
D-optimal choice, the sequential inputs and the command."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from unscatter import design as D
from unscatter import masks as M
from unscatter.cli import main
from unscatter.io import list_pngs, read_mask, write_tsv
from unscatter.model import default_params

torch.set_num_threads(1)
SIZE = 128


@pytest.fixture(scope="module")
def params():
    return D.full_params(default_params("eq1"))


def test_pool_is_seeded_and_prints_something():
    a, b = D.candidate_pool(24, seed=2, size=SIZE), D.candidate_pool(24, seed=2, size=SIZE)
    assert list(a) == list(b) and all(np.array_equal(a[k], b[k]) for k in a)
    assert len(a) == 24 and all(m.dtype == np.uint8 and m.shape == (SIZE, SIZE) and m.max() >= 60 for m in a.values())
    c = D.candidate_pool(24, seed=3, size=SIZE)
    assert any(not np.array_equal(a[k], c[k]) for k in a)
    assert {k.rsplit("_", 1)[0] for k in D.candidate_pool(60, seed=0, size=SIZE)} == set(D.POOL_PATTERNS)


def test_full_model_has_every_effect(params):
    assert params.model.count("+") == 5 and "c0" not in params.free and "tail_fraction" in params.free


def test_information_is_zero_without_edges_and_grows_with_them(params):
    U, _ = D.design_prior(params, 1, seed=0)
    blank = np.zeros((SIZE, SIZE), np.uint8)
    block = blank.copy()
    block[40:90, 40:90] = 255
    fine = blank.copy()
    fine[30:100, 30:100] = np.where((np.arange(70) // 5) % 2 == 0, 255, 0)[None, :]
    F = D.information(np.stack([blank, block, fine]), params, U)
    assert F.shape == (1, 3, len(params.free), len(params.free))
    assert np.abs(F[0, 0]).max() < 1e-6 * np.abs(F[0, 1]).max()  # only the smooth threshold's far tail
    for b in (1, 2):
        assert np.allclose(F[0, b], F[0, b].T) and np.linalg.eigvalsh(F[0, b]).min() > -1e-6 * np.abs(F[0, b]).max()
    j = params.free.index("sigma_px")
    assert F[0, 2, j, j] > 2 * F[0, 1, j, j]  # lines 5 px apart tell sigma far better than one block


def test_greedy_has_diminishing_returns_and_prefers_information(params):
    K = len(params.free)
    rng = np.random.default_rng(0)
    G = rng.normal(size=(3, K, K))
    strong = np.einsum("bij,bkj->bik", G, G)
    F = np.stack([strong[0], strong[0], 0.01 * strong[1], strong[2]])[None]  # two copies of one mask
    d = D.greedy(F, ["a", "a2", "weak", "c"], 3, np.eye(K))
    assert "weak" not in d.ids
    assert d.gains == sorted(d.gains, reverse=True)  # log det is submodular: gains never grow
    assert d.sd.shape == (K,) and np.all(d.sd < 1.0)  # tighter than the unit prior


def test_focus_is_the_schur_complement():
    A = np.array([[[4.0, 1.0], [1.0, 2.0]]])
    # information on parameter 0 after parameter 1: 4 - 1 * 1 / 2
    assert D.criterion_d(A, focus=[0], focus_weight=1.0) == pytest.approx(np.log(np.linalg.det(A[0])) + np.log(3.5))


def test_undecided_effects_read_from_the_ranking(tmp_path):
    rows = [dict(round=1, candidate="(control)", accepted="False", ci_hi=0),
            dict(round=1, candidate="heavy_tail", accepted="True", ci_hi=0.01),
            dict(round=2, candidate="(control)", accepted="False", ci_hi=0),
            dict(round=2, candidate="anisotropy", accepted="False", ci_hi=0.002),
            dict(round=2, candidate="edge_offset", accepted="False", ci_hi=-0.001)]
    write_tsv(tmp_path / "ranking.tsv", rows)
    assert D.undecided_effects(tmp_path) == ["anisotropy"]


def test_design_beats_random_paper_masks_on_its_criterion():
    r = D.design_masks(3, pool=10, draws=1, seed=1, size=SIZE, progress=False)
    assert len(r["masks"]) == 3 and r["criterion"] > r["criterion_paper"]
    assert all(row["designed_sd"] < row["prior_sd"] for row in r["sd"])


def test_cli_masks_design(tmp_path):
    out = tmp_path / "designed"
    res = CliRunner().invoke(main, ["masks", "design", str(out), "--count", "2", "--pool", "6", "--draws", "1",
                                    "--size", str(SIZE), "--criterion", "d", "--no-progress"])
    assert res.exit_code == 0, res.output
    masks = list_pngs(out)
    assert list(masks) == ["design_000", "design_001"]
    assert read_mask(masks["design_000"]).shape == (SIZE, SIZE)
    for f in ("design.tsv", "parameters.tsv", "design.yaml", "design.png"):
        assert (out / "design" / f).is_file()
    assert not (out / "design" / "separation.tsv").exists()
    res = CliRunner().invoke(main, ["masks", "design", str(tmp_path / "disc"), "--count", "2", "--pool", "6", "--draws",
                                    "1", "--size", str(SIZE), "--criterion", "discrimination", "--no-progress"])
    assert res.exit_code == 0, res.output
    from unscatter.io import read_tsv

    rows = read_tsv(tmp_path / "disc" / "design" / "separation.tsv")
    assert len(rows) == 25 and {r["rival"] for r in rows} >= {"(none)", "edge_offset"}
    assert not (tmp_path / "disc" / "design" / "paired.tsv").exists()
    # the default criterion is paired (trial_masks.criterion)
    res = CliRunner().invoke(main, ["masks", "design", str(tmp_path / "paired"), "--count", "2", "--pool", "6",
                                    "--draws", "1", "--size", str(SIZE), "--no-progress"])
    assert res.exit_code == 0, res.output
    rows = read_tsv(tmp_path / "paired" / "design" / "paired.tsv")
    assert [r["effect"] for r in rows] == ["heavy_tail", "anisotropy", "dose_nonlinearity", "illumination_field",
                                           "edge_offset"]
    assert all(float(r["designed_t"]) > 0 and float(r["paper_t"]) > 0 for r in rows)
    bad = CliRunner().invoke(main, ["masks", "design", str(tmp_path / "x"), "--count", "9", "--pool", "4"])
    assert bad.exit_code == 2 and "--count" in bad.output and not (tmp_path / "x").exists()


def test_designed_masks_carry_registration_marks_unless_told_not_to():
    marks, clear = M.fiducial_marks(512)
    assert marks.sum() == 3 * M.FIDUCIAL_PX**2 and (clear & ~marks).sum() > 0 and not (marks & ~clear).any()
    # three corners only: no quarter turn maps them onto themselves
    assert all(not np.array_equal(marks, np.rot90(marks, k)) for k in (1, 2, 3))
    pool = D.candidate_pool(12, seed=2, size=SIZE, fiducials=True)
    plain = D.candidate_pool(12, seed=2, size=SIZE)
    m, c = M.fiducial_marks(SIZE)
    for k in pool:
        assert (pool[k][m] == 255).all() and (pool[k][c & ~m] == 0).all()
        assert np.array_equal(pool[k][~c], plain[k][~c])  # the rest of the candidate is untouched
        assert M.carries_marks(pool[k]) and not M.carries_marks(plain[k])
    r = D.design_masks(2, pool=6, draws=1, seed=1, size=SIZE, progress=False, compare=False)
    assert all((mask[m] == 255).all() and M.carries_marks(mask) for mask in r["masks"].values())
    r = D.design_masks(2, pool=6, draws=1, seed=1, size=SIZE, progress=False, compare=False, fiducials=False)
    assert not all((mask[m] == 255).all() for mask in r["masks"].values())


def test_edge_noise_counts_an_edge_by_its_length_not_its_band_of_uncertain_pixels():
    """A straight edge of a margin ramp m = slope x: the weighted squared margin change
    summed across it is (edge shift)^2 / (edge sd^2 CORRELATION_PX) per unit of edge
    length, whatever the ramp's slope while the dose noise dominates, and it falls where
    the floor EDGE_SD_PX dominates. The pixel model counts a shallow edge's wide band as
    more information."""
    per_px, n = 20, 8000
    x = (np.arange(n) - n / 2) / per_px  # 20 samples per design pixel, +-200 px
    out = {}
    for slope in (0.008, 0.016, 1.0):  # margin per design pixel; the margin moved by 0.1 (the threshold by 0.1 T)
        m = torch.as_tensor(slope * x)[None, None, :].repeat(1, 3, 1)
        g = torch.full_like(m, slope)
        wts = D.pixel_weights(m, g, 1 / per_px).reshape(3, n)[1]
        out[slope] = float((0.1 ** 2 * wts).sum() / per_px)  # per design pixel of edge length
        shift, sd = 0.1 / slope, np.hypot(D.DOSE_NOISE / slope, D.EDGE_SD_PX)
        assert out[slope] == pytest.approx(shift ** 2 / (sd ** 2 * D.CORRELATION_PX), rel=0.02)
    assert out[0.008] == pytest.approx(out[0.016], rel=0.1) and out[1.0] < 0.2 * out[0.016]
    pix = D.pixel_weights(m, g, 1 / 20.0, noise="pixel")
    assert torch.allclose(pix, torch.full_like(pix, 1 / (D.PIXEL_VARIANCE * D.CORRELATION_PX ** 2)))
    with pytest.raises(ValueError, match="noise model"):
        D.pixel_weights(m, g, 1, noise="poisson")


def _slanted_edge(sigma, sets, n=160, angle=7.0):
    """Margins (P, 1, h, w) and the first set's |grad m| of a half-plane mask whose edge is
    slanted by ``angle`` degrees (so it crosses the design's 2-px grid at every sub-pixel
    place), Eq. 1 with an edge offset at kernel ``sigma``, on every 2nd pixel; ``sets``:
    {name: value} changes of each parameter set."""
    from unscatter.model import FixedMasks, extend_params, get_model, masks_to_tensor

    params = extend_params(default_params("eq1"), ["edge_offset"])
    model = get_model(params.model)
    yy, xx = np.mgrid[0:n, 0:n]
    mask = ((xx - n / 2) - np.tan(np.radians(angle)) * (yy - n / 2) > 0).astype(np.uint8) * 255
    vals = [{**params.values, "sigma_px": sigma, **change} for change in sets]
    theta = model.theta({k: [v[k] for v in vals] for k in model.names}, "cpu")
    sim = FixedMasks(model, masks_to_tensor(mask[None], "cpu"), support_px=4 * sigma + 2).decimated(2)
    dose, gy, gx = sim.dose(theta, gradient=True)
    T = theta["T"].double().reshape(-1, 1, 1, 1)
    g = torch.sqrt(gx[0].double() ** 2 + gy[0].double() ** 2) / T[0]
    inner = (slice(None), slice(n // 4 - 24, n // 4 + 24), slice(n // 4 - 24, n // 4 + 24))  # 96 x 96 px, far from the borders
    return (dose.double() / T - 1)[(slice(None),) + inner], g[inner], float(params.values["T"])


def test_edge_weights_hold_on_the_design_grid_wherever_the_edge_falls():
    """On the 2-px grid a sharp edge falls anywhere between samples. The information of a
    slanted edge about its own shift (an edge offset) per unit length is the edge model's
    1 / (CORRELATION_PX (DOSE_NOISE^2 / g^2 + EDGE_SD_PX^2)), g the margin's slope at the
    edge: within 30 % below at sigma 1.5 px, 12 % at 3 px and 3 % at 8 px (the weights
    reach half a sample beyond the edge, where the margin's slope is lower), and within
    25 % from one row of the grid to the next. The same with the edge already moved by
    an edge offset of 2 px (the prior's largest), whose margin's slope is the chain
    rule's (``blur_spectrum(gradient=True)``; the blurred dose's slope alone put the
    information at 0.5 of the model's at sigma 1.5 px). Taken from the thresholded print,
    the weights were 3.4 and 1.8 times too high at sigma 1.5 and 3 px, and up to 20 times
    at one place."""
    from scipy.optimize import brentq
    from scipy.stats import norm

    for sigma, e0, low, high, spread in ((1.5, 0.0, 0.7, 1.02, 1.25), (3.0, 0.0, 0.88, 1.02, 1.25),
                                         (8.0, 0.0, 0.97, 1.02, 1.25), (3.0, 2.0, 0.9, 1.02, 1.25),
                                         (3.0, -2.0, 0.9, 1.02, 1.25), (8.0, 2.0, 0.97, 1.02, 1.25),
                                         (1.5, 2.0, 0.9, 1.15, 2.1), (1.5, -2.0, 0.9, 1.15, 2.1)):
        m, g, T = _slanted_edge(sigma, [{"edge_offset_px": e0}, {"edge_offset_px": e0 + 0.01}])
        J = (m[1] - m[0]) / 0.01
        w = D.pixel_weights(m[0], g, 2).reshape(m[0].shape)
        rows = (w * J ** 2).sum(-1)[0] * 2 * 2 / (2 / np.cos(np.radians(7.0)))  # per design pixel of edge length
        # the blurred step's dose (the full mask's dose is 1) plus e0 |grad D|: its edge u, slope there, and dm/de
        u = brentq(lambda u: norm.cdf(u) + e0 * norm.pdf(u) / sigma - T, -8, 8)
        slope = (norm.pdf(u) / sigma - e0 * u * norm.pdf(u) / sigma ** 2) / T
        shift = norm.pdf(u) / sigma / T
        expect = shift ** 2 / (D.CORRELATION_PX * (D.DOSE_NOISE ** 2 + (D.EDGE_SD_PX * slope) ** 2))
        ratio = float(rows.mean()) / expect
        assert low <= ratio <= high, (sigma, e0, ratio)
        assert float(rows.max() / rows.min()) < spread, (sigma, e0)


def test_an_edge_offset_is_nearly_a_change_of_T_on_one_edge():
    """On one straight edge an edge offset and a change of T both only move the edge: the
    discrimination's lack of fit of one by the other is small on the margin (below 25 %
    of the effect's squared change at sigma 1.5 px, 10 % at 3 px, 3 % at 8 px). On the
    thresholded print the finite change of a 1-px shift is not linear in the derivative
    of T, and left 60 %, 34 % and 10 %."""
    for sigma, most in ((1.5, 0.25), (3.0, 0.1), (8.0, 0.03)):
        m, g, T = _slanted_edge(sigma, [{}, {"edge_offset_px": 1.0}, {"T": 0.501}])
        shares = {}
        for noise in ("edge", "pixel"):
            p = D.response(m, noise)
            C = torch.stack([(p[2] - p[0]) / 1e-3, p[1] - p[0]]).flatten(2)
            G = D._gram(C, D.pixel_weights(m[0], g, 2, noise))[0].numpy()
            shares[noise] = (G[1, 1] - G[0, 1] ** 2 / G[0, 0]) / G[1, 1]
        assert shares["edge"] < most and shares["pixel"] > 2 * shares["edge"], (sigma, shares)


def test_a_prints_dose_is_profiled_out_of_its_information():
    """Each print's overall dose is a nuisance of PRINT_DOSE_SD: a column that is the
    dose's own change keeps only what the prior on the dose leaves of it, a column
    orthogonal to it (in the weighted sum) keeps all of its information."""
    m, g, _ = _slanted_edge(3.0, [{}])
    m0 = m[0]
    w = D.pixel_weights(m0, g, 2)
    dose = (m0 + 1.0).flatten(1)
    other = torch.randn_like(dose)
    other -= (other * dose * w).sum() / (dose * dose * w).sum() * dose  # orthogonal in the weighted sum
    G = D.print_gram(torch.stack([dose, other]), m0, g, 2)[0]
    raw = D._gram(torch.stack([dose, other]), w)[0] * 4
    a = float(raw[0, 0])
    assert float(G[0, 0]) == pytest.approx(a / (1 + a * D.PRINT_DOSE_SD ** 2), rel=1e-6)
    assert float(G[1, 1]) == pytest.approx(float(raw[1, 1]), rel=1e-6)
    assert float(G[0, 1]) == pytest.approx(0.0, abs=1e-9 * a)
    cols = torch.stack([dose, other])  # the pixel model has no dose nuisance
    assert torch.allclose(D.print_gram(cols, m0, g, 2, noise="pixel"), D._gram(cols, D.pixel_weights(m0, g, 2, "pixel")) * 4)


def _rivals(K=3):
    # parameters 0..K-1: 0 and 1 belong to no effect, 2 is effect "b"'s; effects "a" (no parameter
    # among the free ones but its column) and "b"
    return D.Rivals(names=[f"p{i}" for i in range(K)], effects=["a", "b"], own={"a": [], "b": [2]}, base=[0, 1],
                    prior_precision=np.full(K, 1e-9))


def test_separation_is_what_the_rival_cannot_fit():
    rng = np.random.default_rng(1)
    n = 400
    base = rng.normal(size=(n, 2))
    b_par = rng.normal(size=n)
    d_b = rng.normal(size=n)
    inside = base @ np.array([0.7, -1.3]) + 0.5 * b_par  # effect a: Eq. 1 plus effect b's parameter reproduce it
    apart = rng.normal(size=n)
    apart -= np.column_stack([base, b_par, d_b]) @ np.linalg.lstsq(np.column_stack([base, b_par, d_b]), apart, rcond=None)[0]
    rv = _rivals()
    for d_a, expect_none, expect_b in ((inside, None, 0.0), (apart, float(apart @ apart), float(apart @ apart))):
        C = np.column_stack([base, b_par, d_a, d_b])
        G = (C.T @ C)[None]  # one draw
        T = D.separation(G, rv)
        if expect_none is None:
            assert T[("a", None)][0] > 0.01 * float(d_a @ d_a)  # Eq. 1 alone cannot fit effect b's part
        else:
            assert T[("a", None)][0] == pytest.approx(expect_none, rel=1e-6)
        assert T[("a", "b")][0] == pytest.approx(expect_b, abs=1e-6 * float(d_a @ d_a))
    # the criterion rewards separating: the apart effect scores higher
    Ci = np.column_stack([base, b_par, inside, d_b])
    Ca = np.column_stack([base, b_par, apart * np.linalg.norm(inside) / np.linalg.norm(apart), d_b])
    assert D.discrimination((Ca.T @ Ca)[None], rv) > D.discrimination((Ci.T @ Ci)[None], rv)


def test_rivals_are_the_effects_the_model_lacks(params):
    U, sd = D.design_prior(params, 1, seed=0)
    rv = D.rivals_of(params, sd)
    assert rv.effects == ["heavy_tail", "anisotropy", "dose_nonlinearity", "illumination_field", "edge_offset"]
    assert [rv.names[j] for j in rv.base] == [k for k in params.free if k in ("c1", "c2", "c3", "c4", "sigma_px", "T")]
    fitted = params.with_values(dose_gamma=1.2)
    assert "dose_nonlinearity" not in D.rivals_of(fitted, sd).effects
    assert len(rv.pairs()) == 5 * 5


def test_discrimination_design_separates_effects_better_than_random_paper_masks():
    r = D.design_masks(3, pool=10, draws=1, seed=1, size=SIZE, progress=False, criterion="discrimination")
    assert len(r["masks"]) == 3 and r["criterion"] > r["criterion_paper"]
    rows = r["separation"]
    assert len(rows) == 25 and all(row["designed"] >= 0 and row["paper"] >= 0 for row in rows)
    assert np.mean([np.log1p(row["designed"]) for row in rows]) > np.mean([np.log1p(row["paper"]) for row in rows])


def test_the_paired_criterion_prefers_evidence_spread_over_prints_to_the_same_evidence_in_one():
    """The diagnosis accepts an effect by a paired test over prints: four prints that each
    show a quarter of an effect's change beat one print that shows all of it beside three
    that show none, though the design's total lack of fit is the same."""
    rv = D.Rivals(names=["p0"], effects=["a"], own={"a": []}, base=[0], prior_precision=np.array([1.0]))
    rng = np.random.default_rng(0)
    c, d = rng.standard_normal(50), rng.standard_normal(50)

    def gram(scale_d):
        C = np.column_stack([c, scale_d * d])
        return C.T @ C

    spread = np.stack([gram(0.5)] * 4)[None]  # (S=1, n=4, 2, 2): a quarter of d'd in each print
    one = np.stack([gram(1.0)] + [gram(0.0)] * 3)[None]
    assert spread.sum(1)[0, 1, 1] == pytest.approx(one.sum(1)[0, 1, 1])
    assert D.paired(spread, rv) > D.paired(one, rv) + 0.5
    # the prints' lack of fit sums to the design's (``separation``) less the rival prior's share
    for G in (spread, one):
        T = D.per_print_lack_of_fit(G, rv)["a"]
        Gs = G.sum(1)[0]
        beta = Gs[0, 1] / (Gs[0, 0] + 1.0)
        assert T.sum() + beta * 1.0 * beta == pytest.approx(D.separation(G.sum(1), rv)[("a", None)][0])


def test_a_paired_design_spreads_each_effects_evidence_over_the_prints_more_than_the_d_design():
    kw = dict(pool=24, draws=1, seed=2, size=SIZE, progress=False, compare=False)
    r_d, r_p = D.design_masks(4, criterion="d", **kw), D.design_masks(4, criterion="paired", **kw)
    params = D.full_params(default_params("eq1"))
    U, sd = D.design_prior(params, 1, seed=2)
    rv = D.rivals_of(params, sd)
    value = {k: float(D.paired(D.discrimination_gram(r["masks"], params, U, rv, seed=2), rv))
             for k, r in (("d", r_d), ("paired", r_p))}
    assert value["paired"] > value["d"]
    assert len(r_p["masks"]) == 4 and len(r_p["design"].separation) == 25
    assert [row["effect"] for row in r_p["paired"]] == rv.effects and not r_d["paired"]


def test_a_paired_design_counts_each_print_already_made(params):
    """Sequential design: the prints already made enter the paired test print by print,
    and the design's criterion is that of all of them together."""
    U, sd = D.design_prior(params, 1, seed=6)
    rv = D.rivals_of(params, sd)
    cands = D.candidate_pool(6, seed=7, size=SIZE)
    F = D.information(cands, params, U)
    G = D.discrimination_gram(cands, params, U, rv, seed=6)
    prior = np.diag(1.0 / sd**2)
    made = [0, 1]  # two prints already made: the first two candidates
    rest = [i for i in range(6) if i not in made]
    d = D.greedy(F[:, rest], [list(cands)[i] for i in rest], 2, prior, start=F[:, made].sum(axis=1),
                 G=G[:, rest], rivals=rv, G_start=G[:, made], kind="paired")
    idx = made + [list(cands).index(c) for c in d.ids]
    A = prior[None] + F[:, idx].sum(axis=1)
    assert d.criterion == pytest.approx(float(D.criterion_d(A) + D.paired(G[:, idx], rv)), rel=1e-9)
    alone = D.greedy(F[:, rest], [list(cands)[i] for i in rest], 2, prior, start=F[:, made].sum(axis=1),
                     G=G[:, rest], rivals=rv, kind="paired")
    assert alone.criterion != pytest.approx(d.criterion, rel=1e-6)


def test_separation_counts_the_rivals_prior_precision():
    """One rival column c and an effect d = c: the penalised fit leaves d'd lam / (c'c + lam)."""
    rv = D.Rivals(names=["p0"], effects=["a"], own={"a": []}, base=[0], prior_precision=np.array([2.0]))
    G = np.array([[[4.0, 4.0], [4.0, 4.0]]])  # c'c = c'd = d'd = 4
    assert D.separation(G, rv)[("a", None)][0] == pytest.approx(4.0 * 2.0 / (4.0 + 2.0))


def test_discrimination_grams_parameter_block_is_the_information_with_the_effects_neutral(params):
    U, sd = D.design_prior(params, 1, seed=3)
    rv = D.rivals_of(params, sd)
    masks = D.candidate_pool(3, seed=4, size=SIZE)
    G = D.discrimination_gram(masks, params, U, rv, seed=5)
    K = len(params.free)
    assert G.shape == (1, 3, K + len(rv.effects), K + len(rv.effects))
    U0 = D.null_point(params, U, rv)
    assert np.array_equal(U0[:, rv.base], U[:, rv.base])
    assert all(U0[0, j] == pytest.approx((params.values[params.free[j]] - params.bounds[params.free[j]][0])
                                         / np.subtract(*params.bounds[params.free[j]][::-1]))
               for e in rv.effects for j in rv.own[e])
    F0 = D.information(masks, params, U0)
    # equal up to float32 rounding (the effects' sizes widen the FFT padding)
    assert np.allclose(G[:, :, :K, :K], F0, rtol=1e-3, atol=1e-5 * np.abs(F0).max())
    F = D.information(masks, params, U)  # at the draw, effects present: not the null point
    assert not np.allclose(G[:, :, :K, :K], F, rtol=1e-3, atol=1e-5 * np.abs(F).max())
    eff = np.diagonal(G[0], axis1=-2, axis2=-1)[:, K:]  # each effect's squared print change
    assert np.all(eff > 0) and np.allclose(G, np.swapaxes(G, -1, -2))
