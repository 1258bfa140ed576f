"""Image and metadata I/O: the one place where files are read and written.

Every stage reads masks, microscope images, prints and batch metadata through these
functions, so that bad input gets the same clear error everywhere (the file and what
is wrong with it).
"""

from __future__ import annotations

import contextlib
import csv
import difflib
import logging
import math
import os
import secrets
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".tif", ".tiff", ".png")


class InputError(ValueError):
    """Bad input: the message names the file and what is wrong with it, on one line
    (the command line prints it as it is)."""

    def __init__(self, path, problem: str):
        self.path = Path(path)
        self.problem = " ".join(str(problem).split())  # library messages may span lines
        super().__init__(f"{path}: {self.problem}")


# --------------------------------------------------------------------------- masks


def read_mask(path) -> np.ndarray:
    """An 8-bit grayscale mask as uint8 (255 = 100 % dose)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "mask file does not exist")
    try:
        with Image.open(path) as im:
            mode = im.mode
            im.load()
            arr = np.asarray(im)
    except Exception as exc:  # PIL raises many kinds
        raise InputError(path, f"cannot read mask image ({exc})") from exc
    if mode != "L":
        raise InputError(
            path,
            f"mask must be 8-bit grayscale (PNG mode 'L'), found mode {mode!r}"
            + (" with colour channels" if arr.ndim == 3 else ""),
        )
    return arr.astype(np.uint8, copy=False)


def write_png(path, arr: np.ndarray) -> None:
    """Write an 8-bit grayscale PNG (bool arrays become 0/255).

    Masks and prints are always PNG: a lossy format (JPEG) changes grey levels, that is
    the dose, so a name that does not end in .png is an error rather than a hint."""
    path = Path(path)
    check_png_name(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    a = np.asarray(arr)
    if a.dtype == bool:
        a = a.astype(np.uint8) * 255
    if a.dtype != np.uint8:
        raise TypeError(f"write_png expects uint8 or bool, got {a.dtype} for {path}")
    Image.fromarray(a, mode="L").save(path, format="PNG", optimize=False, compress_level=3)


def check_png_name(path) -> None:
    """A mask or print file name must end in .png (written lossless)."""
    if Path(path).suffix.lower() != ".png":
        raise InputError(path, "masks are written as lossless PNG: give a name that ends in .png")


def write_rgb(path, arr: np.ndarray) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.asarray(arr, dtype=np.uint8), mode="RGB").save(path, compress_level=3)


def read_print(path) -> np.ndarray:
    """A binary print (0/255 PNG) as a bool array."""
    arr = read_mask(path)
    vals = np.unique(arr)
    if not set(vals.tolist()) <= {0, 255}:
        raise InputError(path, f"a print must be binary 0/255, found values {vals[:6].tolist()}...")
    return arr > 127


# --------------------------------------------------------------------- microscope


def read_image(path) -> np.ndarray:
    """A fluorescence image (.tif/.tiff/.png, 8 or 16 bit, any size) as float32.

    Also returns nothing about the dtype; use `read_image_raw` for the raw array.
    """
    return read_image_raw(path).astype(np.float32)


def read_image_raw(path) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "image file does not exist")
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise InputError(path, f"unsupported image type {suffix!r} (use .tif, .tiff or .png)")
    try:
        if suffix in (".tif", ".tiff"):
            import tifffile

            arr = tifffile.imread(path)
        else:
            with Image.open(path) as im:
                im.load()
                arr = np.asarray(im)
    except Exception as exc:
        raise InputError(path, f"cannot read image, the file is unreadable or truncated ({exc})") from exc
    arr = np.squeeze(arr)
    if arr.ndim == 3 and arr.shape[-1] in (3, 4):
        raise InputError(path, f"image has colour channels {arr.shape}; expected one grayscale channel")
    if arr.ndim != 2:
        raise InputError(path, f"image must be 2-D grayscale, found shape {arr.shape}")
    if arr.dtype not in (np.uint8, np.uint16):
        raise InputError(path, f"image must be 8 or 16 bit, found {arr.dtype}")
    if min(arr.shape) < 64:
        raise InputError(path, f"image is too small to register ({arr.shape})")
    return arr


def check_image_content(path, raw: np.ndarray, saturated_fraction: float = 0.02) -> None:
    """Reject images that carry no information: constant (camera off) or saturated."""
    lo, hi = int(raw.min()), int(raw.max())
    if lo == hi:
        raise InputError(path, f"image is constant (every pixel = {lo}): camera off or blank frame")
    full = np.iinfo(raw.dtype).max
    frac = float(np.count_nonzero(raw == full)) / raw.size
    if frac > saturated_fraction:
        raise InputError(
            path,
            f"image is saturated: {100 * frac:.1f} % of pixels at the {raw.dtype} maximum {full} "
            f"(more than {100 * saturated_fraction:.1f} %); re-image with a shorter exposure",
        )
    if float(np.std(raw.astype(np.float32))) < 1e-3 * max(hi, 1):
        raise InputError(path, "image has essentially no contrast")


def write_tiff16(path, arr: np.ndarray, pixel_size_um: float | None = None, tags: str = "ome") -> None:
    """A 16-bit TIFF; with ``pixel_size_um`` (the camera pixel at the sample) written as a
    microscope's software writes it: ``tags`` "ome" (OME-XML PhysicalSizeX/Y, as
    Bio-Formats and most acquisition software) or "imagej" (resolution tags in pixels per
    micron with ImageJ's ``unit``)."""
    import tifffile

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = np.asarray(arr, dtype=np.uint16)
    if pixel_size_um is None:
        tifffile.imwrite(path, arr, compression=None)
    elif tags == "ome":
        tifffile.imwrite(path, arr, compression=None, ome=True,
                         metadata={"PhysicalSizeX": float(pixel_size_um), "PhysicalSizeXUnit": "µm",
                                   "PhysicalSizeY": float(pixel_size_um), "PhysicalSizeYUnit": "µm"})
    elif tags == "imagej":
        tifffile.imwrite(path, arr, compression=None, imagej=True, resolution=(1 / pixel_size_um, 1 / pixel_size_um),
                         metadata={"unit": "um"})
    else:
        raise ValueError(f"tags must be 'ome' or 'imagej', not {tags!r}")


# ---------------------------------------------------------------------- YAML / TSV


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, except that a key given twice in one mapping is an error
    (PyYAML keeps the last one silently: of two values given for one setting, the
    second would win unseen)."""

    def construct_mapping(self, node, deep=False):
        seen = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.setdefault(key, key_node)
            except TypeError:  # an unhashable key: PyYAML's own error says so
                break
            if first is not key_node:
                raise yaml.constructor.ConstructorError(
                    problem=f"key {key!r} appears twice (lines {first.start_mark.line + 1} and {key_node.start_mark.line + 1})")
        return super().construct_mapping(node, deep)


def read_yaml(path) -> dict:
    """A YAML mapping; a missing file, text that is not YAML (or not text) and duplicate
    keys are errors naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file does not exist" if not path.is_dir() else "is a folder, not a YAML file")
    try:
        with open(path, encoding="utf-8") as fh:
            data = yaml.load(fh, Loader=_UniqueKeyLoader)  # a SafeLoader
    except (UnicodeDecodeError, yaml.reader.ReaderError):
        raise InputError(path, "not a text (YAML) file") from None
    except yaml.YAMLError as exc:
        raise InputError(path, f"not valid YAML ({exc})") from exc
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise InputError(path, "expected a YAML mapping at the top level")
    return data


def write_yaml(path, data: dict) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        yaml.safe_dump(_plain(data), fh, sort_keys=False)


def _plain(obj):
    """numpy scalars/arrays to plain Python, so YAML stays readable."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def write_tsv(path, rows: list[dict], columns: list[str] | None = None) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if columns is None:
        columns = list(rows[0].keys()) if rows else []
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns, delimiter="\t", extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: _fmt(r.get(k, "")) for k in columns})


def _fmt(v):
    if isinstance(v, (float, np.floating)):
        return f"{float(v):.6g}"
    return v


def read_tsv(path) -> list[dict]:
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file does not exist")
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh, delimiter="\t"))


# -------------------------------------------------------------------- print batch


def _number(path, key, v, minimum: float = 0.0, strict: bool = True) -> float:
    """A finite real number above ``minimum`` (at least, unless ``strict``). A bool is
    not a number here, although Python says it is: YAML reads `yes` and `true` as one."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(path, f"field {key!r} must be a number, found {v!r}")
    if v < minimum or (strict and v == minimum):
        what = "a positive number" if strict and minimum == 0 else f"a number {'>' if strict else '>='} {minimum:g}"
        raise InputError(path, f"field {key!r} must be {what}, found {v!r}")
    return float(v)


def _text(path, key, v) -> str:
    if not isinstance(v, str):
        raise InputError(path, f"field {key!r} must be text, found {v!r} (put it in quotes)")
    return v


def _rotation(path, key, v) -> tuple[float, float]:
    """A number r >= 0 (meaning -r..r) or a pair [lo, hi], within -180..180 degrees."""
    if isinstance(v, list):
        if len(v) != 2:
            raise InputError(path, f"field {key!r} must be a number r (-r..r) or a pair [lo, hi], found {v!r}")
        lo, hi = (_number(path, key, x, minimum=-180, strict=False) for x in v)
    else:
        hi = _number(path, key, v, strict=False)
        lo = -hi
    if not -180 <= lo <= hi <= 180:
        raise InputError(path, f"field {key!r}: the range {v!r} must lie within -180..180 degrees with lo <= hi")
    return lo, hi


def _tolerance(path, key, v) -> float:
    """A relative tolerance above 0 and at most 0.5 (a share, not a percentage)."""
    t = _number(path, key, v)
    if t > 0.5:
        raise InputError(path, f"field {key!r} is a share (0.01 means 1 %), at most 0.5, found {v!r}")
    return t


def _ids(path, key, v) -> tuple[str, ...]:
    """One print id or a list of them (distinct, non-empty text)."""
    items = v if isinstance(v, list) else [v]
    if not items or not all(isinstance(x, str) and x.strip() for x in items):
        raise InputError(path, f"field {key!r} must be a print id or a list of print ids, found {v!r} (put ids in quotes)")
    if len(set(items)) != len(items):
        raise InputError(path, f"field {key!r} names a print twice: {v!r}")
    return tuple(items)


def _factors(path, key, v) -> dict:
    if not isinstance(v, dict):
        raise InputError(path, f"field {key!r} must map names to exposure factors, found {v!r}")
    return {str(k): _number(path, f"{key}.{k}", x) for k, x in v.items()}


# batch.yaml: field -> (required, reader of its value). The data contract is docs/design.md.
BATCH_FIELDS = {
    "pixel_size_um": (True, _number),  # DMD pixel at the sample (Guan et al. 2022: 2.96 um)
    "exposure_s": (True, _number),
    "max_intensity_mw_cm2": (True, _number),
    "material": (True, _text),
    "notes": (False, _text),
    "camera_offset_adu": (False, lambda path, key, v: _number(path, key, v, strict=False)),
    "image_pixel_size_um": (False, _number),  # the camera pixel at the sample
    "image_pixel_size_tolerance": (False, _tolerance),  # how far (relative) any stated camera pixel size may be off
    "image_rotation_deg": (False, _rotation),
    "dense_level": (False, _number),  # fully cured polymer's fluorescence over the background (registration)
    "dense_reference": (False, _ids),  # prints of a large block exposed well past cure: the registration measures it
    "microscope_blur_um": (False, _number),  # the microscope's blur at the sample: its PSF's Gaussian sigma (calibration)
    "layer_um": (False, _number),
    "z_step_um": (False, _number),
    "source_batch": (False, _text),  # registration: the batch the prints come from
    "exposure_factors": (False, _factors),  # a benchmark print job: id suffix -> factor of exposure_s
}


@dataclass(frozen=True)
class BatchMeta:
    """batch.yaml of a print batch, checked (``read_batch_meta``); optional fields are
    None when absent, except ``notes`` ("") and ``camera_offset_adu`` (0)."""

    pixel_size_um: float
    exposure_s: float
    max_intensity_mw_cm2: float
    material: str
    notes: str = ""
    camera_offset_adu: float = 0.0
    image_pixel_size_um: float | None = None
    image_pixel_size_tolerance: float | None = None
    image_rotation_deg: tuple[float, float] | None = None
    dense_level: float | None = None
    dense_reference: tuple[str, ...] | None = None
    microscope_blur_um: float | None = None
    layer_um: float | None = None
    z_step_um: float | None = None
    source_batch: str | None = None
    exposure_factors: dict | None = None

    def as_dict(self) -> dict:
        """The fields that are set, as batch.yaml holds them."""
        d = {k: getattr(self, k) for k in BATCH_FIELDS}
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items() if v is not None}


def check_batch_meta(data: dict, path) -> BatchMeta:
    """batch.yaml's mapping checked field by field; ``path`` names it in errors.

    A misspelt field is an error (with the likely intended name), not a field that is
    silently absent: a lost ``camera_offset_adu`` would quietly shift every threshold.
    """
    if not isinstance(data, dict):
        raise InputError(path, "expected a YAML mapping at the top level")
    for key in data:
        if key not in BATCH_FIELDS:
            near = difflib.get_close_matches(str(key), BATCH_FIELDS, n=1)
            hint = f"did you mean {near[0]!r}?" if near else f"known fields: {', '.join(BATCH_FIELDS)}"
            raise InputError(path, f"unknown field {key!r}; {hint}")
    vals = {}
    for key, (required, read) in BATCH_FIELDS.items():
        if data.get(key) is None:
            if required:
                raise InputError(path, f"missing field {key!r}")
            continue
        vals[key] = read(path, key, data[key])
    if not 0.1 <= vals["pixel_size_um"] <= 100:
        raise InputError(path, f"pixel_size_um = {vals['pixel_size_um']} is not a plausible DMD pixel size (0.1 to 100 um)")
    if not vals["material"].strip():
        raise InputError(path, "field 'material' must be a non-empty string")
    if "dense_level" in vals and "dense_reference" in vals:
        raise InputError(path, "give dense_level (a measured number) or dense_reference (prints to measure it on), not both")
    return BatchMeta(**vals)


def read_batch_meta(path) -> BatchMeta:
    """batch.yaml of a print batch (the file, or the batch folder), checked field by field."""
    path = Path(path)
    if path.is_dir():
        path = path / "batch.yaml"
    return check_batch_meta(read_yaml(path), path)


@dataclass(frozen=True)
class Batch:
    root: Path
    meta: BatchMeta
    masks: dict  # id -> Path
    images: dict  # id -> Path

    @property
    def ids(self) -> list[str]:
        return sorted(self.masks)


def open_batch(root) -> Batch:
    """A print batch in the data contract: batch.yaml, masks/<id>.png, images/<id>.tif.

    Every mask needs exactly one image and every image a mask.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "batch folder does not exist")
    meta = read_batch_meta(root / "batch.yaml")
    mdir, idir = root / "masks", root / "images"
    for d in (mdir, idir):
        if not d.is_dir():
            raise InputError(d, "folder missing from the batch")
    masks: dict[str, Path] = {}
    for p in sorted(mdir.iterdir()):
        if not p.is_file() or p.name.startswith("."):
            continue
        if p.suffix.lower() != ".png":
            raise InputError(p, "masks must be .png files")
        if p.stem in masks:
            raise InputError(p, f"two masks for the same id {p.stem!r}: {masks[p.stem].name} and {p.name}")
        masks[p.stem] = p
    images: dict[str, Path] = {}
    for p in sorted(idir.iterdir()):
        if not p.is_file() or p.name.startswith("."):
            continue
        if p.suffix.lower() not in IMAGE_SUFFIXES:
            raise InputError(p, f"unexpected file in images/ (use {', '.join(IMAGE_SUFFIXES)})")
        if p.stem in images:
            raise InputError(p, f"two images for the same id {p.stem!r}: {images[p.stem].name} and {p.name}")
        images[p.stem] = p
    if not masks:
        raise InputError(mdir, "no masks in the batch")
    missing = sorted(set(masks) - set(images))
    extra = sorted(set(images) - set(masks))
    if missing:
        raise InputError(idir, f"no image for mask(s) {', '.join(missing)} (expected images/<id>.tif or .png)")
    if extra:
        raise InputError(idir, f"image(s) without a mask: {', '.join(images[e].name for e in extra)}")
    return Batch(root=root, meta=meta, masks=masks, images=images)


def list_pngs(folder) -> dict:
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "folder does not exist")
    return {p.stem: p for p in sorted(folder.glob("*.png"))}


# ------------------------------------------------------------------ output folders

# The file by which a folder is known as the output of one of our commands: it names the
# command and lists the files the command wrote.
OUTPUT_MARKER = ".unscatter-output.yaml"
# Files that tools put into an output folder of ours (Snakemake's mtime carrier).
_FOREIGN_OK = {OUTPUT_MARKER, ".snakemake_timestamp"}


def _read_marker(folder: Path) -> dict | None:
    try:
        with open(folder / OUTPUT_MARKER, encoding="utf-8") as fh:
            data = yaml.safe_load(fh)
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None
    return data if isinstance(data, dict) and isinstance(data.get("command"), str) else None


def _files(folder: Path) -> list[str]:
    """Every file below ``folder``, as paths relative to it (marker left out)."""
    out = []
    for root, _dirs, names in os.walk(folder):
        for name in names:
            rel = Path(root, name).relative_to(folder).as_posix()
            if rel not in _FOREIGN_OK:
                out.append(rel)
    return sorted(out)


def _within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


def check_output_dir(path, *, command: str, inputs=(), recognise=None) -> Path:
    """Refuse to write ``command``'s output folder ``path`` where that would lose data.

    The folder must not be, contain or lie inside any of ``inputs`` (paths compared
    after resolving symbolic links; entries that are not paths are skipped). If it
    exists it must be empty, or an earlier output of the same command holding nothing
    that the command did not write: its marker file says so, or, for an output without
    one, ``recognise(folder)`` does (a Zarr store marks itself in its attributes).
    Returns the resolved folder.
    """
    path = Path(path)
    where = path.resolve()
    for given in inputs:
        if not isinstance(given, (str, os.PathLike)):
            continue
        source = Path(given).resolve()
        if where == source:
            also = "" if Path(given) == path else f" ({given})"
            raise InputError(path, f"is also an input{also}; write the output to another folder (nothing was changed)")
        if _within(where, source):
            raise InputError(path, f"lies inside the input {given}; write the output elsewhere (nothing was changed)")
        if _within(source, where):
            raise InputError(path, f"contains the input {given}; write the output elsewhere (nothing was changed)")
    if not where.exists() and not where.is_symlink():
        return where
    if not where.is_dir():
        raise InputError(path, "exists and is not a folder (nothing was changed)")
    if not any(where.iterdir()):
        return where
    marker = _read_marker(where)
    keep = "; give a new or empty folder, or remove this one (nothing was changed)"
    if marker is None:
        if recognise is not None and recognise(where):
            return where
        raise InputError(path, f"is not empty and is not an earlier output of `{_program(command)}`{keep}")
    if marker["command"] != command:
        raise InputError(path, f"holds the output of `{_program(marker['command'])}`, not of `{_program(command)}`{keep}")
    if isinstance(marker.get("files"), list):
        added = sorted(set(_files(where)) - set(marker["files"]))
        if added:
            more = f" and {len(added) - 3} more" if len(added) > 3 else ""
            raise InputError(path, f"holds files that `{_program(command)}` did not write ({', '.join(added[:3])}{more}); "
                                   f"they would be lost{keep}")
    return where


def claim_output_dir(path, *, command: str, inputs=(), recognise=None) -> Path:
    """``check_output_dir``, then create and mark the folder, for a command that writes
    into it as it goes (training keeps its checkpoint there to resume, and replaces
    each of its files atomically). Returns the resolved folder."""
    final = check_output_dir(path, command=command, inputs=inputs, recognise=recognise)
    final.mkdir(parents=True, exist_ok=True)
    _write_marker(final, command)
    return final


def _program(command: str) -> str:
    """How a command is run: unscatter's subcommands, or a script given as its path."""
    return command if command.endswith(".py") else f"unscatter {command}"


def benchmark_output_dir(path, *, script: str, keep: bool = False) -> Path:
    """A benchmark's output folder, emptied for a new run (``keep``: left as it is).

    Benchmarks write their tables lab by lab, so that a long run interrupted keeps what it
    measured; they cannot write into a hidden folder swapped in at the end as
    ``output_dir`` does. The folder is removed only when it is empty or an earlier output
    of the same ``script`` (its marker file); any other folder raises InputError, nothing
    removed: ``--out ~/prints`` must not delete a user's prints.
    """
    where = check_output_dir(path, command=script)
    if where.exists() and not keep:
        shutil.rmtree(where)
    where.mkdir(parents=True, exist_ok=True)
    _write_marker(where, script)
    return where


@contextlib.contextmanager
def output_dir(path, *, command: str, inputs=(), recognise=None, marker: bool = True):
    """Write ``command``'s output folder safely: ``with output_dir(out, command=..., inputs=[...]) as tmp:``.

    ``check_output_dir`` refuses first, so that the user's files stay as they are. The
    body writes into a fresh hidden sibling folder ``tmp``, which replaces ``path`` only
    when the body finishes: the old output is renamed away, the new one renamed in, the
    old one deleted. An interrupted or failed run thus leaves the earlier output whole,
    and a rerun leaves nothing stale from it. The marker file (``OUTPUT_MARKER``: the
    command and the files it wrote) goes in last; ``marker=False`` leaves it out for
    outputs that ``recognise`` knows by themselves (a Zarr store lists every file in it).
    """
    final = check_output_dir(path, command=command, inputs=inputs, recognise=recognise)
    tmp = final.parent / f".{final.name}.{secrets.token_hex(4)}.partial"
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp.mkdir()
    except OSError as exc:  # e.g. a read-only folder: say so before any work is done
        raise InputError(path, f"cannot write the output here ({exc.strerror or exc})") from exc
    try:
        yield tmp
        if marker:
            _write_marker(tmp, command, _files(tmp))
        # the folder may have changed while the command ran: check again before replacing it
        check_output_dir(path, command=command, recognise=recognise)
        _swap_in(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _write_marker(folder: Path, command: str, files: list[str] | None = None) -> None:
    from . import __version__

    data = dict(command=command, unscatter_version=__version__,
                note="written by unscatter; a rerun of this command replaces this folder")
    if files is not None:
        data["files"] = files
    write_yaml(folder / OUTPUT_MARKER, data)


def _swap_in(new: Path, final: Path) -> None:
    """Rename ``new`` to ``final``; an existing ``final`` is renamed away first and
    deleted after, so that one complete version is in place at every moment."""
    old = None
    if final.exists():
        old = final.parent / f".{final.name}.{secrets.token_hex(4)}.old"
        os.rename(final, old)
    try:
        os.rename(new, final)
    except BaseException:
        if old is not None:
            os.rename(old, final)
        raise
    if old is not None:
        try:
            shutil.rmtree(old)
        except OSError as exc:
            log.warning("could not remove the previous output, now at %s (%s)", old, exc)
