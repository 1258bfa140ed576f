# Config validation, the batch table, code versions and every input function.
# Nothing here imports torch or the unscatter package (only its settings module, by
# path): a dry-run and --lint stay fast.

import hashlib
import importlib.util
import os
import re
from functools import cache
from pathlib import Path

from snakemake.exceptions import WorkflowError
from snakemake.utils import validate


validate(config, schema="../schemas/config.schema.yaml")

# Every output, log and benchmark lives under this prefix (config/ci.yaml: results/ci).
RESULTS = config["results"].rstrip("/")

# Outputs of the multi-layer (3-D) stages (workflow/rules/layers.smk).
LAYERS = f"{RESULTS}/layers"

# The user's data: read, never written (README.md, 'Using your own print batches').
DATA = Path("data")

# What a batch folder must hold (README.md, 'Using your own print batches').
BATCH_CONTRACT = ("batch.yaml", "masks", "images")


def _within(inner, outer):
    """Whether the folder inner is outer or lies inside it (symbolic links resolved)."""
    inner, outer = Path(inner).resolve(), Path(outer).resolve()
    return inner == outer or outer in inner.parents


# ------------------------------------------------------------------------- batches
def _batch_folder(entry, what):
    """The folder a config entry names: a folder under data/prints/, or a path; and the
    batch's name, which names its outputs (results/prints/<name>/): the entry itself, or
    the resolved folder's name, and in either case a plain folder name."""
    bare = entry.rstrip(os.sep)  # "session1/" names data/prints/session1 too
    if os.sep in bare:
        folder = Path(bare).resolve()
        name = folder.name
    else:
        folder, name = DATA / "prints" / bare, bare
    if not name or name.startswith("."):
        raise WorkflowError(
            f"config: {what} {entry!r}: the batch name {name!r} is not a plain folder name "
            "(not empty, not starting with '.'); it names the batch's outputs"
        )
    missing = [part for part in BATCH_CONTRACT if not (folder / part).exists()]
    if missing:
        raise WorkflowError(
            f"config: {what} {entry!r}: {folder} lacks {', '.join(missing)} "
            f"(a batch holds {', '.join(BATCH_CONTRACT)}; see README.md)"
        )
    return name, folder


def _batch_folders():
    """Batch name -> folder. The name is the {batch} wildcard of every per-batch output."""
    if config["source"] == "lab":
        name = config["lab"]["batch"]
        return {name: f"{RESULTS}/lab/{name}"}
    if not config["batches"]:
        raise WorkflowError("config: source is 'batches' but the list 'batches' is empty")
    return _named_batches(config["batches"], "batches")


def _named_batches(entries, what):
    """Batch name -> folder of a config list of batches; two folders of one name are an error."""
    folders = {}
    for entry in entries:
        name, folder = _batch_folder(entry, what)
        if name in folders:
            raise WorkflowError(
                f"config: {what} {folders[name]} and {folder} have the same name {name!r}; "
                "outputs are named by the batch folder's name, so rename one folder"
            )
        folders[name] = str(folder)
    return folders


# The batches the printer is calibrated on.
BATCHES = _batch_folders()

# The batch of the benchmark's prints (name -> folder), never calibrated on: the virtual
# lab's print of the benchmark job, or a measured batch named by benchmark.batch.
LAB_BENCHMARK_BATCH = "benchmark_prints"


def _benchmark_batch():
    if config["source"] == "lab":
        if LAB_BENCHMARK_BATCH in BATCHES:
            raise WorkflowError(f"config: lab.batch must not be {LAB_BENCHMARK_BATCH!r} (the benchmark's prints)")
        return {LAB_BENCHMARK_BATCH: f"{RESULTS}/lab/{LAB_BENCHMARK_BATCH}"}
    if not config["benchmark"]["batch"]:
        return {}
    name, folder = _batch_folder(config["benchmark"]["batch"], "benchmark.batch")
    if name in BATCHES:
        raise WorkflowError(
            f"config: benchmark.batch {folder} is also a calibration batch ({BATCHES[name]}): "
            "the benchmark's prints are scored, never calibrated on"
        )
    return {name: str(folder)}


BENCHMARK_BATCH = _benchmark_batch()
ALL_BATCHES = {**BATCHES, **BENCHMARK_BATCH}


def _layer_batches():
    """The multi-layer batches (name -> folder): the 3-D trial prints', and the 3-D
    benchmark's (empty when its print job is not printed yet). The virtual lab's are
    named trials and benchmark; measured ones as in 'batches'."""
    if not config["layers"]["run"]:
        return {}, {}
    if config["source"] == "lab":
        return {"trials": f"{LAYERS}/lab/trials"}, {"benchmark": f"{LAYERS}/lab/benchmark"}
    if not config["layers"]["batches"]:
        raise WorkflowError("config: layers.run with source 'batches' needs layers.batches, the batches of the 3-D "
                            "trial prints (z-stacks; see README.md)")
    trials = _named_batches(config["layers"]["batches"], "layers.batches")
    bench = {}
    if config["layers"]["benchmark_batch"]:
        name, folder = _batch_folder(config["layers"]["benchmark_batch"], "layers.benchmark_batch")
        if name in trials:
            raise WorkflowError(f"config: layers.benchmark_batch {folder} has the name of a 3-D trial batch "
                                f"({trials[name]}): the benchmark's prints are scored, never calibrated on")
        bench[name] = str(folder)
    return trials, bench


# The 3-D trial batches the depth parameters are calibrated on, and the 3-D benchmark's.
LAYER_TRIALS, LAYER_BENCHMARK = _layer_batches()
LAYER_BATCHES = {**LAYER_TRIALS, **LAYER_BENCHMARK}


def _check_results():
    """results: the folder every output goes under must keep clear of what the workflow
    reads: not the repository (or a folder holding it), not data/ or inside it, not
    inside a batch or the designs' folder. Snakemake deletes an output before it
    remakes it, so an output that is a user's folder would be lost."""
    problem = None
    if _within(RESULTS, DATA):
        problem = "is data/ or lies in it, and the workflow only reads data/"
    elif _within(workflow.basedir, RESULTS) or _within(DATA, RESULTS):
        problem = "is the repository, or a folder that holds it or data/"
    else:
        measured = list(ALL_BATCHES.values()) + list(LAYER_BATCHES.values()) if config["source"] == "batches" else []
        reads = measured + [config["designs"]["folder"], config["layers"]["designs"]]
        inside = [f for f in reads if _within(RESULTS, f)]
        if inside:
            problem = f"lies in {inside[0]}, which the workflow only reads"
    if problem:
        raise WorkflowError(f"config: results: {config['results']!r} {problem}; give a folder of its own, e.g. results")


_check_results()


# The calibrated base model (Eq. 1) and the diagnosis's selected model (base + the
# effects it accepted). As the {model} wildcard of augmentation, training and
# compensation: the base model's name (eq1) or "selected".
BASE_MODEL = config["calibration"]["model"]
SELECTED = "selected"
MODELS = {"base": BASE_MODEL, "selected": SELECTED}
# The model that augmentation, training and compensation use (config 'model').
MODEL = MODELS[config["model"]]
# The other one: the benchmark compares its masks for the methods in benchmark.compare.
OTHER = next(label for label in MODELS if label != config["model"])


wildcard_constraints:
    batch="|".join(re.escape(name) for name in ALL_BATCHES),
    b3="|".join(re.escape(name) for name in LAYER_BATCHES) or "trials|benchmark",
    model="|".join(re.escape(name) for name in MODELS.values()),


def batch_folder(wildcards):
    """The folder of a batch: a virtual lab output or a folder the lab handed over."""
    return ALL_BATCHES[wildcards.batch]


def batch_files(wildcards):
    """Every file of a handed-over batch, so that a changed or added image reruns it.

    A virtual lab batch is a directory output of the lab rule and needs no list.
    """
    if config["source"] == "lab":
        return []
    return _contract_files(ALL_BATCHES[wildcards.batch])


def _contract_files(folder):
    root = Path(folder)
    files = [root / "batch.yaml"]
    for sub in ("masks", "images"):
        files += sorted(p for p in (root / sub).rglob("*")
                        if p.is_file() and not any(part.startswith(".") for part in p.relative_to(root).parts))
    return [str(p) for p in files]


def layer_batch_files(wildcards):
    """Every file of a measured multi-layer batch (the layer PNGs of masks/<id>/ too)."""
    return [] if config["source"] == "lab" else _contract_files(LAYER_BATCHES[wildcards.b3])


# ---------------------------------------------------------------------------- lab
def lab_config_file(wildcards):
    """The lab's override file as an input, so that editing it reruns the lab."""
    return [config["lab"]["config"]] if config["lab"]["config"] else []


# -------------------------------------------------------------------- code version
def _package_dir():
    # find_spec locates the installed package without importing it.
    spec = importlib.util.find_spec("unscatter")
    if spec is not None and spec.submodule_search_locations:
        return Path(next(iter(spec.submodule_search_locations)))
    return Path(workflow.basedir) / "src" / "unscatter"


PACKAGE_DIR = _package_dir()


@cache
def code_version(*parts):
    """Hash of the source of the named package modules or subpackages (e.g. "lab", "io").

    Snakemake's code trigger sees only the rule and its script, not the package it calls;
    this hash goes into params, so a change of the stage's code reruns the stage.
    A module that does not exist yet hashes as missing (the dry-run still plans it).
    """
    digest = hashlib.sha256()
    for part in parts:
        path = PACKAGE_DIR / part
        if path.is_dir():
            files = sorted(p for p in path.rglob("*") if p.suffix in (".py", ".yaml") and p.is_file())
        else:
            files = [path.with_suffix(".py")]
        for f in files:
            digest.update(f.relative_to(PACKAGE_DIR).as_posix().encode() + b"\0")
            digest.update(f.read_bytes() if f.is_file() else b"<missing>")
            digest.update(b"\0")
    return digest.hexdigest()[:16]


# ---------------------------------------------------------------------- designs
def design_files(wildcards=None):
    """The design PNGs as inputs, so that an added or edited design reruns what uses it."""
    folder = Path(config["designs"]["folder"])
    if not folder.is_dir():
        raise WorkflowError(f"config: designs.folder {folder} is not a folder")
    files = {p.stem: str(p) for p in sorted(folder.glob("*.png"))}
    names = config["designs"]["names"] or list(files)
    missing = [n for n in names if n not in files]
    if missing:
        raise WorkflowError(f"config: designs.names: no {', '.join(missing)} (.png) in {folder}")
    if not names:
        raise WorkflowError(f"config: designs.folder {folder} has no .png designs")
    return [files[n] for n in names]


# -------------------------------------------------------------------------- targets
def registered_prints():
    """The registered prints the printer is calibrated on (not the benchmark's)."""
    return expand(f"{RESULTS}/prints/{{batch}}", batch=BATCHES)


def calibrated_model():
    return f"{RESULTS}/calibration/{BASE_MODEL}"


def diagnosis_dir():
    return f"{RESULTS}/diagnosis"


def model_dir(model):
    """The folder of a {model} wildcard's params: the calibration's params.yaml, or the
    diagnosis's model.yaml (unscatter.model.load_params takes either folder)."""
    return diagnosis_dir() if model == SELECTED else f"{RESULTS}/calibration/{model}"


def compensated(model=MODEL):
    return {m: f"{RESULTS}/compensated/{model}/{m}" for m in config["compensation"]["methods"]}


def benchmark_masks():
    """Benchmark method label -> folder of its masks: the methods with the model in use
    under their own names, then benchmark.compare with the other model, as <method>_<other>
    (e.g. ilt_base), so that the benchmark compares the base and the selected model."""
    masks = compensated()
    for m in config["benchmark"]["compare"]:
        masks[f"{m}_{OTHER}"] = f"{RESULTS}/compensated/{MODELS[OTHER]}/{m}"
    return masks


def benchmark_targets():
    out = [f"{RESULTS}/benchmark/simulated", f"{RESULTS}/benchmark/print_job"]
    if BENCHMARK_BATCH:
        out.append(f"{RESULTS}/benchmark/metrics.tsv")
    return out


def all_input(wildcards):
    """The final outputs of every stage; a new stage adds its targets here."""
    targets = []
    targets += registered_prints()
    targets.append(calibrated_model())
    targets.append(diagnosis_dir())
    targets.append(f"{RESULTS}/train/{MODEL}")
    targets += list(benchmark_masks().values())
    targets += benchmark_targets()
    targets.append(f"{RESULTS}/report.html")
    if config["trial_masks"]["next"]:
        targets.append(f"{RESULTS}/next_trial_masks")
    targets += layers_targets()
    return targets


def layers_targets():
    """The multi-layer stages' final outputs: the scored 3-D benchmark, or its print job
    while no measured 3-D benchmark batch is given."""
    if not config["layers"]["run"]:
        return []
    targets = [f"{LAYERS}/prints/{name}" for name in LAYER_TRIALS] + [f"{LAYERS}/benchmark/print_job"]
    if LAYER_BENCHMARK:
        targets.append(f"{LAYERS}/benchmark/scores")
    return targets


# ----------------------------------------------------------------------- networks
def _settings_module():
    """unscatter.settings, loaded from its file: the one source of the settings' defaults
    (the schema above is generated from it), without importing the package and torch."""
    import sys

    spec = importlib.util.spec_from_file_location("_unscatter_settings", PACKAGE_DIR / "settings.py")
    settings = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = settings  # dataclasses look their module up
    spec.loader.exec_module(settings)
    return settings


# Pairs each training preset is sized for.
PRESET_PAIRS = _settings_module().PRESET_PAIRS


def augment_count():
    return config["augmentation"]["count"] or PRESET_PAIRS[config["training"]["preset"]]


# ------------------------------------------------------------------ multi-layer


def designs3d_files(wildcards=None):
    """The 3-D designs' layer PNGs as inputs, so that an edited design reruns what uses it."""
    folder = Path(config["layers"]["designs"])
    if not folder.is_dir():
        raise WorkflowError(f"config: layers.designs {folder} is not a folder")
    found = sorted(p.name for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))
    names = config["layers"]["names"] or found
    missing = [n for n in names if n not in found]
    if missing:
        raise WorkflowError(f"config: layers.names: no {', '.join(missing)} in {folder}")
    return [str(p) for n in names for p in sorted((folder / n).glob("*.png"))]
