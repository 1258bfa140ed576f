"""Every user-facing setting, once: its default, its bounds and what it means.

Each stage has one ``Stage`` of ``Setting`` s. The command line builds its options from
them (default, help text, and a click type that enforces the bounds), the package
functions take their defaults from them and check the values they are given, and the
workflow's config schema (workflow/schemas/config.schema.yaml) is generated from them:

    python -m unscatter.settings > workflow/schemas/config.schema.yaml

tests/test_settings.py fails when the committed schema, config/config.yaml, a command
line option or a package default says otherwise, so none of them can drift.

This module imports nothing heavy (no torch, no numpy): the workflow's common.smk loads
it by path during a dry-run.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, make_dataclass
from typing import Any

# ------------------------------------------------------------------------ pieces


@dataclass(frozen=True)
class Range:
    """A closed or open interval of a numeric setting (``hi`` may be ``math.inf``)."""

    lo: float
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False

    def __contains__(self, x) -> bool:
        lo_ok = x > self.lo if self.lo_open else x >= self.lo
        hi_ok = x < self.hi if self.hi_open else x <= self.hi
        return lo_ok and hi_ok

    def text(self) -> str:
        if math.isinf(self.hi):
            return f"{'>' if self.lo_open else '>='} {self.lo:g}"
        return f"in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"

    def schema(self) -> dict:
        """The JSON-schema keywords that say the same."""
        out = {("exclusiveMinimum" if self.lo_open else "minimum"): self.lo}
        if not math.isinf(self.hi):
            out["exclusiveMaximum" if self.hi_open else "maximum"] = self.hi
        return out


SEED = Range(0, 2**32 - 1)  # numpy's seeds are non-negative


@dataclass(frozen=True)
class Setting:
    """One setting: its type, default, bounds and meaning.

    kind: integer | number | boolean | string | array. ``items``: the Setting of an
    array's items (its kind, choices and range; its default unused). ``workflow``:
    whether the config schema has it (some settings are the command line's only).
    """

    kind: str
    default: Any
    description: str
    range: Range | None = None
    choices: tuple | None = None
    nullable: bool = False
    items: Setting | None = None
    unique: bool = False
    min_items: int | None = None
    min_length: int | None = None
    pattern: str | None = None
    workflow: bool = True

    _PYTHON = {"integer": int, "number": float, "boolean": bool, "string": str, "array": list}

    def check(self, value, name: str = "value"):
        """``value`` if it is of this setting's type and within its bounds, else a
        ValueError naming the setting and what is wrong. Integers are taken as numbers;
        booleans are never taken as numbers."""
        if value is None:
            if self.nullable:
                return None
            raise ValueError(f"{name}: a value is required (not null)")
        if self.kind == "array":
            if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
                raise ValueError(f"{name}: {value!r} is not a list")
            value = list(value)
            if self.min_items is not None and len(value) < self.min_items:
                raise ValueError(f"{name}: needs at least {self.min_items} item(s)")
            if self.unique and len(set(map(repr, value))) < len(value):
                raise ValueError(f"{name}: {value!r} repeats an item")
            return [self.items.check(v, f"{name} item") for v in value] if self.items else value
        ok = {
            "integer": isinstance(value, int) and not isinstance(value, bool),
            "number": isinstance(value, (int, float)) and not isinstance(value, bool),
            "boolean": isinstance(value, bool),
            "string": isinstance(value, str),
        }[self.kind]
        if not ok:
            raise ValueError(f"{name}: {value!r} is not a{'n' if self.kind[0] in 'ai' else ''} {self.kind}")
        if self.kind == "number":
            value = float(value)
            if not math.isfinite(value):
                raise ValueError(f"{name}: {value!r} is not a finite number")
        if self.range is not None and value not in self.range:
            raise ValueError(f"{name}: {value!r} is not {self.range.text()}")
        if self.choices is not None and value not in self.choices:
            raise ValueError(f"{name}: {value!r} is not one of {', '.join(map(str, self.choices))}")
        if self.min_length is not None and len(value) < self.min_length:
            raise ValueError(f"{name}: {value!r} is too short")
        if self.pattern is not None:
            import re

            if not re.fullmatch(self.pattern.strip("^$"), value):
                raise ValueError(f"{name}: {value!r} does not match {self.pattern}")
        return value

    def schema(self) -> dict:
        """This setting as a JSON-schema property."""
        out: dict = {"type": [self.kind, "null"] if self.nullable else self.kind}
        if self.range is not None:
            out.update(self.range.schema())
        if self.choices is not None:
            out["enum"] = list(self.choices)
        if self.min_length is not None:
            out["minLength"] = self.min_length
        if self.pattern is not None:
            out["pattern"] = self.pattern
        if self.kind == "array":
            if self.unique:
                out["uniqueItems"] = True
            if self.min_items is not None:
                out["minItems"] = self.min_items
        out["default"] = list(self.default) if isinstance(self.default, tuple) else self.default
        out["description"] = self.description
        if self.items is not None:
            item = self.items.schema()
            item.pop("default")
            item.pop("description")
            out["items"] = item
        return out

    def python_type(self):
        t = self._PYTHON[self.kind]
        return t | None if self.nullable else t


def _int(default, description, lo=None, **kw) -> Setting:
    return Setting("integer", default, description, range=None if lo is None else Range(lo), **kw)


def _seed(description="Seed of the stage's randomness.", **kw) -> Setting:
    return Setting("integer", kw.pop("default", 0), description, range=SEED, **kw)


def _bool(default, description, **kw) -> Setting:
    return Setting("boolean", default, description, **kw)


def _choice(default, choices, description, **kw) -> Setting:
    return Setting("string", default, description, choices=tuple(choices), **kw)


class Stage:
    """The settings of one stage (a section of the workflow config).

    ``default`` is the stage's defaults as a typed, frozen object
    (``REGISTRATION.default.level``); ``make(**values)`` checks values and returns such an
    object; ``check(name, value)`` checks one value.
    """

    def __init__(self, key: str, description: str, **settings: Setting):
        self.key = key
        self.description = description
        self.settings = settings
        cls_name = "".join(part.title() for part in key.split("_")) + "Settings"
        self._cls = make_dataclass(
            cls_name,
            [(k, s.python_type(), field(default=tuple(s.default) if isinstance(s.default, list) else s.default))
             for k, s in settings.items()],
            frozen=True,
        )
        self._cls.__doc__ = description
        self.default = self._cls()

    def __getitem__(self, name: str) -> Setting:
        return self.settings[name]

    def __iter__(self):
        return iter(self.settings.items())

    def check(self, name: str, value):
        """``value`` checked against the setting ``name`` (ValueError: '<stage>.<name>: ...')."""
        if name not in self.settings:
            raise KeyError(f"{self.key} has no setting {name!r}; known: {', '.join(self.settings)}")
        return self.settings[name].check(value, f"{self.key}.{name}")

    def make(self, **values):
        """The stage's settings: its defaults with ``values`` checked and put in."""
        checked = {k: self.check(k, v) for k, v in values.items()}
        checked = {k: tuple(v) if isinstance(v, list) else v for k, v in checked.items()}
        return self._cls(**{**{k: getattr(self.default, k) for k in self.settings}, **checked})

    def schema(self) -> dict:
        props = {k: s.schema() for k, s in self.settings.items() if s.workflow}
        return {"type": "object", "default": {}, "additionalProperties": False, "description": self.description,
                "properties": props}


# ------------------------------------------------------------------ shared values

# The printer models calibration knows (unscatter.model.model_names(); a test keeps them equal).
MODEL_NAMES = ("eq1",)
# The effect library (unscatter.model.effect_names(); a test keeps them equal).
EFFECT_NAMES = ("heavy_tail", "anisotropy", "dose_nonlinearity", "illumination_field", "edge_offset")
METHODS = ("nn", "ilt", "nn+ilt")
# Augmentation pairs each training preset is sized for (augmentation.count null).
PRESET_PAIRS = {"paper": 4000, "default": 1200, "ci": 40}
# Guan et al. 2022, 'Bioprinting setup': 2.96 um per DMD pixel. Only the print job's
# batch.yaml template uses it, when no calibrated model says otherwise.
PAPER_PIXEL_SIZE_UM = 2.96


# ------------------------------------------------------------------------ stages

WORKFLOW = Stage(
    "workflow",
    "Settings of the workflow as a whole.",
    results=Setting("string", "results", "Folder that every output, log and benchmark goes under. A test run can use its own "
                    "(config/ci.yaml: results/ci) and leave the full run's results alone. It must not be data/ or inside "
                    "it, nor the repository or a folder holding it.", min_length=1),
    source=_choice("lab", ("lab", "batches"),
                   "Where the print batches come from. 'lab': the trial masks are printed and imaged on the virtual lab "
                   "(one batch, named by lab.batch). 'batches': the print batches listed under 'batches', in the data "
                   "contract (batch.yaml, masks/, images/)."),
    batches=Setting("array", [], "Print batches to use when source is 'batches'. An entry without a '/' names a folder "
                    "under data/prints/; an entry with a '/' is the path of a batch folder. The batch's name (the entry, "
                    "or the folder's name once the path is resolved) names its outputs, so names must be unique plain "
                    "names (no '/', not starting with '.').", unique=True,
                    items=Setting("string", None, "", min_length=1)),
    model=_choice("selected", ("selected", "base"),
                  "The printer model that augmentation, training and compensation use. selected - the diagnosis's "
                  "model.yaml (the base model plus the effects it accepted; the base model itself when it accepted "
                  "none); base - calibration.model as calibrated."),
)

TRIAL_MASKS = Stage(
    "trial_masks",
    "The trial masks that the virtual lab prints (Guan et al. 2022, 'Trial data acquisition').",
    count=_int(32, "Number of trial masks (paper: 32).", lo=1),
    seed=_seed("Seed of the trial masks; mask i depends only on (seed, i).", default=1),
    size=_int(512, "Side of the design region in DMD pixels (paper: 512).", lo=64),
    kind=_choice("paper", ("paper", "designed"),
                 "paper - the paper's random checkerboards, rectangles and circles; designed - chosen from a pool of "
                 "candidates to teach the printer model the most (unscatter.design: D-optimal on the print's "
                 "sensitivity to the parameters, effects included)."),
    pool=_int(160, "designed: candidate masks to choose from.", lo=1),
    draws=_int(3, "designed: draws of the printer's parameters the design must suit (pseudo-Bayesian design).", lo=1),
    criterion=_choice("paired", ("d", "discrimination", "paired"),
                      "designed: d - D-optimal on the parameters, effects included; discrimination - the same plus "
                      "telling the library's effects apart: every effect's print change must stand out from Eq. 1 "
                      "and from each other effect in its place (linearised T-optimality, unscatter.design.separation); "
                      "paired - D-optimal plus every effect's evidence spread over the prints, as the diagnosis's "
                      "paired test over prints needs it (unscatter.design.paired)."),
    fiducials=_bool(True, "designed: three registration marks (solid squares of 40 px at full grey in three corners, "
                    "a cleared band around them) on every designed mask, so that every print's pose rests on them "
                    "whatever the rest of the mask is (unscatter.masks.fiducial_marks)."),
    paper_fiducials=_bool(False, "paper: the designed masks' three registration marks on the paper's random masks "
                          "too (the paper's masks have none; false keeps them as the paper has them). The "
                          "registration checks each print's pose against its marks; they replace an 80 px square at "
                          "each of three corners of a 512 px field (scaled with the size)."),
    next=_int(0, "Masks of the next print batch, designed around the diagnosis's model and the prints so far "
              "(sequential design, results/next_trial_masks/); 0 - none.", lo=0),
)

LAB = Stage(
    "lab",
    "The virtual lab (printer + microscope) that plays the real lab when source is 'lab'.",
    batch=Setting("string", "lab", "Name of the batch that the virtual lab writes (results/lab/<batch>/).",
                  pattern="^[A-Za-z0-9][A-Za-z0-9_-]*$"),
    config=Setting("string", None, "YAML file of overrides of the lab's defaults (src/unscatter/lab/default.yaml), e.g. "
                   "to switch on an effect; null uses the defaults.", nullable=True),
    seed=_seed("Seed of the lab's randomness (cells, noise, the pose of each image).", default=2022),
)

REGISTRATION = Stage(
    "registration",
    "Registration of each microscope image to its mask and thresholding into a binary print.",
    mode=_choice("similarity", ("similarity", "affine"),
                 "Transform from image to mask coordinates (similarity: rotation, scale, shift)."),
    level=Setting("number", 0.5, "The print is where the density is above this fraction of the batch's dense-polymer "
                  "level (0 would make the background a print, 1 leaves nothing).",
                  range=Range(0, 1, lo_open=True, hi_open=True)),
    min_score=Setting("number", 0.6, "Quality control: lowest registration score accepted (a correlation's share in "
                      "[0, 1]).", range=Range(0, 1)),
    skip_failed=_bool(False, "Go on when a print fails quality control (it is marked failed in qc.tsv and never used); "
                      "false stops at the first failed print."),
)

CALIBRATION = Stage(
    "calibration",
    "Calibration of the printer simulator on the registered prints (Guan et al. 2022, 'Simulator calibration').",
    model=_choice("eq1", MODEL_NAMES, "Printer model to calibrate (eq1: Eq. 1 of the paper; the names of "
                  "unscatter.model.model_names())."),
    seed=_seed("Seed of the genetic algorithm, the folds and the bootstrap."),
    population=_int(48, "GA population size.", lo=4),
    generations=_int(30, "GA generations.", lo=1),
    folds=_int(4, "k-fold cross-validation over prints for held-out error (0 or 1 - none).", lo=0),
    bootstrap=_int(20, "Bootstrap replicates over prints for the parameters' spread (0 - none).", lo=0),
    free_c0=_bool(False, "Fit c0 as well (the paper's 7 parameters). Eq. 1 is unchanged when c and T are scaled "
                  "together, so by default c0 = 1 fixes that gauge."),
    objective=_choice("mismatch", ("mismatch", "pixel_error", "dice"),
                      "What the fit minimises (unscatter.fitting.OBJECTIVES): mismatch - the paper's mean squared "
                      "difference over all pixels (prints weigh by their area); pixel_error - each print's pixel error; "
                      "dice - 1 - Dice per print (IoU's twin). The diagnosis scores held-out prints with the same one. "
                      "On random labs mismatch named the effects as well or better (benchmarks/bench_diagnosis.py)."),
    refine=_bool(True, "Gradient refinement (L-BFGS on a smooth threshold) after the GA.", workflow=False),
    measurement=_choice("auto", ("auto", "registration", "none"),
                        "The measurement between the simulated cure and the measured print (unscatter.measurement): "
                        "auto - as none, but where the fitted sigma is no larger than the blur the registration's "
                        "template measured (the prints do not resolve the scattering) fitted again through the "
                        "measurement, the microscope's blur held: as batch.yaml states it (microscope_blur_um), else as "
                        "the template measured it; registration - the density blurred "
                        "by the microscope (the stated blur held, else fitted) and thresholded at the registration's "
                        "level, as registration.yaml records it (prints without one: none); none - the measured prints "
                        "taken for the cure itself (the paper's). See docs/calibration.md, 'The measurement in the calibration'.",
                        workflow=False),
    threads=_int(1, "torch CPU threads (1 is fastest when cores are shared).", lo=1, workflow=False),
    workers=_int(None, "Processes that run the refits of the folds and the bootstrap at once, each on one torch thread; "
                 "null - one per CPU core (1 on a GPU). With threads 1 the result does not depend on it.",
                 lo=1, nullable=True, workflow=False),
)

DIAGNOSIS = Stage(
    "diagnosis",
    "The residual diagnosis (closed loop): held-out residuals of the calibrated model, effects of the library added "
    "while they lower the held-out error beyond the noise, and the selected model (results/diagnosis/model.yaml).",
    candidates=Setting("array", [], "Candidate effects (" + ", ".join(EFFECT_NAMES) + "); empty - the whole library.",
                       unique=True, items=_choice(None, EFFECT_NAMES, "")),
    folds=_int(None, "k-fold over prints for the held-out residuals (every residual comes from a fit without that "
               "print); null - 4, or 3 with quick.", lo=2, nullable=True),
    seed=_seed("Seed of the folds, the fits and the bootstrap."),
    quick=_bool(False, "Small fits (unscatter.diagnosis.QUICK), seconds to a minute; for CI."),
    gain_test=_choice("sign_flip", ("sign_flip", "t"),
                      "The paired test over prints that a candidate effect's held-out gain must pass (one-sided p "
                      "below unscatter.diagnosis.DEFAULTS max_p, beside the bootstrap interval and the least gain, "
                      "min_improvement): sign_flip - Fisher's sign-flip "
                      "test of the mean gain (exact up to 16 prints); t - Student's paired t-test, which the gains' "
                      "spread (they differ by print by orders of magnitude) makes conservative. docs/diagnosis.md, "
                      "'The sign-flip test of a candidate's gain'."),
    threads=_int(1, "torch CPU threads (1 is fastest when cores are shared).", lo=1, workflow=False),
    workers=_int(None, "Processes that run the fits at once, each on one torch thread (the folds of every candidate "
                 "of a round in parallel); null - one per CPU core (1 on a GPU). The result does not depend on it.",
                 lo=1, nullable=True, workflow=False),
)

DESIGNS = Stage(
    "designs",
    "The target structures to compensate and benchmark (binary PNGs, nonzero = solid).",
    folder=Setting("string", "data/designs", "Folder of design PNGs (same size as the trial masks).", min_length=1),
    names=Setting("array", [], "Designs to use, by file name without .png; empty - every PNG in the folder.",
                  unique=True, items=Setting("string", None, "", min_length=1)),
)

AUGMENTATION = Stage(
    "augmentation",
    "Simulated mask/print pairs from the calibrated printer (Guan et al. 2022, 'Data augmentation'), written as a "
    "Zarr store.",
    count=_int(None, "Mask/print pairs (at least one to train on and one to test); null - what the training preset is "
               "sized for (" + ", ".join(f"{k} {v}" for k, v in PRESET_PAIRS.items()) + ").", lo=2, nullable=True),
    seed=_seed("Seed of the augmentation masks."),
    test_fraction=Setting("number", 0.1, "Held-out share of the pairs (the paper's 400 of 4,000).",
                          range=Range(0, 1, lo_open=True, hi_open=True)),
    size=_int(512, "Mask side in DMD pixels (paper: 512; the workflow uses trial_masks.size).", lo=64,
              workflow=False),
    workers=_int(None, "Parallel workers (null: one per CPU core).", lo=1, nullable=True, workflow=False),
)

TRAINING = Stage(
    "training",
    "The master and slave U-Nets (Guan et al. 2022, Fig. 4), trained with Eq. 2.",
    preset=_choice("default", ("default", "paper", "ci"),
                   "default - two CPU cores, 8 to 11 minutes; paper - the paper's sizes (for a GPU); ci - seconds. "
                   "src/unscatter/training.py (PRESETS) says what each sets and why."),
    epochs=_int(None, "Epochs; null - the preset's (paper: 200).", lo=1, nullable=True),
    seed=_seed("Seed of the weights and the batches."),
    gpus=_int(0, "GPUs to ask the cluster for (SLURM profile); training uses a GPU whenever the machine has one.", lo=0),
    width=_int(None, "Base channels of the U-Nets; null - the preset's (paper: 64).", lo=1, nullable=True,
               workflow=False),
    scale=_int(None, "Train on the field area-downsampled by this factor; null - the preset's.", lo=1, nullable=True,
               workflow=False),
    crop=_int(None, "Train on random crops of this side (at the training scale); null - the preset's (whole field).",
              lo=16, nullable=True, workflow=False),
    coords=_bool(None, "X, Y coordinate channels as extra inputs; null - the preset's.", nullable=True, workflow=False),
    lr=Setting("number", None, "Adam learning rate; null - the preset's (paper: 1e-5).",
               range=Range(0, 1, lo_open=True), nullable=True, workflow=False),
    batch=_int(None, "Batch size; null - the preset's (paper: 10).", lo=1, nullable=True, workflow=False),
    max_train=_int(None, "Use at most this many training pairs; null - the preset's (all).", lo=1, nullable=True,
                   workflow=False),
    threads=_int(None, "torch CPU threads; null - torch's setting.", lo=1, nullable=True, workflow=False),
)

COMPENSATION = Stage(
    "compensation",
    "Masks that print the designs despite the scattering.",
    methods=Setting("array", list(METHODS), "nn - the trained master network (the paper); ilt - the mask optimised "
                    "through the calibrated simulator; nn+ilt - the network's mask refined by ILT.", unique=True,
                    min_items=1, items=_choice(None, METHODS, "")),
    robust=_bool(True, "ILT optimises for 90, 100 and 110 % of the nominal dose at once (robust to dose drift)."),
)

BENCHMARK = Stage(
    "benchmark",
    "Compensated masks against the identical mask at several grey levels, each printed at 90, 100 and 110 % of the "
    "exposure and scored against its design.",
    doses=Setting("array", [1.0, 0.75, 0.7, 0.5], "Grey levels of the identical mask (Guan et al. 2022, Fig. 6 - 100, "
                  "75, 70 and 50 %).", min_items=1, items=Setting("number", None, "", range=Range(0, 1, lo_open=True))),
    compare=Setting("array", ["ilt"], "Methods also computed with the other printer model (base when model is selected, "
                    "and the other way round) and benchmarked as <method>_<model>, e.g. ilt_base, so the benchmark "
                    "compares the two models. ilt needs no training; nn and nn+ilt train a second pair of networks. "
                    "Empty - no comparison.", unique=True, items=_choice(None, METHODS, "")),
    fiducials=_bool(True, "The trial masks' three registration marks (unscatter.masks.fiducial_marks) on every "
                    "benchmark mask of each design whose masks leave the field's corners dark (5 % grey at most, which the "
                    "marks replace: benchmark.MARK_ROOM_GREY), so that each print's pose "
                    "rests on them whatever the design (a star that maps onto itself turned, a dim print); the scoring "
                    "leaves the marks' corners out. false - the masks as the paper prints them."),
    batch=Setting("string", None, "With source 'batches': the batch of the benchmark's print job once printed and "
                  "imaged (a folder under data/prints/, or a path); it is scored, never used for calibration. null - the "
                  "print job is written and the benchmark is scored on the calibrated simulator only. With source 'lab' "
                  "the virtual lab prints the job.", nullable=True),
)

LAYERS = Stage(
    "layers",
    "Multi-layer (3-D) prints: 3-D trial prints, their z-stacks registered, the depth parameters calibrated, the "
    "3-D designs compensated and benchmarked against identical layer masks at the best uniform dose.",
    run=_bool(False, "Run the 3-D stages (results/layers/)."),
    count=_int(12, "3-D trial prints (bridges, channels, towers, stairs).", lo=3),
    layers=_int(8, "Layers of each 3-D trial print.", lo=2),
    size=_int(160, "Side of the 3-D trial prints in DMD pixels.", lo=32),
    seed=_seed("Seed of the 3-D trial prints.", default=3),
    free=Setting("array", ["sigma_px", "T"], "2-D parameters fitted with the depth parameters (the rest come from the "
                 "2-D model).", unique=True, items=_choice(None, ("sigma_px", "T"), "")),
    designs=Setting("string", "data/designs3d", "Folder of 3-D designs (one folder of layer PNGs each).", min_length=1),
    names=Setting("array", [], "3-D designs to use; empty - every one.", unique=True,
                  items=Setting("string", None, "", min_length=1)),
    bootstrap=_int(8, "Bootstrap replicates over the 3-D trial prints: the depth parameters' spread (0 - none).",
                   lo=0),
    batches=Setting("array", [], "With source 'batches': the 3-D trial print batches (z-stacks, in the data contract: "
                    "batch.yaml with layer_um and z_step_um, masks/<id>/ one PNG a layer, images/<id>.tif), named as "
                    "in 'batches'. Needed when run is true and source is 'batches'.", unique=True,
                    items=Setting("string", None, "", min_length=1)),
    benchmark_batch=Setting("string", None, "With source 'batches': the 3-D benchmark's print job once printed and "
                            "imaged as z-stacks; scored, never calibrated on. null - the print job is written, not "
                            "scored. With source 'lab' the virtual lab prints the job.", nullable=True),
)

# The config's layout: the workflow's own settings at the top level, then a section a stage.
SECTIONS = (TRIAL_MASKS, LAB, REGISTRATION, CALIBRATION, DIAGNOSIS, DESIGNS, AUGMENTATION, TRAINING, COMPENSATION,
            BENCHMARK, LAYERS)
_TOP = ("results", "source", "batches")  # before the sections; 'model' goes after diagnosis


def config_schema() -> dict:
    """The workflow's config schema (JSON schema, draft 2020-12) made from the settings."""
    props: dict = {k: WORKFLOW[k].schema() for k in _TOP}
    for stage in SECTIONS:
        props[stage.key] = stage.schema()
        if stage is DIAGNOSIS:
            props["model"] = WORKFLOW["model"].schema()
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "description": "Configuration of the unscatter workflow. Every key has a default here; config/config.yaml "
                       "repeats them (a test keeps the two equal), and a config given with --configfile only needs "
                       "the keys it changes. Generated from src/unscatter/settings.py (python -m unscatter.settings): "
                       "edit that, not this file.",
        "type": "object",
        "additionalProperties": False,
        "properties": props,
    }


def schema_text() -> str:
    import yaml

    head = ("# Generated from src/unscatter/settings.py: python -m unscatter.settings > workflow/schemas/config.schema.yaml\n"
            "# Edit the settings there; tests/test_settings.py fails when this file differs.\n")
    return head + yaml.safe_dump(config_schema(), sort_keys=False, width=110, allow_unicode=True)


if __name__ == "__main__":  # pragma: no cover
    import sys

    sys.stdout.write(schema_text())
