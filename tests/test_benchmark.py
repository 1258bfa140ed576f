"""Benchmark: print ids, the print job for a real printer, scoring on the simulator as
printer, scoring a registered batch, and the virtual lab through registration."""

import math

import numpy as np
import pytest

from unscatter import metrics
from unscatter.benchmark import (
    COLUMNS,
    IDENTICAL,
    IDENTICAL_DOSES,
    MARK_ROOM_GREY,
    benchmark_masks,
    identical_mask,
    parse_print_id,
    print_id,
    read_registered,
    run_benchmark,
    score_measured,
    score_prints,
    simulator_printer,
    write_print_job,
)
from unscatter.compensation import compensate_designs
from unscatter.masks import carries_marks, fiducial_marks, with_fiducials
from unscatter.io import open_batch, read_batch_meta, read_mask, read_tsv, write_png, write_tsv, write_yaml
from unscatter.model import default_params, save_params, simulate

PX_UM = 2.96
VALUES = dict(c1=-0.06, c2=-0.04, c3=0.03, c4=-0.02, sigma_px=5.0, T=0.5)
SHORT = dict(schedule=((4, 30), (2, 15), (1, 5)), threads=1)  # a quicker ILT: these tests are about the benchmark


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    params = default_params(pixel_size_um=PX_UM).with_values(**VALUES)
    save_params(root / "params.yaml", params)
    designs = root / "designs"
    for name in ("cross", "star"):
        write_png(designs / f"{name}.png", read_mask(f"data/designs/{name}.png"))
    compensate_designs(designs, root / "ilt", "ilt", params_path=root / "params.yaml", frames=False, **SHORT)
    return root, params, designs


@pytest.fixture(scope="module")
def simulated(setup):
    root, params, designs = setup
    rows = run_benchmark(designs, {"ilt": root / "ilt"}, root / "out", PX_UM, simulator_printer(params))
    return root / "out", rows


# ------------------------------------------------------------------------------ ids


@pytest.mark.parametrize("method,dose,exposure", [("ilt", 1.0, 1.0), ("nn+ilt", 1.0, 1.1), ("nn", 1.0, 0.9),
                                                  (IDENTICAL, 0.75, 1.0), (IDENTICAL, 0.5, 1.1), ("ilt_robust", 1.0, 1.0)])
def test_print_ids_parse_back(method, dose, exposure):
    pid = print_id("rings_widths", method, dose, exposure)
    q = parse_print_id(pid)
    assert (q["design"], q["method"], q["mask_dose"], q["exposure"]) == ("rings_widths", method, dose, exposure)


def test_print_id_examples_and_bad_ids():
    assert print_id("star", IDENTICAL, 0.7) == "star__identical_70"
    assert print_id("star", "ilt", 1.0, 0.9) == "star__ilt__x090"
    for bad in ("star", "star__", "__ilt", "a__b__c__d", "star__ilt__x9", "star__i lt"):
        with pytest.raises(ValueError):
            parse_print_id(bad)
    with pytest.raises(ValueError):
        print_id("my__design", "ilt")
    with pytest.raises(ValueError):
        print_id("star", "identical_fake")


def test_pooled_iou_weighs_prints_by_area_not_empty_ones_by_one():
    """A mask that prints nothing: a few stray predicted pixels make its per-print IoU 0
    (and an empty prediction 1), which outweighs a whole print in a mean; pooled, they are
    those pixels."""
    big = np.zeros((64, 64), bool)
    big[8:56, 8:56] = True  # 2304 px
    near = big.copy()
    near[8:56, 8] = False  # 48 px short
    empty = np.zeros_like(big)
    stray = empty.copy()
    stray[0, :4] = True  # 4 px printed where nothing did
    truth = [big, empty]
    a, b = [near, stray], [big, empty]  # b: exact
    assert metrics.pooled_iou([near], [big]) == pytest.approx(metrics.iou(near, big))
    assert np.mean([metrics.iou(p, t) for p, t in zip(a, truth)]) == pytest.approx((2256 / 2304) / 2)
    assert metrics.pooled_iou(a, truth) == pytest.approx(2256 / 2308)
    assert metrics.pooled_iou(b, truth) == 1.0
    assert metrics.pooled_iou([empty], [empty]) == 1.0
    with pytest.raises(ValueError):
        metrics.pooled_iou([near], truth)


def test_identical_masks_scale_the_grey_level():
    d = np.zeros((8, 8), bool)
    d[2:5, 2:6] = True
    for dose, grey in zip(IDENTICAL_DOSES, (255, 191, 178, 128)):
        m = identical_mask(d, dose)
        assert m.dtype == np.uint8 and set(np.unique(m)) == {0, grey} and np.array_equal(m > 0, d)


# -------------------------------------------------------------------------- print job


def test_print_job_is_a_batch_without_images(setup, tmp_path):
    root, _, designs = setup
    job = tmp_path / "print_job"
    rows = write_print_job({"ilt": root / "ilt", "nn+ilt": root / "ilt"}, designs, job)
    n = 2 * (2 + len(IDENTICAL_DOSES)) * 3  # designs x (methods + identical doses) x exposures
    assert len(rows) == n and len(list((job / "masks").glob("*.png"))) == n
    assert (job / "images").is_dir() and not any((job / "images").iterdir())
    meta = read_batch_meta(job / "batch.yaml")  # the contract's fields, valid as written
    assert meta.pixel_size_um == PX_UM
    assert "images/<same id>" in (job / "README.txt").read_text()
    assert "data/prints/<name>/" in (job / "README.txt").read_text()
    seen = set()
    for r in read_tsv(job / "job.tsv"):
        q = parse_print_id(r["id"])
        assert (q["design"], q["method"], q["mask_dose"], q["exposure"]) == (
            r["design"], r["method"], float(r["mask_dose"]), float(r["exposure"]))
        seen.add((q["design"], q["method"], q["mask_dose"], q["exposure"]))
        m = read_mask(job / "masks" / f"{r['id']}.png")
        if q["method"] == IDENTICAL:  # with the registration marks: both designs leave the corners empty
            assert np.array_equal(m, with_fiducials(identical_mask(read_mask(designs / f"{q['design']}.png"), q["mask_dose"])))
        else:
            assert np.array_equal(m, with_fiducials(read_mask(root / "ilt" / f"{q['design']}.png")))
    assert len(seen) == n
    assert float(read_tsv(job / "job.tsv")[0]["exposure_s"]) > 0
    assert "2 of the 2 designs' masks carry three registration marks" in (job / "README.txt").read_text()


def test_registration_marks_go_only_where_a_design_leaves_room_for_them(setup, tmp_path):
    root, _, designs = setup
    masks, _ = benchmark_masks(designs, {"ilt": root / "ilt"}, fiducials=False)
    assert not any(carries_marks(m) for m in masks.values())
    # a design that reaches into a corner: its masks are printed as they are, the others' carry the marks
    two = tmp_path / "designs"
    write_png(two / "cross.png", read_mask(designs / "cross.png"))
    corner = np.zeros((512, 512), np.uint8)
    corner[60:160, 60:160] = 255  # into the top left mark's cleared band
    write_png(two / "corner.png", corner)
    masks, _ = benchmark_masks(two, {}, fiducials=True)
    assert all(carries_marks(m) == (pid.startswith("cross__")) for pid, m in masks.items())
    assert all(np.array_equal(m, identical_mask(corner, parse_print_id(pid)["mask_dose"]))
               for pid, m in masks.items() if pid.startswith("corner__"))
    # a method's faint grey over the whole field (a network's mask) leaves room for them; an assist feature does not
    one = tmp_path / "one"
    write_png(one / "cross.png", read_mask(designs / "cross.png"))
    for grey, marked in ((MARK_ROOM_GREY, True), (MARK_ROOM_GREY + 1, False)):
        method = tmp_path / f"nn_{grey}"
        write_png(method / "cross.png", np.maximum(read_mask(designs / "cross.png"), grey).astype(np.uint8))
        masks, _ = benchmark_masks(one, {"nn": method}, fiducials=True)
        assert all(carries_marks(m) == marked for m in masks.values()), grey


def test_masks_must_match_the_designs(setup, tmp_path):
    root, _, designs = setup
    bad = tmp_path / "bad"
    write_png(bad / "cross.png", np.zeros((100, 100), np.uint8))
    write_png(bad / "star.png", np.zeros((512, 512), np.uint8))
    with pytest.raises(ValueError, match="design's size"):
        benchmark_masks(designs, {"nn": bad})
    with pytest.raises(ValueError, match="reference"):
        benchmark_masks(designs, {IDENTICAL: root / "ilt"})


# ----------------------------------------------------------- the simulator as printer


def test_benchmark_on_the_simulator_writes_every_row_and_figure(simulated):
    out, rows = simulated
    table = read_tsv(out / "metrics.tsv")
    assert list(table[0]) == COLUMNS
    keys = {(r["design"], r["method"], float(r["mask_dose"])) for r in table}
    expect = {(d, "ilt", 1.0) for d in ("cross", "star")} | {(d, IDENTICAL, x) for d in ("cross", "star") for x in IDENTICAL_DOSES}
    assert keys == expect and len(table) == len(expect)
    assert all(r["status"] == "ok" for r in table)
    for name in ("fig6_prints.png", "fig5_masks.png", "metrics_bars.png"):
        assert (out / name).stat().st_size > 10000, name
    assert [r["variant"] for r in read_tsv(out / "summary.tsv")] == ["ilt"] + [f"identical {round(100 * x)} %" for x in IDENTICAL_DOSES]


def test_compensated_masks_beat_identical_masks(simulated):
    _, rows = simulated
    by = {(r["design"], r["method"], r["mask_dose"]): r for r in rows}
    for d in ("cross", "star"):
        ilt, ident = by[(d, "ilt", 1.0)], by[(d, IDENTICAL, 1.0)]
        assert ilt["iou"] > ident["iou"] and ilt["epe_um"] < ident["epe_um"]
        # the plain mask prints worse as its dose is turned down (Fig. 6)
        ious = [by[(d, IDENTICAL, x)]["iou"] for x in IDENTICAL_DOSES]
        assert ious == sorted(ious, reverse=True)
        assert all(r["pv_band_um"] > 0 for r in (ilt, ident))


def test_benchmark_scores_with_the_metrics_module(setup, simulated):
    root, params, designs = setup
    _, rows = simulated
    d = read_mask(designs / "star.png") != 0
    m = identical_mask(d, 0.75)
    p = simulate(params, m)
    lo = simulate(params.with_values(T=0.5 / 0.9), m)
    hi = simulate(params.with_values(T=0.5 / 1.1), m)
    r = next(r for r in rows if r["design"] == "star" and r["mask_dose"] == 0.75)
    assert r["iou"] == pytest.approx(metrics.iou(p, d))
    assert r["epe_um"] == pytest.approx(metrics.epe_um(p, d, PX_UM))
    assert r["pv_band_um"] == pytest.approx(metrics.pv_band_um(lo, hi, d, PX_UM))


def test_a_missing_print_is_reported_not_scored(setup):
    _, params, designs = setup
    d = read_mask(designs / "cross.png") != 0
    prints = {print_id("cross", IDENTICAL, 1.0, e): simulate(params.with_values(T=0.5 / e), identical_mask(d)) for e in (0.9, 1.1)}
    prints[print_id("cross", "ilt")] = None
    prints[print_id("cross", IDENTICAL)] = simulate(params, identical_mask(d))
    rows = {r["method"]: r for r in score_prints(prints, designs, PX_UM)}
    assert rows["ilt"]["status"] == "no print" and math.isnan(rows["ilt"]["iou"])
    assert rows[IDENTICAL]["status"] == "ok" and not math.isnan(rows[IDENTICAL]["pv_band_um"])


def test_masks_are_compared_on_the_designs_that_all_of_them_printed(setup, tmp_path):
    """A mask whose print of one design failed registration is averaged over the other
    designs only; the ``common_*`` columns hold every mask to the same designs, and the
    summary names the design a mask has no print of (seen: the default run's star failed
    for three methods, and identical 100 % kept it: 0.920 over 6 designs, 0.907 over the
    5 that every mask printed)."""
    from unscatter.benchmark import common_designs, fig_bars, summarise, summary_line

    _, params, designs = setup
    prints = {}
    for name in ("cross", "star"):
        d = read_mask(designs / f"{name}.png") != 0
        prints[print_id(name, IDENTICAL)] = simulate(params, identical_mask(d))
        prints[print_id(name, IDENTICAL, 0.5)] = None  # nothing to register at half grey
        prints[print_id(name, "ilt")] = d.copy()  # a perfect print: IoU 1
    prints[print_id("star", "ilt")] = None  # failed registration
    rows = score_prints(prints, designs, PX_UM)
    assert common_designs(rows) == ["cross"]
    s = {r["variant"]: r for r in summarise(rows)}
    ident = {r["design"]: r["iou"] for r in rows if r["method"] == IDENTICAL and r["mask_dose"] == 1.0}
    assert s["ilt"]["designs"] == 1 and s["ilt"]["no_print"] == "star" and s["ilt"]["common_iou"] == 1.0
    assert s["identical 100 %"]["designs"] == 2 and s["identical 100 %"]["common_designs"] == 1
    assert s["identical 100 %"]["iou"] == pytest.approx(np.mean(list(ident.values())))
    assert s["identical 100 %"]["common_iou"] == pytest.approx(ident["cross"])
    assert ident["cross"] != ident["star"]  # so the two means differ, and the check above can fail
    assert s["identical 50 %"]["no_print"] == "cross,star" and math.isnan(s["identical 50 %"]["common_iou"])
    assert "no print of star" in summary_line(s["ilt"]) and "(1 design)" in summary_line(s["ilt"])
    assert "on the 1 designs that every full-grey mask printed: IoU" in summary_line(s["identical 100 %"])
    fig_bars(tmp_path / "bars.png", list(s.values()))
    assert (tmp_path / "bars.png").stat().st_size > 0
    # no mask at full grey: nothing in common, and no line claims a comparison on it
    half = [r for r in rows if r["mask_dose"] != 1.0]
    assert common_designs(half) == [] and "every full-grey" not in summary_line(summarise(half)[0])


# ------------------------------------------------------------------ a measured batch


def score_key(r: dict) -> tuple:
    return r["design"], r["method"], r["mask_dose"]


def assert_scored_alike(marked: list, plain: list):
    """The scores of prints of marked masks (their marks left out) against those of the
    unmarked masks. The marks' scattered light reaches a design's print only at its
    faintest (one pixel of the star at 50 % grey here), hence the tolerances."""
    a = {score_key(r): r for r in plain}
    tol = dict(iou=1e-4, pixel_error=1e-4, epe_um=0.01, pv_band_um=0.01, solid_fraction=1e-4)
    for r in marked:
        for k, a_tol in tol.items():
            assert r[k] == pytest.approx(a[score_key(r)][k], abs=a_tol), (score_key(r), k)


def test_score_measured_equals_the_printer_path(setup, simulated, tmp_path):
    """A registration-like folder of the same prints scores the same as run_benchmark."""
    root, params, designs = setup
    out, rows = simulated
    job = tmp_path / "job"
    write_print_job({"ilt": root / "ilt"}, designs, job)
    reg = tmp_path / "registered"
    qc = []
    for pid_path in sorted((job / "masks").glob("*.png")):
        pid = pid_path.stem
        e = parse_print_id(pid)["exposure"]
        write_png(reg / f"{pid}.png", simulate(params.with_values(T=0.5 / e), read_mask(pid_path)))
        qc.append(dict(id=pid, status="ok", mask=f"../job/masks/{pid}.png"))
    write_tsv(reg / "qc.tsv", qc)
    write_yaml(reg / "batch.yaml", dict(pixel_size_um=PX_UM, exposure_s=20, max_intensity_mw_cm2=20.8, material="test"))
    measured = score_measured(reg, designs, tmp_path / "scored")
    assert_scored_alike(measured, rows)
    marks = fiducial_marks(512)[0]
    assert read_mask(reg / f"{print_id('cross', 'ilt')}.png")[marks].mean() > 0.9
    assert (tmp_path / "scored" / "fig5_masks.png").is_file()
    # a print that failed registration QC is reported as such, and not scored
    failed = print_id("star", "ilt")
    qc = [dict(r, status="failed") if r["id"] == failed else r for r in qc]
    write_tsv(reg / "qc.tsv", qc)
    again = {score_key(r): r for r in score_measured(reg, designs, tmp_path / "scored2", figures=False)}
    assert again[("star", "ilt", 1.0)]["status"] == "registration failed" and math.isnan(again[("star", "ilt", 1.0)]["iou"])
    assert again[("cross", "ilt", 1.0)]["status"] == "ok"


def test_run_benchmark_hands_a_registered_printer_the_marked_masks(setup, simulated, tmp_path):
    """With ``fiducials`` the printer gets the print job's masks, marks and all; prints
    that come back as a registration output is read (``read_registered``) score as the
    unmarked masks' do."""
    root, params, designs = setup
    _, rows = simulated
    seen = {}

    def printer(masks, exposures):  # the simulator, its prints read back from a registration-like folder
        reg, qc = tmp_path / "reg", []
        for pid, m in masks.items():
            seen[pid] = m
            write_png(tmp_path / "masks" / f"{pid}.png", m)
            write_png(reg / f"{pid}.png", simulate(params.with_values(T=params.values["T"] / exposures[pid]), m))
            qc.append(dict(id=pid, status="ok", mask=f"../masks/{pid}.png"))
        write_tsv(reg / "qc.tsv", qc)
        return read_registered(reg)

    marked = run_benchmark(designs, {"ilt": root / "ilt"}, tmp_path / "out", PX_UM, printer, figures=False, fiducials=True)
    plain, _ = benchmark_masks(designs, {"ilt": root / "ilt"})
    assert set(seen) == set(plain) and all(carries_marks(m) and not carries_marks(plain[k]) for k, m in seen.items())
    assert len(marked) == len(rows)
    assert_scored_alike(marked, rows)


# ----------------------------------------------------------------- the virtual lab


@pytest.mark.slow
def test_virtual_lab_prints_go_through_registration(setup, tmp_path):
    from unscatter.lab.jobs import print_on_virtual_lab

    root, _, designs = setup
    one = tmp_path / "designs"
    write_png(one / "cross.png", read_mask(designs / "cross.png"))
    job = tmp_path / "job"
    write_print_job({"ilt": root / "ilt"}, one, job, doses=(1.0, 0.5))
    prints = print_on_virtual_lab(job / "masks", tmp_path / "work", seed=3)
    batch = open_batch(tmp_path / "work" / "batch")  # one batch in the data contract, all exposures
    assert set(batch.ids) == {p.stem for p in (job / "masks").glob("*.png")}
    assert read_batch_meta(tmp_path / "work" / "batch" / "batch.yaml").exposure_s == 20
    qc = {r["id"]: r for r in read_tsv(prints / "qc.tsv")}
    assert set(qc) == set(batch.ids)
    for pid, r in qc.items():
        # a print whose polymer images too faint to tell a speck from nothing fails as 'faint';
        # that is right only where the lab cured next to nothing (under 0.05 % of the field, as
        # benchmarks/bench_registration.py counts an empty print that printed)
        cured = float((read_mask(tmp_path / "work" / "truth" / "prints" / f"{pid}.png") > 0).mean())
        assert r["status"] in ("ok", "empty") or (r["reason"].startswith("faint") and cured < 5e-4), (pid, r["status"], r["reason"], cured)
    assert all(qc[print_id("cross", m, 1.0, 1.0)]["status"] == "ok" for m in ("ilt", IDENTICAL))
    # more exposure, more polymer
    solid = {e: read_mask(prints / f"{print_id('cross', 'ilt', 1.0, e)}.png").mean() for e in (0.9, 1.0, 1.1)}
    assert solid[0.9] < solid[1.0] < solid[1.1]
    rows = score_measured(prints, one, tmp_path / "scored")
    assert {(r["method"], r["mask_dose"]) for r in rows} == {("ilt", 1.0), (IDENTICAL, 1.0), (IDENTICAL, 0.5)}
    by = {(r["method"], r["mask_dose"]): r for r in rows}
    assert by[(IDENTICAL, 1.0)]["iou"] > by[(IDENTICAL, 0.5)]["iou"]
    assert (tmp_path / "scored" / "metrics.tsv").is_file()


# ------------------------------------------------------------- CLI and the report


def test_cli_benchmark_simulate_job_and_report(setup, tmp_path):
    from click.testing import CliRunner

    from unscatter.cli import main

    root, _, designs = setup
    results = tmp_path / "results"
    run = CliRunner().invoke(main, ["benchmark", "simulate", str(designs), str(results / "benchmark" / "simulated"),
                                    "--params", str(root / "params.yaml"), "--method", f"ilt={root / 'ilt'}", "--doses", "1,0.5"])
    assert run.exit_code == 0, run.output
    assert "ilt " in run.output and "identical 50 %" in run.output
    summary = {r["variant"]: r for r in read_tsv(results / "benchmark" / "simulated" / "summary.tsv")}
    assert float(summary["ilt"]["iou"]) > float(summary["identical 100 %"]["iou"])
    run = CliRunner().invoke(main, ["benchmark", "job", str(designs), str(results / "benchmark" / "print_job"),
                                    "--method", f"ilt={root / 'ilt'}", "--doses", "1"])
    assert run.exit_code == 0, run.output
    assert len(read_tsv(results / "benchmark" / "print_job" / "job.tsv")) == 2 * 2 * 3  # designs x masks x exposures
    bad = CliRunner().invoke(main, ["benchmark", "job", str(designs), str(tmp_path / "j"), "--method", "ilt"])
    assert bad.exit_code != 0 and "NAME=FOLDER" in bad.output
    bad = CliRunner().invoke(main, ["benchmark", "job", str(designs), str(tmp_path / "j"), "--doses", "1,1.5"])
    assert bad.exit_code != 0 and "(0, 1]" in bad.output

    run = CliRunner().invoke(main, ["report", str(results)])
    assert run.exit_code == 0, run.output
    page = (results / "report.html").read_text()
    # the simulated benchmark's numbers, with the file they come from
    assert f"from {results.as_posix()}/benchmark/simulated/summary.tsv" in page
    assert f"{float(summary['ilt']['iou']):.4g}" in page
    assert "data:image/png;base64," in page  # figures are embedded: the page stands alone
    # stages that did not run are named, not silently left out
    assert "Not printed yet" in page and "No registered batches." in page
