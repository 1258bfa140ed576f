"""The virtual lab: a DLP bioprinter and a fluorescence microscope.

It plays the real lab, so it is deliberately richer than Eq. 1 of Guan et al. 2022:
besides a quadratic illumination field, a Gaussian scattering kernel and a cure
threshold it has cell-to-cell dose randomness, a saturating polymer density, and
effects that Eq. 1 lacks (heavy-tailed scattering by default; anisotropy, grey-level
dose nonlinearity, illumination beyond quadratic and post-wash swelling/erosion can be
switched on in its config). Its microscope can add haze, a tilted background and uneven
staining, off by default. ``random_lab`` (``unscatter.lab.random``) draws whole labs
over wide ranges, to test registration on labs it was never tuned to.

Nothing outside ``unscatter.lab`` and its tests may import it or read its config:
calibration, diagnosis and compensation see only the files a real lab would hand over.
"""

from __future__ import annotations

import copy
from importlib import resources
from pathlib import Path

import yaml

from .microscope import image_print
from .printer import Printer, polymer_density
from .random import describe_lab, random_lab

__all__ = ["Printer", "polymer_density", "image_print", "load_config", "print_batch", "print_layers", "read_job",
           "random_lab", "describe_lab"]


def default_config() -> dict:
    with resources.files(__package__).joinpath("default.yaml").open() as fh:
        return yaml.safe_load(fh)


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in (over or {}).items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def load_config(path=None, overrides: dict | None = None) -> dict:
    """The lab config: package defaults, then a user file, then overrides (deep merge)."""
    cfg = default_config()
    if path is not None:
        from ..io import read_yaml

        cfg = _merge(cfg, read_yaml(path))
    if overrides:
        cfg = _merge(cfg, overrides)
    return cfg


def print_batch(mask_dir, out_batch, lab_config=None, truth_dir=None, overrides=None, seed=None, progress=True,
                exposures: dict | None = None, inputs=()):
    """Print every mask in MASK_DIR and image it; write a batch in the data contract.

    ``exposures`` (mask id -> factor of the nominal exposure, default 1) prints some masks
    longer or shorter, as a print job's ``job.tsv`` asks (see ``read_job``). The truth (true transforms, noise-free prints in mask coordinates, polymer density)
    goes to ``truth_dir`` (default: ``<out_batch>.truth``), outside the batch. Both are
    new folders or earlier outputs of the lab, apart from MASK_DIR, the lab config and
    ``inputs`` (e.g. the job.tsv that ``exposures`` came from).
    """
    from .run import run_batch

    cfg = load_config(lab_config, overrides)
    if seed is not None:
        cfg["seed"] = int(seed)
    out_batch = Path(out_batch)
    truth_dir = Path(truth_dir) if truth_dir else out_batch.with_name(out_batch.name + ".truth")
    return run_batch(Path(mask_dir), out_batch, truth_dir, cfg, progress=progress, exposures=exposures,
                     inputs=[*inputs, *([lab_config] if lab_config else [])], source=lab_config or "lab config")


def print_layers(mask_root, out_batch, lab_config=None, truth_dir=None, overrides=None, seed=None, progress=True):
    """Print and image multi-layer masks: every folder ``mask_root/<id>/`` holds one PNG a
    layer, bottom first. Writes a batch (masks/<id>/, images/<id>.tif confocal z-stacks,
    batch.yaml with layer_um and z_step_um) and its truth (default ``<out_batch>.truth``:
    voxel prints, density, the poses and z offsets); see ``unscatter.lab.layers``."""
    from .layers import run_layers

    cfg = load_config(lab_config, overrides)
    if seed is not None:
        cfg["seed"] = int(seed)
    out_batch = Path(out_batch)
    truth_dir = Path(truth_dir) if truth_dir else out_batch.with_name(out_batch.name + ".truth")
    return run_layers(Path(mask_root), out_batch, truth_dir, cfg, progress=progress,
                      inputs=[lab_config] if lab_config else [], source=lab_config or "lab config")


def read_job(job_tsv) -> dict:
    """mask id -> exposure factor from a print job's ``job.tsv`` (columns id, exposure)."""
    from ..io import InputError, read_tsv

    rows = read_tsv(job_tsv)
    if not rows or "id" not in rows[0] or "exposure" not in rows[0]:
        raise InputError(job_tsv, "a print job needs the columns 'id' and 'exposure'")
    out = {}
    for r in rows:
        try:
            out[r["id"]] = float(r["exposure"])
        except (TypeError, ValueError):
            raise InputError(job_tsv, f"exposure of {r['id']!r} is not a number: {r['exposure']!r}") from None
    return out
