"""Calibration of Eq. 1 on virtual-lab prints whose printer is exactly Eq. 1 (plus the
lab's cell-to-cell dose noise), and the handling of bad inputs."""

from __future__ import annotations

import os
import shutil
from types import SimpleNamespace

import numpy as np
import pytest

from unscatter import metrics
from unscatter.calibration import calibrate
from unscatter.prints import load_prints
from unscatter.io import InputError, read_mask, read_tsv, read_yaml, write_png, write_tsv, write_yaml
from unscatter.masks import trial_masks
from unscatter.model import design_coords, load_params

# the lab with every effect beyond Eq. 1 switched off
EQ1_LAB = {"printer": {"kernel": {"heavy_tail": None, "anisotropy": {"ratio": 1.0, "angle_deg": 0.0}},
                       "illumination": {"quartic": 0.0, "hotspot": None}, "dose_gamma": 1.0, "edge_offset_um": 0.0}}
FAST = dict(population=12, generations=4, folds=0, bootstrap=0, residual_maps=False, figure=False, progress=False)


def write_prints_dir(out, prints: dict, mask_paths: dict, status=None, pixel_size_um=2.96):
    """A registration-output-like folder: <id>.png, qc.tsv (mask paths relative), batch.yaml."""
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for mid, pr in prints.items():
        st = (status or {}).get(mid) or ("ok" if pr is not None and pr.any() else "empty")
        if pr is not None:
            write_png(out / f"{mid}.png", pr)
        rel = os.path.relpath(mask_paths[mid], out)  # relative to the prints folder, as registration writes it
        rows.append(dict(id=mid, status=st, reason="", mask=rel))
    write_tsv(out / "qc.tsv", rows, ["id", "status", "reason", "mask"])
    write_yaml(out / "batch.yaml", dict(pixel_size_um=pixel_size_um, material="test"))
    return out


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    from unscatter.lab import Printer, load_config

    root = tmp_path_factory.mktemp("lab")
    cfg = load_config(overrides=EQ1_LAB)
    px = cfg["batch"]["pixel_size_um"]
    printer = Printer(cfg["printer"], 512, px)
    level = cfg["microscope"]["level"]
    masks = trial_masks(32, seed=0, size=512)
    mask_paths, A, B = {}, {}, {}
    for i, (mid, m) in enumerate(masks.items()):
        mask_paths[mid] = root / "masks" / f"{mid}.png"
        write_png(mask_paths[mid], m)
        # two prints of every mask with different lab randomness: the noise floor
        A[mid] = printer.crop(printer.density(m, np.random.default_rng([1, i]))) >= level
        B[mid] = printer.crop(printer.density(m, np.random.default_rng([2, i]))) >= level
    il, pc = cfg["printer"]["illumination"], cfg["printer"]
    truth = dict(c0=1.0, c1=il["cx2"], c2=il["cy2"], c3=il["cx"], c4=il["cy"],
                 sigma_px=pc["kernel"]["sigma_um"] / px, T=pc["cure"]["threshold"])
    floor = float(np.mean([metrics.iou(A[k], B[k]) for k in masks]))
    ids8 = list(masks)[:8]
    return SimpleNamespace(
        root=root, masks=masks, mask_paths=mask_paths, prints=A, truth=truth, floor=floor,
        dir=write_prints_dir(root / "prints", A, mask_paths),
        dir8=write_prints_dir(root / "prints8", {k: A[k] for k in ids8}, mask_paths),
    )


@pytest.fixture(scope="module")
def calibrated(lab, tmp_path_factory):
    out = tmp_path_factory.mktemp("calibration")
    params = calibrate([lab.dir], out, seed=0, folds=4, bootstrap=6, progress=False)
    return SimpleNamespace(params=params, out=out)


# ------------------------------------------------------------------- recovery


def test_recovers_sigma_and_threshold(lab, calibrated):
    v, t = calibrated.params.values, lab.truth
    assert v["c0"] == 1.0  # the gauge
    assert abs(v["sigma_px"] / t["sigma_px"] - 1) < 0.05
    assert abs(v["T"] / t["T"] - 1) < 0.03
    # the illumination field, compared as a field (its coefficients trade off a little)
    x = design_coords(64).double().numpy()
    X, Y = np.meshgrid(x, x)

    def field(c):
        return c["c0"] + c["c1"] * X**2 + c["c2"] * Y**2 + c["c3"] * X + c["c4"] * Y

    assert np.abs(field(v) - field(t)).max() < 0.04


def test_heldout_iou_reaches_the_labs_noise_floor(lab, calibrated):
    val = calibrated.params.info["validation"]
    assert val["folds"] == 4
    # the model is the noise-free mean print, so it may match a print better than a
    # second print of the same mask does; it must not be worse by more than a little
    assert val["heldout_iou_mean"] >= lab.floor - 0.01
    assert abs(val["heldout_iou_mean"] - val["in_sample_iou_mean"]) < 0.005  # no overfitting
    rows = read_tsv(calibrated.out / "cv.tsv")
    assert len(rows) == 32 and {r["id"] for r in rows} == set(lab.masks)
    assert np.mean([float(r["iou"]) for r in rows]) == pytest.approx(val["heldout_iou_mean"], abs=1e-5)
    # the mask itself, the baseline: scattering rounds and grows these prints, so the model beats it by far
    mb = val["mask_baseline"]
    assert val["beats_mask"] and val["heldout_error"] < 0.5 * mb["heldout_error"]
    assert val["heldout_iou_pooled"] > mb["heldout_iou_pooled"] + 0.03
    assert np.mean([float(r["mask_iou"]) for r in rows]) == pytest.approx(mb["heldout_iou_mean"], abs=1e-5)
    # each fold's threshold is chosen on the other folds' prints, never on its own
    from unscatter.fitting import mask_threshold

    data = load_prints(lab.dir)
    at = {lab_id: j for j, lab_id in enumerate(data.labels)}
    for fold in {r["fold"] for r in rows}:
        train = [at[r["id"]] for r in rows if r["fold"] != fold]
        ts = {int(r["mask_threshold"]) for r in rows if r["fold"] == fold}
        assert ts == {mask_threshold(data.masks[train], data.prints[train])}


def test_the_mask_warnings_say_which_way_the_model_loses():
    from unscatter.calibration import _against_mask

    cv = dict(heldout_error=0.010, heldout_iou_mean=0.90, heldout_iou_pooled=0.92, beats_mask=True,
              mask_baseline=dict(heldout_error=0.020, heldout_iou_mean=0.80, heldout_iou_pooled=0.85, thresholds=[128],
                                 iou_better_p=0.9))
    assert _against_mask("eq1", cv, "mismatch") == []  # better by both
    lost = _against_mask("eq1", dict(cv, beats_mask=False), "mismatch")
    assert len(lost) == 1 and "no better than the mask itself" in lost[0] and ">= 128" in lost[0]
    disagree = _against_mask("eq1", dict(cv, mask_baseline=dict(cv["mask_baseline"], iou_better_p=0.01)), "mismatch")
    assert len(disagree) == 1 and "objective and the score disagree" in disagree[0] and "p 0.01" in disagree[0]
    assert _against_mask("eq1", dict(folds=0, note="cross-validation off"), "mismatch") == []


def test_prints_that_are_the_mask_itself_are_not_beaten_and_it_says_so(tmp_path):
    """Prints that are their masks thresholded and shifted by up to 2 px (no scattering,
    nothing Eq. 1 models): the calibrated model does no better than the mask itself on
    held-out prints, and the calibration says so instead of handing on a model that
    compensates for scattering that is not there."""
    rng = np.random.default_rng(5)
    masks = trial_masks(16, seed=3, size=256)
    paths = {k: tmp_path / "masks" / f"{k}.png" for k in masks}
    for k, m in masks.items():
        write_png(paths[k], m)
    prints = {k: np.roll(m >= 128, tuple(rng.integers(-2, 3, 2)), (0, 1)) for k, m in masks.items()}
    d = write_prints_dir(tmp_path / "prints", prints, paths)
    with pytest.warns(UserWarning, match="no better than the mask itself"):
        params = calibrate([d], tmp_path / "cal", seed=0, **dict(FAST, folds=4))
    val = params.info["validation"]
    assert not val["beats_mask"] and val["mask_baseline"]["thresholds"] and all(
        64 < t <= 192 for t in val["mask_baseline"]["thresholds"])
    assert any("no better than the mask itself" in w for w in params.info["warnings"])
    # the diagnosis finds no effect that does better, and says so
    from unscatter.diagnosis import diagnose

    r = diagnose([d], tmp_path / "cal", tmp_path / "diag", quick=True, seed=0, candidates=["edge_offset"], folds=2,
                 figures=False, progress=False, workers=1)
    assert not r["beats_mask"] and r["after"]["heldout_error"] >= r["mask"]["heldout_error"]
    assert "**No model beats the mask itself**" in (tmp_path / "diag" / "report.md").read_text()


def test_a_sigma_within_the_microscopes_blur_is_not_taken_for_scattering(lab, tmp_path):
    """Where the registration measured a microscope blur as large as the fitted sigma, the
    prints do not resolve the scattering: the calibration says so (fitted as the cure; the
    default fits such prints again through the measurement: tests/test_measurement.py).
    A blur well below it (and prints without a registration.yaml) give no such warning."""
    ids = list(lab.masks)[:12]
    d = write_prints_dir(tmp_path / "prints", {k: lab.prints[k] for k in ids}, lab.mask_paths)
    sigma = lab.truth["sigma_px"]
    for blur, resolved in ((1.2 * sigma, False), (0.3 * sigma, True), (None, None)):
        if blur is not None:
            write_yaml(d / "registration.yaml", dict(measurement=dict(blur_px=blur, smoothing_px=0.5, gel_share=0.6,
                                                                      level=0.5)))
        params = calibrate([d], tmp_path / f"cal{blur}", seed=0, measurement="none", **FAST)
        res = params.info["validation"].get("resolution")
        warned = any("do not resolve the scattering" in w for w in params.info["warnings"])
        if blur is None:
            assert res is None and not warned
            continue
        assert res["resolved"] is resolved and warned is (not resolved)
        assert res["measurement_blur_px"] == pytest.approx(np.hypot(blur, 0.5), abs=1e-3)
        assert abs(res["sigma_px"] / sigma - 1) < 0.1
        (d / "registration.yaml").unlink()


def test_the_mask_threshold_is_the_objectives_best_grey_level():
    from unscatter.fitting import mask_threshold, per_print_error

    rng = np.random.default_rng(0)
    w = rng.uniform(0.5, 2.0, 5)
    for levels in (256, 5):  # every grey level, or a few (ties: the middle of the first run of best t)
        masks = (rng.integers(0, levels, (5, 24, 24)) * (255 // (levels - 1))).astype(np.uint8)
        prints = masks.astype(float) + rng.normal(0, 40, masks.shape) >= 150
        for objective, weights in (("mismatch", None), ("dice", None), ("pixel_error", w)):
            e = np.array([per_print_error(masks >= t, prints, objective, weights=weights).mean() for t in range(1, 257)])
            best = np.flatnonzero(e == e.min())
            first = np.split(best, np.flatnonzero(np.diff(best) > 1) + 1)[0]
            assert mask_threshold(masks, prints, objective, weights=weights) == first[len(first) // 2] + 1
            if levels == 5:
                assert len(first) > 1  # the ties are there to break
    assert mask_threshold(masks, masks >= 100) == 95  # between the levels present, 63 and 126: the middle
    full = np.arange(256, dtype=np.uint8).reshape(1, 16, 16)
    assert mask_threshold(full, full >= 100) == 100  # every level present: exact
    assert mask_threshold(full, np.zeros(full.shape, bool)) == 256  # nothing prints
    with pytest.raises(ValueError, match="no prints"):
        mask_threshold(masks[:0], prints[:0])


def test_outputs(lab, calibrated):
    out = calibrated.out
    d = read_yaml(out / "params.yaml")
    assert d["model"] == "eq1" and "c0 is fixed to 1" in d["gauge"]
    assert d["data"]["prints"] == 32 and d["data"]["ids"] == list(lab.masks)
    assert d["data"]["prints_dirs"] == [str(lab.dir.resolve())]
    assert d["objective"]["value"] <= d["objective"]["ga"]
    assert d["fit"]["on_bound"] == [] and d["warnings"] == []
    for k in ("c1", "c2", "c3", "c4", "sigma_px", "T"):
        e = d["parameters"][k]
        assert e["std"] > 0 and e["q05"] <= e["q95"], k
    assert d["uncertainty"]["used"] == 6
    assert "std" not in d["parameters"]["c0"]
    assert calibrated.params.info["parameter_extras"]["sigma_px"]["std"] == d["parameters"]["sigma_px"]["std"]
    hist = read_tsv(out / "history.tsv")
    assert [int(r["generation"]) for r in hist] == list(range(31))
    best = [float(r["best"]) for r in hist]
    assert all(a >= b for a, b in zip(best, best[1:]))  # elitism: the best never gets worse
    res = sorted((out / "residuals").glob("*.png"))
    assert len(res) == 32
    from PIL import Image

    with Image.open(res[0]) as im:
        assert im.mode == "RGB" and im.size == (512, 512)
    assert (out / "fit.png").stat().st_size > 10_000
    assert len(read_tsv(out / "bootstrap.tsv")) == 6


def test_simulate_dir_reproduces_the_fit(lab, calibrated, tmp_path):
    from unscatter.calibration import simulate_dir

    masks = tmp_path / "m"
    masks.mkdir()
    for k in list(lab.masks)[:3]:
        shutil.copy(lab.mask_paths[k], masks / f"{k}.png")
    paths = simulate_dir(calibrated.out / "params.yaml", masks, tmp_path / "sim")
    assert [p.name for p in paths] == [f"{k}.png" for k in list(lab.masks)[:3]]
    sim = read_mask(paths[0])
    assert set(np.unique(sim)) <= {0, 255}
    in_sample = {r["id"]: float(r["in_sample_iou"]) for r in read_tsv(calibrated.out / "cv.tsv")}
    for p in paths:  # the same prints the calibration scored
        assert metrics.iou(read_mask(p) > 0, lab.prints[p.stem]) == pytest.approx(in_sample[p.stem], abs=1e-5)


def test_seeded_runs_are_reproducible(lab, tmp_path):
    a = calibrate([lab.dir8], tmp_path / "a", seed=3, **FAST)
    b = calibrate([lab.dir8], tmp_path / "b", seed=3, **FAST)
    assert a.values == b.values
    assert read_tsv(tmp_path / "a" / "history.tsv") == read_tsv(tmp_path / "b" / "history.tsv")


def test_refits_in_worker_processes_give_the_same_calibration_as_in_one(lab, tmp_path, caplog):
    """The refits of the folds and the bootstrap run in worker processes (``workers``);
    each depends only on its prints, weights and seed, so the held-out metrics and the
    bootstrap's parameters are those of one process, to the last digit."""
    runs = {}
    for w in (1, 2):
        caplog.clear()
        with caplog.at_level("INFO", logger="unscatter.fitting"):
            p = calibrate([lab.dir8], tmp_path / f"w{w}", seed=3, **dict(FAST, folds=2, bootstrap=3), workers=w)
        assert ("the refits run in 2 worker processes" in caplog.text) == (w == 2)
        assert "worker processes stopped" not in caplog.text
        boot = read_tsv(tmp_path / f"w{w}" / "bootstrap.tsv")
        runs[w] = (p.values, read_tsv(tmp_path / f"w{w}" / "cv.tsv"), boot, p.info["parameter_extras"])
        assert len(boot) == 3 and len(runs[w][1]) == 8
    assert runs[2] == runs[1]


def test_bounds_that_exclude_the_optimum_are_flagged(lab, tmp_path):
    with pytest.warns(UserWarning, match="sigma_px .* upper bound"):
        p = calibrate([lab.dir8], tmp_path, bounds={"sigma_px": (0.5, 2.0)}, **FAST)
    assert p.info["fit"]["on_bound"] == ["sigma_px"]
    d = read_yaml(tmp_path / "params.yaml")
    assert d["parameters"]["sigma_px"]["on_bound"] == "upper"
    assert any("sigma_px" in w for w in d["warnings"])


def test_unknown_setting_is_an_error(lab, tmp_path):
    with pytest.raises(TypeError, match="unknown calibration setting"):
        calibrate([lab.dir8], tmp_path, populaton=3)


def test_unknown_objective_is_an_error(lab, tmp_path):
    with pytest.raises(ValueError, match="calibration.objective: 'iou' is not one of mismatch"):
        calibrate([lab.dir8], tmp_path, objective="iou", **FAST)


# ------------------------------------------------------------------ objectives


def test_per_print_objectives_pixel_error_and_dice():
    """The per-print objectives. pixel_error: the weighted mismatch equals the mean over prints of each
    print's pixel error |measured XOR simulated| / max(|measured|, floor x pixels), so a
    thin print weighs as much as a large one; the paper's mismatch weighs them equally
    per pixel. Subsets (folds, bootstrap resamples) keep the weights. dice: 1 - Dice per
    print."""
    import torch

    from unscatter.fitting import Objective, build_objective, per_print_error, print_weights
    from unscatter.model import FixedMasks, get_model, masks_to_tensor

    cpu = torch.device("cpu")
    m = get_model("eq1")
    masks = np.stack(list(trial_masks(6, seed=4, size=64).values()))
    masks[5] = 0
    masks[5, 30:34, 10:50] = 255  # a thin line: a small print
    values = dict(c0=1.0, c1=-0.05, c2=0.0, c3=0.02, c4=0.0, sigma_px=1.5, T=0.5)
    sim = FixedMasks(m, masks_to_tensor(masks, cpu), support_px=12)
    with torch.no_grad():
        measured = sim.prints(m.theta(values, cpu))[0].numpy()
        other = m.theta(dict(values, sigma_px=2.2, T=0.45), cpu)
        simulated = sim.prints(other)[0].numpy()
    npx = measured[0].size
    area = measured.reshape(6, -1).sum(axis=1)
    assert area[5] < 0.25 * area[:5].mean() and area.min() > 0.02 * npx
    w = print_weights(measured, "pixel_error", 0.02)
    assert w.mean() == pytest.approx(1.0)
    np.testing.assert_allclose(w * area, w[0] * area[0])  # inverse to the printed area
    assert print_weights(measured, "pixel_error", 0.1)[5] == pytest.approx(print_weights(measured, "pixel_error", 0.1)[1])
    np.testing.assert_array_equal(print_weights(measured, "mismatch"), np.ones(6))
    xor = (measured != simulated).reshape(6, -1).sum(axis=1)
    obj = Objective.build(sim, measured, 1, w)
    # the mean pixel error over the mean of 1 / area (the weights are normalised)
    assert obj.hard(other)[0] == pytest.approx(np.mean(xor / area) / np.mean(1 / area) / npx, rel=1e-5)
    paper = Objective.build(sim, measured, 1)
    assert paper.hard(other)[0] == pytest.approx(xor.mean() / npx, rel=1e-5)
    sub = obj.subset([1, 5], [2.0, 1.0])
    expect = np.average(xor[[1, 5]] / npx, weights=w[[1, 5]] * [2.0, 1.0])
    assert sub.hard(other)[0] == pytest.approx(expect, rel=1e-5)
    with pytest.raises(ValueError, match="unknown objective"):
        print_weights(measured, "iou")
    # 1 - Dice per print (IoU's twin), hard and smooth, and its per-print errors
    dice = build_objective(sim, measured, 1, "dice", 0.02)
    ssum = simulated.reshape(6, -1).sum(axis=1)
    expect = xor / (area + ssum + 0.02 * npx)
    assert dice.hard(other)[0] == pytest.approx(expect.mean(), rel=1e-5)
    np.testing.assert_allclose(per_print_error(simulated, measured, "dice", 0.02), expect)
    assert float(dice.smooth(other, 0.01)[0]) == pytest.approx(expect.mean(), rel=0.05)
    assert float(dice.subset([1, 5]).hard(other)[0]) == pytest.approx(expect[[1, 5]].mean(), rel=1e-5)


# ------------------------------------------------------------------ bad input


def _small(tmp_path, n=4, size=64, seed=0):
    masks = trial_masks(n, seed=seed, size=size)
    paths = {}
    for k, m in masks.items():
        paths[k] = tmp_path / "masks" / f"{k}.png"
        write_png(paths[k], m)
    prints = {k: m > 127 for k, m in masks.items()}
    return masks, paths, prints


def test_failed_prints_are_never_used_empty_ones_are(tmp_path):
    masks, paths, prints = _small(tmp_path)
    ids = list(masks)
    prints[ids[1]] = np.zeros((64, 64), bool)
    d = write_prints_dir(tmp_path / "p", {**prints, ids[2]: None}, paths, status={ids[2]: "failed"})
    data = load_prints([d])
    assert data.ids == [ids[0], ids[1], ids[3]]
    assert data.status == ["ok", "empty", "ok"] and data.failed == [ids[2]]


def test_prints_of_different_sizes(tmp_path):
    masks, paths, prints = _small(tmp_path)
    k = list(masks)[2]
    big = trial_masks(1, seed=9, size=96)["trial_000"]
    write_png(paths[k], big)
    prints[k] = big > 127
    d = write_prints_dir(tmp_path / "p", prints, paths)
    with pytest.raises(InputError, match="96x96, the others are 64x64") as e:
        load_prints([d])
    assert e.value.path.name == f"{k}.png"


def test_print_and_mask_of_different_sizes(tmp_path):
    masks, paths, prints = _small(tmp_path)
    k = list(masks)[1]
    prints[k] = np.ones((32, 32), bool)
    d = write_prints_dir(tmp_path / "p", prints, paths)
    with pytest.raises(InputError, match="mask coordinates"):
        load_prints([d])


def test_no_usable_prints(tmp_path):
    masks, paths, prints = _small(tmp_path)
    d = write_prints_dir(tmp_path / "p", {k: None for k in masks}, paths, status={k: "failed" for k in masks})
    with pytest.raises(InputError, match="no usable prints") as e:
        calibrate([d], tmp_path / "out")
    assert e.value.path == d


@pytest.mark.parametrize("fill, word", [(False, "empty"), (True, "solid")])
def test_prints_without_edges_identify_nothing(tmp_path, fill, word):
    masks, paths, _ = _small(tmp_path)
    d = write_prints_dir(tmp_path / "p", {k: np.full((64, 64), fill) for k in masks}, paths)
    with pytest.raises(InputError, match=f"all 4 usable prints are {word}.*cannot be identified"):
        calibrate([d], tmp_path / "out")


def test_bad_metadata(tmp_path):
    masks, paths, prints = _small(tmp_path)
    d = write_prints_dir(tmp_path / "p", prints, paths)
    e2 = write_prints_dir(tmp_path / "q", prints, paths, pixel_size_um=3.5)
    with pytest.raises(InputError, match="pixel_size_um 3.5 differs"):
        load_prints([d, e2])
    (d / "batch.yaml").unlink()
    with pytest.raises(InputError, match="does not exist"):
        load_prints([d])
    with pytest.raises(InputError, match="prints folder does not exist"):
        load_prints([tmp_path / "nope"])
    f = write_prints_dir(tmp_path / "r", prints, paths)
    rows = read_tsv(f / "qc.tsv")
    write_tsv(f / "qc.tsv", rows, ["id", "status", "reason"])
    with pytest.raises(InputError, match="missing column"):
        load_prints([f])
    rows[0]["status"] = "maybe"
    write_tsv(f / "qc.tsv", rows)
    with pytest.raises(InputError, match="status 'maybe'"):
        load_prints([f])
    g = write_prints_dir(tmp_path / "s", prints, paths)
    write_png(g / f"{list(masks)[0]}.png", np.full((64, 64), 128, np.uint8))
    with pytest.raises(InputError, match="binary"):
        load_prints([g])


def test_several_prints_dirs_are_pooled(lab, tmp_path):
    d2 = tmp_path / "other"
    shutil.copytree(lab.dir8, d2)
    rows = read_tsv(d2 / "qc.tsv")
    for r in rows:  # absolute mask paths work too
        r["mask"] = str(lab.mask_paths[r["id"]])
    write_tsv(d2 / "qc.tsv", rows)
    data = load_prints([lab.dir8, d2])
    assert len(data) == 16 and data.labels[0] == f"prints8/{data.ids[0]}" and data.labels[8] == f"other/{data.ids[0]}"


# ------------------------------------------------------------------------ CLI


def test_cli_calibrate_and_simulate(lab, tmp_path):
    from click.testing import CliRunner

    import torch

    from unscatter.cli import main

    before = torch.get_num_threads()
    r = CliRunner().invoke(main, ["calibrate", str(lab.dir8), "--out", str(tmp_path / "cal"), "--seed", "1",
                                  "--population", "12", "--generations", "3", "--folds", "2", "--bootstrap", "2",
                                  "--bounds", "sigma_px=0.5,2", "--threads", "1"])
    assert r.exit_code == 0, r.output
    assert "calibrated eq1 on 8 prints" in r.output and "held-out IoU" in r.output
    assert "warning: sigma_px" in r.output  # the fit sits on the upper bound given
    p = load_params(tmp_path / "cal" / "params.yaml")
    assert p.bounds["sigma_px"] == (0.5, 2.0) and p.info["fit"]["seed"] == 1
    assert torch.get_num_threads() == before  # the run's thread count does not leak
    r = CliRunner().invoke(main, ["simulate", str(tmp_path / "cal" / "params.yaml"), str(lab.root / "masks"), str(tmp_path / "sim")])
    assert r.exit_code == 0, r.output
    assert len(list((tmp_path / "sim").glob("*.png"))) == 32
    r = CliRunner().invoke(main, ["calibrate", str(tmp_path / "nope"), "--out", str(tmp_path / "x")])
    assert r.exit_code == 2 and "prints folder does not exist" in r.output
    r = CliRunner().invoke(main, ["calibrate", str(lab.dir8), "--out", str(tmp_path / "x"), "--bounds", "sigma_px=1"])
    assert r.exit_code == 2 and "NAME=LOWER,UPPER" in r.output
