"""Run the virtual lab over a folder of masks and write a print batch plus its truth."""

from __future__ import annotations

import shutil
import zlib
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..io import InputError, list_pngs, read_mask, write_png, write_tiff16, write_tsv, write_yaml
from .microscope import image_print
from .printer import Printer


def mask_rng(seed: int, mask_id: str) -> np.random.Generator:
    """Each print's randomness depends on the lab seed and the mask id only."""
    return np.random.default_rng([int(seed), zlib.crc32(mask_id.encode())])


def _exposed(printer_cfg: dict, factor: float) -> dict:
    """The printer config for an exposure ``factor`` times the nominal one.

    The lab has no exposure time of its own: the absorbed dose scales with it, which is
    played by dividing the cure doses by the factor.
    """
    cure = dict(printer_cfg["cure"], threshold=printer_cfg["cure"]["threshold"] / factor,
                gel_dose=printer_cfg["cure"]["gel_dose"] / factor)
    return dict(printer_cfg, cure=cure)


def run_batch(mask_dir: Path, out_batch: Path, truth_dir: Path, cfg: dict, progress=True,
              exposures: dict | None = None) -> list[dict]:
    masks = list_pngs(mask_dir)
    if not masks:
        raise InputError(mask_dir, "no .png masks to print")
    exposures = {k: float(v) for k, v in (exposures or {}).items()}
    unknown = sorted(set(exposures) - set(masks))
    if unknown:
        raise InputError(mask_dir, f"the print job names masks that are not here: {', '.join(unknown[:5])}")
    bad = [k for k, v in exposures.items() if not 0.2 <= v <= 5.0]
    if bad:
        raise InputError(mask_dir, f"exposure factors outside 0.2..5 for {', '.join(bad[:5])}")
    first = read_mask(next(iter(masks.values())))
    size = first.shape[0]
    meta = cfg["batch"]
    printers: dict = {}

    def printer_for(mid: str) -> Printer:
        e = exposures.get(mid, 1.0)
        if e not in printers:
            printers[e] = Printer(cfg["printer"] if e == 1.0 else _exposed(cfg["printer"], e), size, meta["pixel_size_um"])
        return printers[e]

    printer = printer_for(next(iter(masks)))
    mic = cfg["microscope"]
    level = float(mic["level"])

    for d in (out_batch, truth_dir):
        if d.exists():
            shutil.rmtree(d)
    (out_batch / "masks").mkdir(parents=True)
    (out_batch / "images").mkdir()
    (truth_dir / "prints").mkdir(parents=True)
    (truth_dir / "density").mkdir()

    rows = []
    for mid, path in tqdm(masks.items(), desc="virtual lab: printing", disable=not progress, unit="print"):
        mask = read_mask(path)
        if mask.shape != (size, size):
            raise InputError(path, f"mask is {mask.shape}, the batch's masks are {size}x{size}")
        rng = mask_rng(cfg["seed"], mid)
        printer = printer_for(mid)
        rho = printer.density(mask, rng)
        truth = printer.crop(rho) >= level
        img, pose, M = image_print(rho, printer.pad, size, mic, rng)
        shutil.copyfile(path, out_batch / "masks" / f"{mid}.png")
        if mic.get("format", "tif16") == "png8":  # an 8-bit camera or export
            write_png(out_batch / "images" / f"{mid}.png", (img >> 8).astype(np.uint8))
        else:
            write_tiff16(out_batch / "images" / f"{mid}.tif", img)
        write_png(truth_dir / "prints" / f"{mid}.png", truth)
        np.save(truth_dir / "density" / f"{mid}.npy", printer.crop(rho).astype(np.float32))
        rows.append(dict(id=mid, exposure=exposures.get(mid, 1.0), **pose, m00=M[0, 0], m01=M[0, 1], m02=M[0, 2], m10=M[1, 0], m11=M[1, 1], m12=M[1, 2],
                         solid_fraction=float(truth.mean())))
    batch_yaml = dict(meta)
    if mic.get("declare_offset", True):
        batch_yaml["camera_offset_adu"] = mic["offset_adu"] / (256 if mic.get("format") == "png8" else 1)
    batch_yaml["notes"] = f"virtual lab, seed {cfg['seed']}"
    if any(v != 1.0 for v in exposures.values()):
        batch_yaml["notes"] += "; some masks printed at other exposures: see job.tsv"
        write_tsv(out_batch / "job.tsv", [dict(id=k, exposure=exposures.get(k, 1.0),
                                               exposure_s=float(meta["exposure_s"]) * exposures.get(k, 1.0)) for k in masks])
    write_yaml(out_batch / "batch.yaml", batch_yaml)
    write_tsv(truth_dir / "transforms.tsv", rows)
    write_yaml(truth_dir / "lab_config.yaml", cfg)
    return rows
