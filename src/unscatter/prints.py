"""Registered prints as the fits read them: the usable trial pairs (mask, binary print) of
one or more registration outputs (``<id>.png`` prints in mask coordinates, ``qc.tsv``,
``batch.yaml``; the data contract in docs/design.md). Prints with status ok or empty are
used, failed ones never. Calibration, diagnosis and the sequential design read them here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .io import InputError, read_mask, read_print, read_tsv, read_yaml

USABLE = ("ok", "empty")  # an empty print is a measurement too: nothing cured
STATUSES = ("ok", "empty", "failed")


@dataclass
class PrintSet:
    """The usable trial pairs of one or more registration outputs."""

    labels: list  # unique id per print (``<dir name>/<id>`` when several dirs)
    ids: list
    dirs: list  # prints dir of each print
    status: list
    masks: np.ndarray  # (B, H, W) uint8
    prints: np.ndarray  # (B, H, W) bool
    pixel_size_um: float
    prints_dirs: list
    failed: list = field(default_factory=list)

    def __len__(self):
        return len(self.ids)


def load_prints(prints_dirs) -> PrintSet:
    """Read registration outputs; errors name the file or folder at fault."""
    if isinstance(prints_dirs, (str, Path)):
        prints_dirs = [prints_dirs]
    dirs = [Path(d) for d in prints_dirs]
    if not dirs:
        raise ValueError("no prints folders given")
    labels, ids, owners, status, masks, prints, failed = [], [], [], [], [], [], []
    pixel, pixel_src, shape, shape_src = None, None, None, None
    for d in dirs:
        if not d.is_dir():
            raise InputError(d, "prints folder does not exist")
        meta = read_yaml(d / "batch.yaml")
        try:
            px = float(meta["pixel_size_um"])
        except (KeyError, TypeError, ValueError):
            raise InputError(d / "batch.yaml", "needs a numeric pixel_size_um") from None
        if not (math.isfinite(px) and px > 0):
            raise InputError(d / "batch.yaml", f"pixel_size_um must be positive, found {px}")
        if pixel is not None and not math.isclose(px, pixel, rel_tol=1e-6):
            raise InputError(d / "batch.yaml", f"pixel_size_um {px} differs from {pixel} in {pixel_src}; calibrate batches of one printer setup together")
        pixel, pixel_src = px, d / "batch.yaml"
        rows = read_tsv(d / "qc.tsv")
        cols = set(rows[0]) if rows else set()
        missing = {"id", "status", "mask"} - cols
        if rows and missing:
            raise InputError(d / "qc.tsv", f"missing column(s) {sorted(missing)}")
        for r in rows:
            st = (r["status"] or "").strip()
            if st not in STATUSES:
                raise InputError(d / "qc.tsv", f"print {r['id']!r} has status {st!r}; expected one of {STATUSES}")
            if st == "failed":  # never fit a print that failed registration QC
                failed.append(f"{d.name}/{r['id']}" if len(dirs) > 1 else r["id"])
                continue
            mpath = Path(r["mask"])
            if not mpath.is_absolute():
                mpath = d / mpath
            mask = read_mask(mpath)
            ppath = d / f"{r['id']}.png"
            if not ppath.is_file():
                raise InputError(ppath, f"print listed in qc.tsv with status {st!r} but the file is missing")
            pr = read_print(ppath)
            if pr.shape != mask.shape:
                raise InputError(ppath, f"print is {pr.shape[0]}x{pr.shape[1]} but its mask {mpath} is {mask.shape[0]}x{mask.shape[1]}; prints must be in mask coordinates")
            if shape is not None and pr.shape != shape:
                raise InputError(ppath, f"print is {pr.shape[0]}x{pr.shape[1]}, the others are {shape[0]}x{shape[1]} (first: {shape_src})")
            shape, shape_src = pr.shape, ppath
            ids.append(r["id"])
            labels.append(f"{d.name}/{r['id']}" if len(dirs) > 1 else r["id"])
            owners.append(d)
            status.append(st)
            masks.append(mask)
            prints.append(pr)
    where = dirs[0] if len(dirs) == 1 else Path(", ".join(str(d) for d in dirs))
    if not ids:
        raise InputError(where, f"no usable prints (status ok or empty) in qc.tsv; {len(failed)} failed")
    if len(set(labels)) != len(labels):
        raise InputError(where, "the same print id appears twice")
    P = np.stack(prints)
    if not P.any():
        raise InputError(where, f"all {len(ids)} usable prints are empty (nothing cured): the threshold and the kernel cannot be identified; print at a higher dose")
    if P.all():
        raise InputError(where, f"all {len(ids)} usable prints are solid everywhere: the threshold and the kernel cannot be identified; print at a lower dose")
    return PrintSet(labels, ids, owners, status, np.stack(masks), P, pixel, dirs, failed)
