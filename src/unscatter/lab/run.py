"""Run the virtual lab over a folder of masks and write a print batch plus its truth."""

from __future__ import annotations

import shutil
import zlib
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..io import InputError, check_batch_meta, list_pngs, output_dir, read_mask, write_png, write_tiff16, write_tsv, write_yaml
from ..masks import dense_reference_mask
from .microscope import digitize, image_print, stored
from .printer import Printer


REFERENCE_ID = "dense_reference"  # the id of the dense reference print a lab config asks for (``dense_reference``)


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


def dark_level(mic: dict, samples: int = 200_000) -> float:
    """The camera's dark offset as a lab measures it: the mean of a dark frame as the
    images are stored. A 16-bit image holds the offset (rounded: 0.5 ADU is nothing to
    a 16-bit offset); an 8-bit export keeps the top byte (``img >> 8``), which drops the
    rest, so its dark frame reads about half a level below offset / 256 where the read
    noise dithers it (less where it does not). Declaring offset / 256 left the
    background of a dim 8-bit image half a level low: its polymer read up to 38 % too
    bright in units of it (lab 7 of the registration benchmark's seed 434016831), which
    moved its prints' threshold. A fixed random stream, apart from the lab's."""
    if mic.get("format", "tif16") != "png8":
        return float(mic["offset_adu"])
    dark = stored(digitize(np.random.default_rng(0).normal(0.0, float(mic["read_noise_e"]), samples), mic), mic)
    return round(float(dark.mean()), 4)


def psf_sigma_um(mic: dict, mask_um: float) -> float:
    """The microscope's blur at the sample (um), as a lab would state it: the Gaussian
    sigma that ``image_print`` applies (the optics' PSF and the camera's sampling), at the
    middle of the lab's focus blur and of its magnifications (geometric)."""
    s = float(np.sqrt(mic["scale"][0] * mic["scale"][1]))
    blur = 0.5 * (mic["blur_px"][0] + mic["blur_px"][1])
    return float(f"{np.hypot(blur / s, max(0.0, 0.5 * (1 / s - 1))) * mask_um:.4g}")


def batch_yaml(cfg: dict, exposures: dict, source) -> dict:
    """The batch.yaml the lab writes, checked as registration will check it (``source``,
    the lab config, is named when a value there is wrong)."""
    meta, mic = cfg["batch"], cfg["microscope"]
    out = dict(meta)
    if mic.get("declare_offset", True):
        out["camera_offset_adu"] = dark_level(mic)
    if mic.get("declare_blur", False):
        out["microscope_blur_um"] = psf_sigma_um(mic, float(out["pixel_size_um"]))
    md = mic.get("pixel_size_metadata")
    if md:
        if md["where"] == "batch":  # one objective: the camera pixel at the sample, as calibrated
            lo, hi = mic["scale"]
            out["image_pixel_size_um"] = float(f"{out['pixel_size_um'] / np.sqrt(lo * hi) * (1 + md['error']):.5g}")
        if md.get("tolerance"):
            out["image_pixel_size_tolerance"] = md["tolerance"]
    out["notes"] = f"virtual lab, seed {cfg['seed']}"
    if any(v != 1.0 for v in exposures.values()):
        out["notes"] += "; some masks printed at other exposures: see job.tsv"
    if cfg.get("dense_reference") is not None:  # the dense reference print the lab adds (run_batch)
        out["dense_reference"] = [REFERENCE_ID]
    check_batch_meta(out, source)
    return out


def stated_pixel_um(mic: dict, mask_um: float, scale: float, seed: int, mask_id: str) -> float | None:
    """The camera pixel at the sample that the image's own metadata states (microscope
    ``pixel_size_metadata`` with ``where`` "ome" or "imagej"), or None. The acquisition
    software knows the zoom of each image: the stated size is the true one, mask_um /
    scale, off by the lab's calibration ``error`` (one for all images) and by the
    zoom's repeatability ``jitter`` (relative sd, per image; its own random stream, so
    the images are those of the same lab without metadata)."""
    md = mic.get("pixel_size_metadata")
    if not md or md["where"] not in ("ome", "imagej") or mic.get("format", "tif16") != "tif16":
        return None
    jit = float(md.get("jitter", 0.0)) * float(np.random.default_rng([int(seed), zlib.crc32(mask_id.encode()), 1]).standard_normal())
    return float(f"{mask_um / scale * (1 + md['error']) * (1 + jit):.5g}")


def run_batch(mask_dir: Path, out_batch: Path, truth_dir: Path, cfg: dict, progress=True,
              exposures: dict | None = None, inputs=(), source="lab config") -> list[dict]:
    """Print and image every mask of ``mask_dir`` into the batch ``out_batch`` and its
    truth ``truth_dir`` (each a new folder, or an earlier output of the lab).
    ``inputs``: other files the run reads (a job file, the lab config), never written over."""
    masks = list_pngs(mask_dir)
    if not masks:
        raise InputError(mask_dir, "no .png masks to print")
    ref = cfg.get("dense_reference")
    if ref is not None and (isinstance(ref, bool) or not isinstance(ref, (int, float)) or not 1.0 < ref <= 5.0):
        raise InputError(source, f"dense_reference must be an exposure factor above 1 and at most 5 (or null), found {ref!r}")
    if ref is not None and REFERENCE_ID in masks:
        raise InputError(mask_dir, f"a mask is named {REFERENCE_ID!r}, the id of the dense reference the lab config asks for")
    exposures = {k: float(v) for k, v in (exposures or {}).items()}
    unknown = sorted(set(exposures) - set(masks))
    if unknown:
        raise InputError(mask_dir, f"the print job names masks that are not here: {', '.join(unknown[:5])}")
    bad = [k for k, v in exposures.items() if not 0.2 <= v <= 5.0]
    if bad:
        raise InputError(mask_dir, f"exposure factors outside 0.2..5 for {', '.join(bad[:5])}")
    first = read_mask(next(iter(masks.values())))
    size = first.shape[0]
    if ref is not None:  # a large block cured through: the registration measures the dense level on it
        masks = {**masks, REFERENCE_ID: None}
        exposures[REFERENCE_ID] = float(ref)
    meta = batch_yaml(cfg, exposures, source)
    printers: dict = {}

    def printer_for(mid: str) -> Printer:
        e = exposures.get(mid, 1.0)
        if e not in printers:
            printers[e] = Printer(cfg["printer"] if e == 1.0 else _exposed(cfg["printer"], e), size, meta["pixel_size_um"])
        return printers[e]

    printer = printer_for(next(iter(masks)))
    mic = cfg["microscope"]
    level = float(mic["level"])

    reads = [mask_dir, *inputs]
    with (output_dir(out_batch, command="lab print", inputs=reads + [truth_dir]) as batch,
          output_dir(truth_dir, command="lab print", inputs=reads + [out_batch]) as truth_out):
        for sub in (batch / "masks", batch / "images", truth_out / "prints", truth_out / "density"):
            sub.mkdir()
        rows = []
        for mid, path in tqdm(masks.items(), desc="virtual lab: printing", disable=not progress, unit="print"):
            mask = read_mask(path) if path is not None else dense_reference_mask(size)
            if mask.shape != (size, size):
                raise InputError(path, f"mask is {mask.shape}, the batch's masks are {size}x{size}")
            rng = mask_rng(cfg["seed"], mid)
            printer = printer_for(mid)
            rho = printer.density(mask, rng)
            truth = printer.crop(rho) >= level
            img, pose, M = image_print(rho, printer.pad, size, mic, rng)
            cam_um = stated_pixel_um(mic, float(meta["pixel_size_um"]), pose["scale"], cfg["seed"], mid)
            if path is not None:
                shutil.copyfile(path, batch / "masks" / f"{mid}.png")
            else:
                write_png(batch / "masks" / f"{mid}.png", mask)
            if mic.get("format", "tif16") == "png8":  # an 8-bit camera or export
                write_png(batch / "images" / f"{mid}.png", stored(img, mic))
            else:
                write_tiff16(batch / "images" / f"{mid}.tif", img, pixel_size_um=cam_um,
                             tags=(mic.get("pixel_size_metadata") or {}).get("where", "ome"))
            write_png(truth_out / "prints" / f"{mid}.png", truth)
            np.save(truth_out / "density" / f"{mid}.npy", printer.crop(rho).astype(np.float32))
            rows.append(dict(id=mid, exposure=exposures.get(mid, 1.0), **pose, m00=M[0, 0], m01=M[0, 1], m02=M[0, 2], m10=M[1, 0], m11=M[1, 1], m12=M[1, 2],
                             solid_fraction=float(truth.mean())))
        if any(v != 1.0 for v in exposures.values()):
            write_tsv(batch / "job.tsv", [dict(id=k, exposure=exposures.get(k, 1.0),
                                               exposure_s=float(meta["exposure_s"]) * exposures.get(k, 1.0)) for k in masks])
        write_yaml(batch / "batch.yaml", meta)
        write_tsv(truth_out / "transforms.tsv", rows)
        write_yaml(truth_out / "lab_config.yaml", cfg)
    return rows
