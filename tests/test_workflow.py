"""The Snakemake workflow: config schema, and what a dry-run plans.

Dry-runs only (a couple of seconds each), except the one marked slow. Every run writes
under a temporary results prefix, so the repository's results/ is never touched.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import yaml
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"


# ----------------------------------------------------------------------- helpers
def snakemake(*args, configs=(), check=True):
    """Run snakemake in the repository; returns the completed process (output merged)."""
    cmd = [sys.executable, "-m", "snakemake", *args]
    for cfg in configs:
        cmd += ["--configfile", str(cfg)]
    proc = subprocess.run(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stdout}")
    return proc


def planned(*args, configs=()):
    """(rule, wildcards) of every job that a dry-run plans, `all` left out."""
    out = snakemake("--dry-run", "--cores", "2", *args, configs=configs).stdout
    jobs, rule = [], None
    for line in out.splitlines():
        m = re.match(r"^(?:local)?rule (\w+):$", line)
        if m:
            if rule not in (None, "all"):
                jobs.append((rule, wildcards))
            rule, wildcards = m.group(1), ""
            continue
        m = re.match(r"^\s+wildcards: (.*)$", line)
        if m and rule:
            wildcards = m.group(1).strip()
    if rule not in (None, "all"):
        jobs.append((rule, wildcards))
    return sorted(jobs)


def write_config(path: Path, **cfg) -> Path:
    path.write_text(yaml.safe_dump(cfg))
    return path


def fake_batch(root: Path, name: str, n: int = 2) -> Path:
    """A small batch in the data contract: batch.yaml, masks/<id>.png, images/<id>.tif."""
    batch = root / name
    (batch / "masks").mkdir(parents=True)
    (batch / "images").mkdir()
    (batch / "batch.yaml").write_text(
        yaml.safe_dump(dict(pixel_size_um=2.96, exposure_s=20, max_intensity_mw_cm2=20.8, material="test", notes="fake"))
    )
    for i in range(n):
        mask = np.zeros((64, 64), np.uint8)
        mask[16:48, 16:48] = 255
        Image.fromarray(mask, mode="L").save(batch / "masks" / f"p{i}.png")
        Image.fromarray((mask // 2).astype(np.uint16) + 100).save(batch / "images" / f"p{i}.tif")
    past = 1_000_000_000  # older than any output the test makes
    for p in [batch, *batch.rglob("*")]:
        os.utime(p, (past, past))
    return batch


def schema_defaults(schema: dict):
    """The config the schema's defaults make (objects: the defaults of their properties)."""
    if schema.get("type") == "object" and "properties" in schema:
        return {key: schema_defaults(sub) for key, sub in schema["properties"].items()}
    return schema["default"]


def undocumented(schema: dict, where="config") -> list[str]:
    missing = []
    for key, sub in schema.get("properties", {}).items():
        if not sub.get("description"):
            missing.append(f"{where}.{key}: no description")
        if "default" not in sub:
            missing.append(f"{where}.{key}: no default")
        missing += undocumented(sub, f"{where}.{key}")
    return missing


def merged(base: dict, over: dict) -> dict:
    out = dict(base)
    for key, value in over.items():
        out[key] = merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


# ------------------------------------------------------------------------ config
def test_config_yaml_equals_schema_defaults():
    """config/config.yaml and the schema's defaults must not drift apart."""
    schema = yaml.safe_load(SCHEMA.read_text())
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    assert config == schema_defaults(schema)


def test_every_config_key_has_description_and_default():
    assert undocumented(yaml.safe_load(SCHEMA.read_text())) == []


@pytest.mark.parametrize("name", ["config.yaml", "ci.yaml", "paper.yaml"])
def test_shipped_configs_are_valid(name):
    schema = yaml.safe_load(SCHEMA.read_text())
    base = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    cfg = merged(base, yaml.safe_load((REPO / "config" / name).read_text()) or {})
    jsonschema.Draft202012Validator(schema).validate(cfg)


def test_unknown_config_key_is_rejected(tmp_path):
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"), registration={"mdoe": "affine"})
    proc = snakemake("--dry-run", configs=[cfg], check=False)
    assert proc.returncode != 0
    assert "mdoe" in proc.stdout


# ---------------------------------------------------------------------- dry-runs
def test_default_config_dry_run():
    """The README's `snakemake --cores 2`, as a dry-run."""
    snakemake("--dry-run", "--cores", "2")


# Every job after calibration: the diagnosis, the networks and masks of its selected
# model (config 'model'), the base model's ilt masks (benchmark.compare) and the benchmark.
DOWNSTREAM = [("augment", "model=selected"), ("benchmark_job", ""), ("benchmark_simulated", ""),
              ("compensate", "model=eq1, method=ilt"), ("compensate", "model=selected, method=ilt"),
              ("compensate", "model=selected, method=nn"), ("compensate", "model=selected, method=nn+ilt"),
              ("diagnose", ""), ("report", ""), ("train", "model=selected")]


def test_default_config_plans_every_stage(tmp_path):
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"))
    assert planned(configs=[cfg]) == sorted(
        DOWNSTREAM + [("benchmark_score", ""), ("calibrate", "model=eq1"), ("register_prints", "batch=benchmark_prints"),
                      ("register_prints", "batch=lab"), ("trial_masks", ""), ("virtual_lab", "batch=lab"),
                      ("virtual_lab_benchmark", "")])


def test_next_trial_masks_are_planned_after_the_diagnosis(tmp_path):
    """trial_masks.next > 0: the sequential design of the next batch joins the run."""
    batch = fake_batch(tmp_path, "session1")
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"), source="batches", batches=[str(batch)],
                       trial_masks={"next": 8})
    jobs = planned(configs=[cfg])
    assert ("next_trial_masks", "") in jobs and ("diagnose", "") in jobs
    assert ("next_trial_masks", "") not in planned(configs=[write_config(
        tmp_path / "d.yaml", results=str(tmp_path / "results"), source="batches", batches=[str(batch)])])


LAYERS_JOBS = [("benchmark3d_job", ""), ("benchmark3d_score", ""), ("calibrate3d", ""), ("compensate3d", ""),
               ("register3d", "b3=benchmark"), ("register3d", "b3=trials"), ("trial_masks3d", ""),
               ("virtual_lab3d", "b3=benchmark"), ("virtual_lab3d", "b3=trials")]


def test_layers_run_plans_the_3d_stages(tmp_path):
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"), layers={"run": True})
    jobs = planned(configs=[cfg])
    assert set(LAYERS_JOBS) <= set(jobs)
    off = write_config(tmp_path / "d.yaml", results=str(tmp_path / "results"))
    assert not set(LAYERS_JOBS) & set(planned(configs=[off]))


def fake_batch3d(root: Path, name: str, n: int = 2, layers: int = 3) -> Path:
    """A small multi-layer batch: batch.yaml with layer_um and z_step_um, masks/<id>/NNN.png,
    images/<id>.tif (a z-stack)."""
    batch = fake_batch(root, name, n)
    meta = yaml.safe_load((batch / "batch.yaml").read_text())
    (batch / "batch.yaml").write_text(yaml.safe_dump(dict(meta, layer_um=50, z_step_um=25)))
    for i in range(n):
        flat = batch / "masks" / f"p{i}.png"
        (batch / "masks" / f"p{i}").mkdir()
        for j in range(layers):
            (batch / "masks" / f"p{i}" / f"{j:03d}.png").write_bytes(flat.read_bytes())
        flat.unlink()
    past = 1_000_000_000
    for p in [batch, *batch.rglob("*")]:
        os.utime(p, (past, past))
    return batch


def test_measured_3d_batches_are_registered_and_calibrated(tmp_path):
    """source: batches with layers.run - the measured 3-D trial batches are registered and
    calibrated on; the benchmark's print job is written, and scored once its printed batch
    is given, never calibrated on."""
    batch = fake_batch(tmp_path, "session1")
    t1, t2, bench = (fake_batch3d(tmp_path, n) for n in ("stacks1", "stacks2", "bench3d"))
    base = dict(results=str(tmp_path / "results"), source="batches", batches=[str(batch)])
    cfg = write_config(tmp_path / "c.yaml", **base, layers={"run": True, "batches": [str(t1), str(t2)]})
    jobs = planned(configs=[cfg])
    layers = sorted(j for j in jobs if j[0] in {name for name, _ in LAYERS_JOBS})
    assert layers == [("benchmark3d_job", ""), ("calibrate3d", ""), ("compensate3d", ""), ("register3d", "b3=stacks1"),
                      ("register3d", "b3=stacks2")]
    cfg = write_config(tmp_path / "c.yaml", **base,
                       layers={"run": True, "batches": [str(t1)], "benchmark_batch": str(bench)})
    jobs = planned(configs=[cfg])
    assert ("benchmark3d_score", "") in jobs and ("register3d", "b3=bench3d") in jobs
    assert not [j for j in jobs if j[0] in ("virtual_lab3d", "trial_masks3d")]
    out = snakemake("--dry-run", "--printshellcmds", "--forceall", "--rerun-triggers", "mtime", configs=[cfg]).stdout
    calib = out[out.index("rule calibrate3d:"):]
    calib = calib[:calib.index("\n\n")]
    assert "layers/prints/stacks1" in calib and "bench3d" not in calib


@pytest.mark.parametrize("layers, message", [
    ({"run": True}, "layers.run with source 'batches' needs layers.batches"),
    ({"run": True, "batches": ["STACKS"], "benchmark_batch": "STACKS"}, "never calibrated on"),
    ({"run": True, "batches": ["MISSING"]}, "lacks batch.yaml"),
])
def test_measured_3d_batches_fail_clearly(tmp_path, layers, message):
    batch, stacks = fake_batch(tmp_path, "session1"), fake_batch3d(tmp_path, "stacks1")
    layers = {k: ([str(stacks) if e == "STACKS" else str(tmp_path / "missing") for e in v] if k == "batches" else
                  str(stacks) if v == "STACKS" else v) for k, v in layers.items()}
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"), source="batches", batches=[str(batch)],
                       layers=layers)
    proc = snakemake("--dry-run", configs=[cfg], check=False)
    assert proc.returncode != 0 and message in proc.stdout, proc.stdout[-2000:]


def test_slurm_profile_dry_run(tmp_path):
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"))
    out = snakemake("--dry-run", "--workflow-profile", "workflow/profiles/slurm", configs=[cfg]).stdout
    assert "slurm_partition=" in out


def test_batches_source_plans_no_lab(tmp_path):
    batch = fake_batch(tmp_path, "session1")
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"), source="batches", batches=[str(batch)])
    # no benchmark batch yet: the print job and the simulated benchmark, nothing to score
    assert planned(configs=[cfg]) == sorted(DOWNSTREAM + [("calibrate", "model=eq1"), ("register_prints", "batch=session1")])


def fake_outputs(results: Path, batches) -> None:
    """Every output of a run on the measured batches, newer than every input."""
    dirs = [f"prints/{b}" for b in batches] + ["calibration/eq1", "diagnosis", "augment/selected.zarr", "train/selected",
                                               "compensated/selected/nn", "compensated/selected/ilt",
                                               "compensated/selected/nn+ilt", "compensated/eq1/ilt", "benchmark/print_job",
                                               "benchmark/simulated"]
    for d in dirs:
        (results / d).mkdir(parents=True)
    (results / "report.html").write_text("report")


def test_model_base_trains_on_the_base_model(tmp_path):
    """model: base - the networks and masks use Eq. 1 as calibrated; the benchmark then
    compares the selected model's ilt masks (ilt_selected), and the diagnosis still runs."""
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"), model="base")
    jobs = planned(configs=[cfg])
    assert ("train", "model=eq1") in jobs and ("augment", "model=eq1") in jobs and ("diagnose", "") in jobs
    assert [j for j in jobs if j[0] == "compensate"] == [
        ("compensate", "model=eq1, method=ilt"), ("compensate", "model=eq1, method=nn"),
        ("compensate", "model=eq1, method=nn+ilt"), ("compensate", "model=selected, method=ilt")]
    assert ("train", "model=selected") not in jobs
    out = snakemake("--dry-run", "--printshellcmds", configs=[cfg]).stdout
    assert "compensated/selected/ilt" in out


def test_adding_a_batch_plans_only_that_batch(tmp_path):
    results = tmp_path / "results"
    first, second = fake_batch(tmp_path, "session1"), fake_batch(tmp_path, "session2")
    # a whole run on session1 is done: every output is newer than its inputs and scripts
    fake_outputs(results, ["session1"])
    cfg = write_config(tmp_path / "c.yaml", results=str(results), source="batches", batches=[str(first)])
    assert planned(configs=[cfg]) == []
    cfg = write_config(tmp_path / "c.yaml", results=str(results), source="batches", batches=[str(first), str(second)])
    # the new batch is registered, then the calibration, the diagnosis and everything after
    # them is redone; session1's registration is not
    assert planned(configs=[cfg]) == sorted(DOWNSTREAM + [("calibrate", "model=eq1"), ("register_prints", "batch=session2")])
    # a changed image of session1 reruns session1 too
    later = time.time() + 60
    os.utime(first / "images" / "p0.tif", (later, later))
    assert planned(configs=[cfg]) == sorted(DOWNSTREAM + [("calibrate", "model=eq1"), ("register_prints", "batch=session1"),
                                                          ("register_prints", "batch=session2")])


def test_a_printed_benchmark_job_is_scored_not_calibrated_on(tmp_path):
    """The benchmark's print job comes back as a batch: it is registered and scored, and
    the calibration and everything before the benchmark stay as they are."""
    results = tmp_path / "results"
    trial, bench = fake_batch(tmp_path, "session1"), fake_batch(tmp_path, "bench1")
    fake_outputs(results, ["session1"])
    cfg = write_config(tmp_path / "c.yaml", results=str(results), source="batches", batches=[str(trial)])
    assert planned(configs=[cfg]) == []
    cfg = write_config(tmp_path / "c.yaml", results=str(results), source="batches", batches=[str(trial)],
                       benchmark={"batch": str(bench)})
    assert planned(configs=[cfg]) == [("benchmark_score", ""), ("register_prints", "batch=bench1"), ("report", "")]
    # the same batch as a calibration batch too: refused, with the reason
    cfg = write_config(tmp_path / "c.yaml", results=str(results), source="batches", batches=[str(trial), str(bench)],
                       benchmark={"batch": str(bench)})
    proc = snakemake("--dry-run", configs=[cfg], check=False)
    assert proc.returncode != 0 and "never calibrated on" in proc.stdout


def test_unknown_design_fails_clearly(tmp_path):
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"), designs={"names": ["star", "nosuch"]})
    proc = snakemake("--dry-run", configs=[cfg], check=False)
    assert proc.returncode != 0 and "no nosuch (.png) in data/designs" in proc.stdout


def test_batch_without_contract_fails_clearly(tmp_path):
    (tmp_path / "half" / "masks").mkdir(parents=True)
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"), source="batches", batches=[str(tmp_path / "half")])
    proc = snakemake("--dry-run", configs=[cfg], check=False)
    assert proc.returncode != 0
    assert "lacks batch.yaml, images" in proc.stdout


def test_duplicate_batch_names_fail_clearly(tmp_path):
    a, b = fake_batch(tmp_path / "a", "same"), fake_batch(tmp_path / "b", "same")
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"), source="batches", batches=[str(a), str(b)])
    proc = snakemake("--dry-run", configs=[cfg], check=False)
    assert proc.returncode != 0
    assert "have the same name 'same'" in proc.stdout


def test_a_batch_path_is_named_by_its_resolved_folder(tmp_path):
    batch = fake_batch(tmp_path, "session1")
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"), source="batches",
                       batches=[str(batch / "masks" / "..")])
    assert ("register_prints", "batch=session1") in planned(configs=[cfg])


@pytest.mark.parametrize("entry", ["..", ".", ".hidden", "{tmp}/.hidden/masks/.."])
def test_batch_names_must_be_plain_names(tmp_path, entry):
    """A batch named '..' would make results/prints/.. the results folder itself, which
    Snakemake deletes before it registers the batch."""
    fake_batch(tmp_path, ".hidden")
    entry = entry.format(tmp=tmp_path)
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"), source="batches", batches=[entry])
    proc = snakemake("--dry-run", configs=[cfg], check=False)
    assert proc.returncode != 0 and "config: batches" in proc.stdout and "not a plain folder name" in proc.stdout
    assert "Job stats" not in proc.stdout


@pytest.mark.parametrize("results", ["data", "data/results", ".", "..", "{batch}/results"])
def test_results_keeps_clear_of_the_users_data(tmp_path, results):
    batch = fake_batch(tmp_path, "session1")
    cfg = write_config(tmp_path / "c.yaml", results=results.format(batch=batch), source="batches", batches=[str(batch)])
    proc = snakemake("--dry-run", configs=[cfg], check=False)
    assert proc.returncode != 0 and "config: results:" in proc.stdout and "Job stats" not in proc.stdout


def test_unknown_calibration_model_fails_before_planning(tmp_path):
    cfg = write_config(tmp_path / "c.yaml", results=str(tmp_path / "results"), calibration={"model": "eq2"})
    proc = snakemake("--dry-run", configs=[cfg], check=False)
    assert proc.returncode != 0 and "'eq2' is not one of ['eq1']" in proc.stdout and "Job stats" not in proc.stdout


# ---------------------------------------------------------------------- real run
@pytest.mark.slow
def test_trial_masks_and_virtual_lab_real_run(tmp_path):
    results = tmp_path / "results"
    cfg = write_config(tmp_path / "c.yaml", results=str(results), trial_masks={"count": 3})
    snakemake(str(results / "lab" / "lab"), "--cores", "2", configs=[cfg])
    batch = results / "lab" / "lab"
    ids = ["trial_000", "trial_001", "trial_002"]
    assert sorted(p.stem for p in (batch / "masks").glob("*.png")) == ids
    assert sorted(p.stem for p in (batch / "images").glob("*.tif")) == ids
    assert set(yaml.safe_load((batch / "batch.yaml").read_text())) >= {"pixel_size_um", "exposure_s", "max_intensity_mw_cm2", "material", "notes"}
    assert (results / "lab" / "lab.truth" / "transforms.tsv").is_file()
    assert "printed and imaged 3 masks" in (results / "logs" / "virtual_lab" / "lab.log").read_text()
    # nothing left to do; a changed lab seed reruns the lab, not the trial masks
    assert planned(str(batch), configs=[cfg]) == []
    cfg2 = write_config(tmp_path / "c2.yaml", results=str(results), trial_masks={"count": 3}, lab={"seed": 7})
    assert planned(str(batch), configs=[cfg2]) == [("virtual_lab", "batch=lab")]
    # the paper's masks carry the registration marks only when asked (trial_masks.paper_fiducials)
    from unscatter.io import read_mask
    from unscatter.masks import carries_marks

    assert sorted(p.stem for p in (results / "trial_masks").glob("*.png")) == ids
    assert not any(carries_marks(read_mask(p)) for p in (results / "trial_masks").glob("*.png"))
    cfg3 = write_config(tmp_path / "c3.yaml", results=str(results), trial_masks={"count": 3, "paper_fiducials": True})
    snakemake(str(results / "trial_masks"), "--cores", "2", configs=[cfg3])
    assert sorted(p.stem for p in (results / "trial_masks").glob("*.png")) == ids
    assert all(carries_marks(read_mask(p)) for p in (results / "trial_masks").glob("*.png"))
