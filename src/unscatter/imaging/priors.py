"""Pose priors from metadata: the camera's pixel size fixes the scale, a stated rotation
range bounds the rotation. With priors the search is smaller, faster and safer; without
them it covers the Settings' ranges.

The camera pixel size at the sample comes from, in this order:

1. batch.yaml ``image_pixel_size_um`` (the whole batch);
2. the image's OME-XML (``Pixels/@PhysicalSizeX`` with its unit, micrometres by default);
3. an ImageJ TIFF's resolution tags with its ``unit`` (micron, um, nm, mm);
4. TIFF resolution tags in pixels per centimetre (ResolutionUnit 3).

Resolution in pixels per inch is ignored: it is what image programs write by default
(72, 96, 300 dpi) and says nothing about a microscope. The scale (image px per mask px)
is then pixel_size_um / image_pixel_size_um, searched within the tolerance: batch.yaml
``image_pixel_size_tolerance`` (a share, 0.01 = 1 %: what a calibration with a stage
micrometer gives) or, without it, ``Settings.scale_tolerance`` (5 %: an objective's
nominal magnification). Within that range the scale is also a prior (``scale_prior``):
it holds the scale of a print whose features cannot fix it (one dot, one block) as the
batch's one magnification does, so a stated tolerance of a few tenths of a per cent lets
such a print register, and the default 5 % does not. The prints whose features fix
their scale check a stated size: six or more correct it, fewer that contradict it drop
it (``batch.stated_scales``).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..io import InputError

UNIT_UM = {"m": 1e6, "cm": 1e4, "mm": 1e3, "um": 1.0, "µm": 1.0, "\u00b5m": 1.0, "micron": 1.0, "microns": 1.0,
           "micrometer": 1.0, "micrometre": 1.0, "nm": 1e-3}


def _unit(u) -> float | None:
    return UNIT_UM.get(str(u).strip().lower().replace("\\u00b5", "µ")) if u is not None else None


def image_pixel_size_um(path) -> tuple[float | None, str]:
    """The camera pixel size at the sample (um) that a TIFF's metadata states, and where
    it was found; (None, '') for PNGs and TIFFs that state none."""
    path = Path(path)
    if path.suffix.lower() not in (".tif", ".tiff"):
        return None, ""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tf:
            if tf.is_ome and tf.ome_metadata:
                root = ET.fromstring(tf.ome_metadata)
                for el in root.iter():
                    if el.tag.endswith("Pixels") and el.get("PhysicalSizeX"):
                        f = _unit(el.get("PhysicalSizeXUnit", "µm"))
                        if f:
                            return float(el.get("PhysicalSizeX")) * f, "OME-XML PhysicalSizeX"
            page = tf.pages[0]
            tags = page.tags
            if "XResolution" not in tags:
                return None, ""
            num, den = tags["XResolution"].value
            if not num or not den:
                return None, ""
            per_unit = num / den  # pixels per unit
            ij = tf.imagej_metadata or {}
            if ij.get("unit") and _unit(ij["unit"]):
                return _unit(ij["unit"]) / per_unit, f"ImageJ resolution ({ij['unit']})"
            unit = int(tags["ResolutionUnit"].value) if "ResolutionUnit" in tags else 2
            if unit == 3:
                return 1e4 / per_unit, "TIFF resolution (pixels per cm)"
    except (ValueError, KeyError, TypeError, ET.ParseError, OSError) as exc:
        raise InputError(path, f"cannot read the image's resolution metadata ({exc})") from exc
    return None, ""


def rotation_range(meta: dict, default: tuple, source) -> tuple:
    """batch.yaml ``image_rotation_deg``: r (meaning -r..r) or [lo, hi]; else ``default``."""
    v = meta.get("image_rotation_deg")
    if v is None:
        return tuple(default)
    if isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v <= 180:
        return (-float(v), float(v))
    if (isinstance(v, (list, tuple)) and len(v) == 2 and all(isinstance(a, (int, float)) and not isinstance(a, bool) for a in v)
            and -180 <= v[0] <= v[1] <= 180):
        return (float(v[0]), float(v[1]))
    raise InputError(source, f"image_rotation_deg must be a number 0..180 (meaning -r..r) or a pair [lo, hi] within "
                             f"-180..180, not {v!r}")


def scale_range(meta: dict, image_path, default: tuple, tolerance: float, source) -> tuple[tuple, str]:
    """The searched scale (image px per mask px) and where it came from."""
    mask_um = meta.get("pixel_size_um")
    cam = meta.get("image_pixel_size_um")
    tolerance = meta.get("image_pixel_size_tolerance") or tolerance
    where = "batch.yaml image_pixel_size_um"
    if cam is None:
        cam, where = image_pixel_size_um(image_path)
    if cam is None:
        return tuple(default), "search"
    if isinstance(cam, bool) or not isinstance(cam, (int, float)) or not cam > 0:
        raise InputError(source, f"image_pixel_size_um must be a positive number, not {cam!r}")
    if isinstance(mask_um, bool) or not isinstance(mask_um, (int, float)) or not mask_um > 0:
        raise InputError(source, "pixel_size_um (the mask pixel at the sample) is needed with a camera pixel size")
    s = float(mask_um) / float(cam)
    return (s / (1 + tolerance), s * (1 + tolerance)), f"{where}, within {100 * tolerance:g} %"


def scale_prior(scale_range: tuple, where: str) -> tuple[float, float] | None:
    """(log scale, its standard deviation) from a stated camera pixel size, the tolerance
    either side taken as two standard deviations; None when the scale was searched."""
    if where == "search":
        return None
    lo, hi = np.log(scale_range[0]), np.log(scale_range[1])
    return float(0.5 * (lo + hi)), float(0.25 * (hi - lo))
