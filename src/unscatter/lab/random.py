"""Randomised labs: lab configs drawn over wide ranges.

Registration (and whatever else reads a batch) is developed against the default lab. A
real lab differs from it in optics, camera, export and printer, often by factors of
several, and has effects nobody modelled. ``random_lab`` draws such a lab: every
microscope and printer setting from ranges of ten times or more where the physics allows
it, and, each with probability one half, the microscope effects the default lab lacks
(haze, a tilted background, uneven staining). It returns overrides for
``load_config(overrides=...)`` and ``print_batch(overrides=...)``.

``RANGES`` holds the bounds of every drawn number; the tests check draws against it.
"""

from __future__ import annotations

import numpy as np

RANGES = {
    # microscope
    "rotation_deg": (0.0, 15.0),  # the largest rotation of the lab's images
    "scale": (0.7, 1.4),  # image px per mask px; a lab draws a sub-range
    "image_px": (640, 1024),  # rows and cols, drawn apart (non-square fields)
    "blur_px": (0.5, 3.0),
    "vignetting": (0.0, 0.4),
    "background": (0.02, 0.5),  # relative to saturated polymer
    "photons": (200.0, 8000.0),
    "read_noise_e": (1.0, 20.0),
    "offset_adu": (0.0, 1000.0),
    "lamp_jitter": (0.0, 0.2),
    "peak_fraction": (0.3, 0.7),  # brightest expected pixel as a share of the camera's range
    "haze_fraction": (0.0, 0.2),
    "haze_sigma_px": (10.0, 40.0),
    "background_tilt": (0.0, 0.5),
    "staining": (0.0, 0.25),
    "staining_length_px": (60.0, 250.0),
    "pixel_size_tolerance": (0.001, 0.01),  # (log-uniform) a stated camera pixel size calibrated with a stage micrometer
    "pixel_size_error": (-0.03, 0.03),  # an objective's nominal magnification, not calibrated
    "stale_factor": (2.0, 5.0),  # a stale calibration: off by this many times its stated tolerance
    "zoom_jitter": (0.0, 0.001),  # relative sd of a zoom's repeatability (per image)
    # printer
    "sigma_um": (6.0, 25.0),
    "tail_fraction": (0.0, 0.4),
    "tail_length_um": (20.0, 100.0),
    "anisotropy": (1.0, 1.8),
    "linear": (-0.08, 0.08),  # illumination cx, cy
    "quadratic": (-0.15, 0.03),  # illumination cx2, cy2
    "hotspot_amplitude": (0.0, 0.4),
    "hotspot_width": (0.2, 0.6),
    "dose_gamma": (0.9, 1.15),
    "threshold": (0.35, 0.7),
    "gel_share": (0.5, 0.85),  # gel dose as a share of the threshold
    "edge_offset_um": (-6.0, 4.0),
    "dose_noise": (0.01, 0.06),
    "cell_um": (8.0, 16.0),
    "print_to_print": (0.0, 0.04),
}

DESIGN_PX = 512  # the mask field the lab's images must show in full
MARGIN_PX = 12  # image px kept free around the rotated, scaled field


def _u(rng, key):
    lo, hi = RANGES[key]
    return float(rng.uniform(lo, hi))


def _log_u(rng, key):
    lo, hi = RANGES[key]
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def field_extent_px(scale: float, rotation_deg: float, design_px: int = DESIGN_PX) -> float:
    """Width (= height) of the bounding box of the design field rotated by up to
    ``rotation_deg`` and scaled by ``scale``, in image pixels."""
    th = np.deg2rad(min(abs(rotation_deg), 45.0))
    return float(scale * design_px * (np.cos(th) + np.sin(th)))


def _microscope(rng: np.random.Generator) -> dict:
    rot = _u(rng, "rotation_deg")
    lo_s, hi_s = RANGES["scale"]
    kind = rng.random()
    if kind < 0.25:  # a lab whose magnification varies over the whole range
        scale = [lo_s, hi_s]
    else:  # a zoom set by hand for each image (a narrow range somewhere in the whole), or one
        # objective, whose scale only refocusing changes (0.2 % at most)
        c, hw = _log_u(rng, "scale"), float(rng.uniform(0.02, 0.15) if kind < 0.6 else rng.uniform(0.0, 0.002))
        scale = [max(lo_s, c * np.exp(-hw)), min(hi_s, c * np.exp(hw))]
    # the field of view fits the rotated field at the largest scale (draw_pose then keeps
    # the design in view for any shift it draws)
    need = int(np.ceil(field_extent_px(scale[1], rot))) + 2 * MARGIN_PX
    lo_px, hi_px = RANGES["image_px"]
    size = [int(rng.integers(max(lo_px, need), hi_px + 1)) for _ in range(2)]
    if rng.random() < 0.4:
        size[1] = size[0]
    b0 = _log_u(rng, "blur_px")
    blur = [b0, min(RANGES["blur_px"][1], b0 * float(rng.uniform(1.0, 1.6)))]
    v1 = _u(rng, "vignetting")
    vig = [float(rng.uniform(0, v1)), v1]
    background, photons = _log_u(rng, "background"), _log_u(rng, "photons")
    jitter = _u(rng, "lamp_jitter")
    offset = 0.0 if rng.random() < 0.2 else _u(rng, "offset_adu")
    fmt = "png8" if rng.random() < 0.35 else "tif16"
    # the gain a user would set: the brightest expected pixel (dense polymer on background,
    # a bright lamp) at a share of the camera's range, so nothing saturates and an 8-bit
    # export still resolves the dim labs
    peak = photons * (1 + background) * (1 + 3 * jitter)
    gain = _u(rng, "peak_fraction") * (65535 - offset) / peak
    m = dict(
        image_size=size,
        rotation_deg=rot,
        scale=scale,
        blur_px=blur,
        vignetting=vig,
        background=background,
        photons=photons,
        lamp_jitter=jitter,
        read_noise_e=_log_u(rng, "read_noise_e"),
        offset_adu=offset,
        declare_offset=bool(rng.random() < 0.7),
        format=fmt,
        adu_per_e=gain,
        haze=dict(fraction=_u(rng, "haze_fraction"), sigma_px=_u(rng, "haze_sigma_px")) if rng.random() < 0.5 else None,
        background_tilt=_u(rng, "background_tilt") if rng.random() < 0.5 else 0.0,
        staining=dict(variation=_u(rng, "staining"), length_px=_u(rng, "staining_length_px")) if rng.random() < 0.5 else None,
    )
    return m


def _pixel_size_metadata(rng: np.random.Generator, m: dict) -> dict | None:
    """What a lab states about its camera pixel at the sample (``stated_pixel_um``): one
    lab in three nothing; else per image in OME-XML or ImageJ tags (a 16-bit TIFF) or, for
    one objective, once in batch.yaml. Calibrated with a stage micrometer (a tolerance
    stated, the error within half of it), the objective's nominal value (no tolerance,
    a few per cent off) or, one lab in ten of those that state something, a stale
    calibration off by several times the tolerance it states. Drawn after everything else,
    so a seed's labs are the same with metadata as without."""
    lo, hi = m["scale"]
    one = hi / lo < 1.005  # one objective: only refocusing changes the scale
    where = (["ome", "imagej"] if m["format"] == "tif16" else []) + (["batch"] if one else [])
    if rng.random() < 1 / 3 or not where:
        return None
    kind = rng.random()
    tol = _log_u(rng, "pixel_size_tolerance")
    if kind < 0.45:
        error, stated = float(rng.uniform(-0.5, 0.5)) * tol, tol
    elif kind < 0.9:
        error, stated = _u(rng, "pixel_size_error"), None
    else:
        error, stated = float(rng.choice([-1, 1])) * _u(rng, "stale_factor") * tol, tol
    # a zoom's repeatability, or refocusing under one objective (which no metadata knows)
    jitter = float(np.log(hi / lo) / 2) if one else _u(rng, "zoom_jitter")
    return dict(where=str(rng.choice(where)), error=error, tolerance=stated, jitter=jitter)


def _printer(rng: np.random.Generator) -> dict:
    threshold = _u(rng, "threshold")
    hotspot = None
    if rng.random() < 0.6:
        hotspot = dict(amplitude=_u(rng, "hotspot_amplitude"), x0=float(rng.uniform(-0.8, 0.8)),
                       y0=float(rng.uniform(-0.8, 0.8)), width=_u(rng, "hotspot_width"))
    return dict(
        illumination=dict(c0=1.0, cx=_u(rng, "linear"), cy=_u(rng, "linear"), cx2=_u(rng, "quadratic"),
                          cy2=_u(rng, "quadratic"), quartic=0.0, hotspot=hotspot),
        dose_gamma=_u(rng, "dose_gamma"),
        kernel=dict(
            sigma_um=_u(rng, "sigma_um"),
            heavy_tail=dict(fraction=_u(rng, "tail_fraction"), length_um=_u(rng, "tail_length_um")),
            anisotropy=dict(ratio=_u(rng, "anisotropy") if rng.random() < 0.6 else 1.0,
                            angle_deg=float(rng.uniform(0, 180))),
        ),
        cure=dict(threshold=threshold, gel_dose=threshold * _u(rng, "gel_share")),
        edge_offset_um=_u(rng, "edge_offset_um"),
        cells=dict(dose_noise=_u(rng, "dose_noise"), cell_um=_u(rng, "cell_um"), print_to_print=_u(rng, "print_to_print")),
    )


def _rounded(x):
    """Four significant digits: the config reads (and prints) as a lab would write it."""
    if isinstance(x, dict):
        return {k: _rounded(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_rounded(v) for v in x]
    if isinstance(x, float):
        return float(f"{x:.4g}")
    return x


def random_lab(rng: np.random.Generator) -> dict:
    """A lab drawn over wide ranges (``RANGES``): overrides of the lab's default config
    (``microscope`` and ``printer`` sections). The design field stays in view at every
    pose the lab can draw."""
    m, p = _microscope(rng), _printer(rng)
    m["pixel_size_metadata"] = _pixel_size_metadata(rng, _rounded(m))
    return _rounded(dict(microscope=m, printer=p))


def describe_lab(over: dict) -> str:
    """One line with a drawn lab's key settings (for benchmark reports)."""
    m, p = over.get("microscope", {}), over.get("printer", {})
    parts = [f"{m['image_size'][0]}x{m['image_size'][1]} {m['format']}",
             f"offset {m['offset_adu']:g}{'' if m['declare_offset'] else ' (undeclared)'}",
             f"photons {m['photons']:.0f}", f"bg {m['background']:.3g}", f"read {m['read_noise_e']:.3g} e",
             f"blur {m['blur_px'][0]:.2g}-{m['blur_px'][1]:.2g}", f"vig {m['vignetting'][1]:.2f}",
             f"rot {m['rotation_deg']:.1f}", f"scale {m['scale'][0]:.3f}-{m['scale'][1]:.3f}",
             f"jitter {m['lamp_jitter']:.2f}"]
    if m.get("haze"):
        parts.append(f"haze {m['haze']['fraction']:.2f}/{m['haze']['sigma_px']:.0f}px")
    if m.get("background_tilt"):
        parts.append(f"tilt {m['background_tilt']:.2f}")
    if m.get("staining"):
        parts.append(f"stain {m['staining']['variation']:.2f}/{m['staining']['length_px']:.0f}px")
    md = m.get("pixel_size_metadata")
    if md:
        tol = f"+-{100 * md['tolerance']:.2g} %" if md.get("tolerance") else "no tolerance"
        parts.append(f"px size in {md['where']} {100 * md['error']:+.2g} % ({tol})")
    k, c = p["kernel"], p["cure"]
    ht = k.get("heavy_tail")
    parts += [f"| sigma {k['sigma_um']:.1f} um", f"tail {ht['fraction']:.2f}/{ht['length_um']:.0f} um" if ht else "no tail",
              f"aniso {k['anisotropy']['ratio']:.2f}", f"T {c['threshold']:.2f} gel {c['gel_dose']:.2f}",
              f"gamma {p['dose_gamma']:.2f}", f"edge {p['edge_offset_um']:+.1f} um", f"noise {p['cells']['dose_noise']:.3f}"]
    hs = p["illumination"].get("hotspot")
    if hs:
        parts.append(f"hotspot {hs['amplitude']:.2f}")
    if p["illumination"].get("quartic"):
        parts.append(f"quartic {p['illumination']['quartic']:+.3f}")
    if p.get("oxygen_inhibition"):
        parts.append(f"O2 {p['oxygen_inhibition']['strength']:.2f}/{p['oxygen_inhibition']['length_um']:.0f} um")
    if p.get("kernel_dose_growth"):
        parts.append(f"kernel x{1 + p['kernel_dose_growth']:.2f} at full grey")
    return " ".join(parts)
