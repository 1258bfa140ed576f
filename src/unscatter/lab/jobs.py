"""The virtual lab as a printer for in-process benchmarks (a convenience over files).

``virtual_lab_printer`` writes a print job, prints and images it on the virtual lab in
one batch (masks printed at the exposure their id asks for), and registers the batch
with ``unscatter.imaging.register_batch`` exactly as any trial batch is registered. The
lab's truth stays in ``work_dir/truth`` and is never read here. The workflow does the
same in files: ``unscatter benchmark job`` -> ``unscatter lab print --job`` ->
``unscatter register`` -> ``unscatter benchmark score``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from ..benchmark import Printer, parse_print_id, read_registered
from ..io import InputError, list_pngs, write_png


def print_on_virtual_lab(masks_dir, work_dir, lab_config=None, seed=None, progress: bool = False) -> Path:
    """Print a folder of benchmark masks (ids from ``benchmark.print_id``) and register them.

    Masks whose id ends in ``__x090`` / ``__x110`` are printed at 90 / 110 % of the nominal
    exposure. Returns the registered prints' folder (``work_dir/prints``).
    """
    from ..imaging import register_batch
    from . import print_batch

    masks_dir, work_dir = Path(masks_dir), Path(work_dir)
    files = list_pngs(masks_dir)
    if not files:
        raise InputError(masks_dir, "no masks to print")
    exposures = {}
    for pid in files:
        try:
            exposures[pid] = parse_print_id(pid)["exposure"]
        except ValueError:
            exposures[pid] = 1.0
    for sub in ("batch", "truth", "prints"):
        if (work_dir / sub).exists():
            shutil.rmtree(work_dir / sub)
    print_batch(masks_dir, work_dir / "batch", lab_config=lab_config, truth_dir=work_dir / "truth", seed=seed,
                progress=progress, exposures=exposures)
    prints = work_dir / "prints"
    register_batch(work_dir / "batch", prints, skip_failed=True, progress=progress)
    return prints


def virtual_lab_printer(work_dir, lab_config=None, seed=None, progress: bool = False) -> Printer:
    """The virtual lab plus registration as a ``benchmark.Printer``."""

    def printer(masks: dict, exposures: dict) -> dict:
        job = Path(work_dir) / "job_masks"
        if job.exists():
            shutil.rmtree(job)
        for pid, m in masks.items():
            if parse_print_id(pid)["exposure"] != exposures[pid]:
                raise ValueError(f"{pid}: the id says exposure {parse_print_id(pid)['exposure']}, asked for {exposures[pid]}")
            write_png(job / f"{pid}.png", m)
        # the masks in hand, not read back from the job: read_registered leaves their marks out
        return read_registered(print_on_virtual_lab(job, work_dir, lab_config=lab_config, seed=seed, progress=progress),
                               masks)

    return printer
