"""One source for every setting (unscatter.settings): the workflow schema, config.yaml,
the command line and the package defaults must all say what the settings say, and
every command line option must be bounded."""

from __future__ import annotations

import inspect
import math
import re
from pathlib import Path

import click
import jsonschema
import pytest
import yaml
from click.testing import CliRunner

from unscatter import settings as S
from unscatter.cli import main

REPO = Path(__file__).resolve().parents[1]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"


def test_the_schema_is_generated_from_the_settings():
    """Fails when someone edits the schema by hand or the settings without regenerating:
    python -m unscatter.settings > workflow/schemas/config.schema.yaml"""
    assert SCHEMA.read_text() == S.schema_text()


def test_the_schema_has_every_workflow_setting_and_nothing_else():
    props = yaml.safe_load(SCHEMA.read_text())["properties"]
    for stage in S.SECTIONS:
        want = sorted(k for k, s in stage if s.workflow)
        assert sorted(props[stage.key]["properties"]) == want, stage.key
    assert sorted(k for k in props if not isinstance(props[k].get("properties"), dict)) == sorted(S.WORKFLOW.settings)


# --------------------------------------------------------------- the command line
def _commands(group: click.Group, prefix=()):
    for name, cmd in group.commands.items():
        if isinstance(cmd, click.Group):
            yield from _commands(cmd, prefix + (name,))
        else:
            yield " ".join(prefix + (name,)), cmd


# command -> the stage whose settings its options are, and options that deliberately
# differ in default (with the reason in cli.py's help text).
STAGE_OF = {
    "masks trial": (S.TRIAL_MASKS, {}),
    "masks design": (S.TRIAL_MASKS, {}),
    "masks trial3d": (S.LAYERS, {}),
    "lab print": (S.LAB, {"seed": None}),  # None: the lab config's seed
    "register": (S.REGISTRATION, {}),
    "calibrate": (S.CALIBRATION, {}),
    "diagnose": (S.DIAGNOSIS, {"candidates": None}),  # a comma-separated list; none given: the whole library
    "augment": (S.AUGMENTATION, {"count": S.PRESET_PAIRS["default"]}),  # the workflow's null
    "train": (S.TRAINING, {}),
    "compensate": (S.COMPENSATION, {}),
}


def _bounds(t) -> tuple:
    return (t.min, t.max, t.min_open, t.max_open)


def _range_bounds(r: S.Range, integer: bool) -> tuple:
    cast = int if integer else float
    return (None if math.isinf(r.lo) else cast(r.lo), None if math.isinf(r.hi) else cast(r.hi), r.lo_open, r.hi_open)


@pytest.mark.parametrize("command", sorted(STAGE_OF))
def test_cli_options_follow_the_settings(command):
    stage, exceptions = STAGE_OF[command]
    cmd = dict(_commands(main))[command]
    matched = 0
    for p in cmd.params:
        if not isinstance(p, click.Option) or p.name not in stage.settings:
            continue
        s = stage[p.name]
        matched += 1
        want = exceptions.get(p.name, tuple(s.default) if isinstance(s.default, list) else s.default)
        assert p.default == want, f"{command} --{p.name}: default {p.default!r}, settings say {want!r}"
        if s.choices is not None:
            assert list(p.type.choices) == list(s.choices), p.name
        elif s.range is not None:
            assert _bounds(p.type) == _range_bounds(s.range, s.kind == "integer"), p.name
    assert matched >= 1


def test_every_numeric_cli_option_is_bounded():
    """A number on the command line always has bounds (IntRange / FloatRange)."""
    loose = []
    for name, cmd in _commands(main):
        for p in cmd.params:
            if isinstance(p, click.Option) and isinstance(p.type, (click.types.IntParamType, click.types.FloatParamType)) \
                    and not isinstance(p.type, (click.IntRange, click.FloatRange)):
                loose.append(f"{name} {p.opts[0]}")
    assert not loose, f"unbounded numeric options: {loose}"


@pytest.mark.parametrize("args, option", [
    (["masks", "trial", "OUT", "--seed", "-1"], "--seed"),
    (["masks", "trial", "OUT", "--size", "8"], "--size"),
    (["calibrate", "P", "--out", "O", "--population", "2"], "--population"),
    (["calibrate", "P", "--out", "O", "--model", "eq2"], "--model"),
    (["calibrate", "P", "--out", "O", "--threads", "0"], "--threads"),
    (["diagnose", "P", "--base", "B", "--out", "O", "--folds", "1"], "--folds"),
    (["augment", "P", "O", "--test-fraction", "1"], "--test-fraction"),
    (["augment", "P", "O", "--count", "1"], "--count"),
    (["train", "D", "O", "--lr", "0"], "--lr"),
    (["train", "D", "O", "--epochs", "0"], "--epochs"),
    (["register", "B", "O", "--level", "1"], "--level"),
    (["benchmark", "job", ".", "O", "--doses", "1,0"], "--doses"),
    (["compensate", "D.png", "--model", "M", "-o", "m.png", "--offset", "-1", "0"], "--offset"),
])
def test_out_of_bounds_options_are_one_line_errors(tmp_path, args, option):
    with CliRunner().isolated_filesystem(temp_dir=tmp_path):
        r = CliRunner().invoke(main, args)
        assert r.exit_code == 2, r.output
        assert option in r.output and "Traceback" not in r.output
        assert not Path("O").exists() and not Path("OUT").exists()


# ------------------------------------------------------------- the package defaults
def _default(fn, name):
    return inspect.signature(fn).parameters[name].default


def test_package_defaults_follow_the_settings():
    from unscatter import augment, benchmark, calibration, compensation, diagnosis, masks, training
    from unscatter.imaging import register_batch
    from unscatter.imaging.batch import Settings

    for fn in (masks.trial_masks, masks.write_trial_masks):
        for k in ("count", "seed", "size"):
            assert _default(fn, k) == getattr(S.TRIAL_MASKS.default, k), (fn.__name__, k)
    for k in ("mode", "level", "min_score", "skip_failed"):
        assert _default(register_batch, k) == getattr(S.REGISTRATION.default, k), k
        assert getattr(Settings(), k) == getattr(S.REGISTRATION.default, k), k
    assert _default(calibration.calibrate, "model") == S.CALIBRATION.default.model
    assert _default(calibration.calibrate, "seed") == S.CALIBRATION.default.seed
    for k in ("population", "generations", "folds", "bootstrap", "free_c0", "refine", "threads", "objective"):
        assert calibration.DEFAULTS[k] == getattr(S.CALIBRATION.default, k), k
    for k in ("folds", "seed", "quick"):
        assert _default(diagnosis.diagnose, k) == getattr(S.DIAGNOSIS.default, k), k
    assert diagnosis.DEFAULTS["threads"] == S.DIAGNOSIS.default.threads
    # diagnosis.folds null means "4, or 3 with quick": say what the package does
    assert (diagnosis.DEFAULTS["folds"], diagnosis.QUICK["folds"]) == (4, 3)
    assert "null - 4, or 3 with quick" in S.DIAGNOSIS["folds"].description
    for k in ("seed", "size", "test_fraction", "workers"):
        assert _default(augment.augment, k) == getattr(S.AUGMENTATION.default, k), k
    assert _default(training.train, "preset") == S.TRAINING.default.preset
    assert training.DEFAULTS["seed"] == S.TRAINING.default.seed
    assert sorted(training.PRESETS) == sorted(S.TRAINING["preset"].choices) == sorted(S.PRESET_PAIRS)
    assert compensation.ILT_DEFAULTS["robust"] == S.COMPENSATION.default.robust
    assert tuple(compensation.METHODS) == S.METHODS
    assert benchmark.IDENTICAL_DOSES == tuple(S.BENCHMARK.default.doses)
    from unscatter.design import design_masks

    for k in ("pool", "draws", "seed", "size", "criterion"):
        assert _default(design_masks, k) == getattr(S.TRIAL_MASKS.default, k), k


def test_model_and_effect_names_are_the_libraries():
    from unscatter.model import effect_names, model_names

    assert list(S.MODEL_NAMES) == model_names()
    assert list(S.EFFECT_NAMES) == effect_names()
    from unscatter.fitting import OBJECTIVES

    assert sorted(OBJECTIVES) == sorted(S.CALIBRATION["objective"].choices)


def test_no_copied_default_literals():
    """The paper's pixel size and the preset pair counts live in settings.py only (the
    virtual lab's own config is the lab's, kept apart on purpose)."""
    found = []
    for root in (REPO / "src", REPO / "workflow"):
        for f in root.rglob("*"):
            if f.suffix not in (".py", ".smk") or f.name == "settings.py":
                continue
            for i, line in enumerate(f.read_text().splitlines(), 1):
                code = line.split("#")[0]
                if re.search(r"\b2\.96\b", code) or re.search(r"\"(paper|default|ci)\":\s*(4000|1200|40)\b", code):
                    found.append(f"{f.relative_to(REPO)}:{i}")
    assert not found, found


# --------------------------------------------------------------- checks everywhere
@pytest.mark.parametrize("call, message", [
    (lambda: __import__("unscatter.masks", fromlist=["x"]).trial_masks(2, seed=-1), "trial_masks.seed"),
    (lambda: __import__("unscatter.masks", fromlist=["x"]).trial_masks(0), "trial_masks.count"),
    (lambda: __import__("unscatter.training", fromlist=["x"]).settings_for("ci", lr=-1.0), "training.lr"),
    (lambda: __import__("unscatter.imaging", fromlist=["x"]).register_batch("b", "o", level=1.5), "registration.level"),
    (lambda: __import__("unscatter.calibration", fromlist=["x"]).calibrate("p", "o", population=2), "calibration.population"),
])
def test_the_package_checks_the_same_bounds(call, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        call()


def test_the_schema_rejects_what_the_settings_reject():
    schema = yaml.safe_load(SCHEMA.read_text())
    v = jsonschema.Draft202012Validator(schema)
    assert v.is_valid({"trial_masks": {"seed": 3}})
    for bad in ({"trial_masks": {"seed": -1}}, {"registration": {"level": 1.0}}, {"diagnosis": {"folds": 1}},
                {"calibration": {"model": "eq2"}}, {"benchmark": {"doses": [0.0]}}, {"compensation": {"methods": []}}):
        assert not v.is_valid(bad), bad
        section, (key, value) = next(iter(bad.items())), next(iter(next(iter(bad.values())).items()))
        with pytest.raises(ValueError):
            dict((st.key, st) for st in S.SECTIONS)[section[0]].check(key, value)


@pytest.mark.parametrize("setting, value, ok", [
    (S.CALIBRATION["population"], True, False),  # a boolean is not a number
    (S.CALIBRATION["population"], 4.0, False),
    (S.CALIBRATION["population"], 4, True),
    (S.REGISTRATION["level"], float("nan"), False),
    (S.REGISTRATION["level"], 1, False),
    (S.REGISTRATION["level"], 0.3, True),
    (S.BENCHMARK["doses"], [1.0, 1.0], True),  # doses may repeat (not unique)
    (S.COMPENSATION["methods"], ["nn", "nn"], False),
    (S.LAB["batch"], "../x", False),
    (S.LAB["config"], None, True),
    (S.TRIAL_MASKS["count"], None, False),
])
def test_setting_check(setting, value, ok):
    if ok:
        setting.check(value)
    else:
        with pytest.raises(ValueError):
            setting.check(value)


def test_stage_objects_are_typed_and_frozen():
    r = S.REGISTRATION.make(level=0.7)
    assert (r.level, r.min_score, r.mode) == (0.7, 0.6, "similarity")
    with pytest.raises(Exception):
        r.level = 0.2
    with pytest.raises(KeyError):
        S.REGISTRATION.make(levle=0.3)
