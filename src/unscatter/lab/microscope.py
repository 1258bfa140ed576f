"""The virtual fluorescence microscope: density on the DMD grid -> 16-bit camera image."""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage


def similarity(rotation_deg: float, scale: float, center_src, center_dst) -> np.ndarray:
    """2x3 matrix mapping source pixel (x, y) to destination: rotate+scale about centres."""
    th = np.deg2rad(rotation_deg)
    a, b = scale * np.cos(th), scale * np.sin(th)
    A = np.array([[a, -b], [b, a]])
    t = np.asarray(center_dst, float) - A @ np.asarray(center_src, float)
    return np.hstack([A, t[:, None]])


def draw_pose(cfg: dict, design_px: int, rng: np.random.Generator) -> dict:
    """Random rotation, scale and shift within the config's ranges, design kept in view."""
    H, W = cfg["image_size"]
    r = float(cfg["rotation_deg"])
    rot = float(rng.uniform(-r, r))
    lo, hi = cfg["scale"]
    scale = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    # half-extent of the rotated, scaled design region; keep a few pixels of margin
    th = np.deg2rad(abs(rot))
    half = 0.5 * scale * design_px * (np.cos(th) + np.sin(th)) + 4
    lim = np.array([max(0.0, H / 2 - half), max(0.0, W / 2 - half)])
    lim = np.minimum(lim, cfg["shift_frac"] * np.array([H, W]))
    dy, dx = (float(rng.uniform(-m, m)) for m in lim)
    return dict(rotation_deg=rot, scale=scale, shift_x=dx, shift_y=dy)


def smooth_field(rng: np.random.Generator, shape, length_px: float) -> np.ndarray:
    """A smooth random field of zero mean and unit std that varies over ``length_px``:
    white noise on a coarse grid, interpolated bicubically (cheap at any image size)."""
    H, W = shape
    gh, gw = int(np.ceil(H / length_px)) + 3, int(np.ceil(W / length_px)) + 3
    coarse = rng.standard_normal((gh, gw)).astype(np.float32)
    f = cv2.resize(coarse, (int(gw * length_px), int(gh * length_px)), interpolation=cv2.INTER_CUBIC)
    o = int(1.5 * length_px)  # leave out the border of the interpolation
    f = f[o : o + H, o : o + W].astype(np.float64)
    return (f - f.mean()) / max(f.std(), 1e-12)


def _stain(polymer: np.ndarray, cfg: dict | None, rng: np.random.Generator) -> np.ndarray:
    """Uneven staining or photobleaching: the polymer's fluorescence (not the background)
    varies smoothly across the print by a relative std of ``variation``."""
    if not cfg or not cfg.get("variation", 0) > 0:
        return polymer
    f = 1.0 + float(cfg["variation"]) * smooth_field(rng, polymer.shape, float(cfg["length_px"]))
    return polymer * np.maximum(f, 0.0).astype(np.float32)


def _haze(light: np.ndarray, cfg: dict | None) -> np.ndarray:
    """A wide PSF wing: a ``fraction`` of the light (out-of-focus light, scatter in the dish)
    spread by a Gaussian of ``sigma_px`` image pixels, so prints glow into the background."""
    if not cfg or not cfg.get("fraction", 0) > 0:
        return light
    f = float(cfg["fraction"])
    return (1 - f) * light + f * cv2.GaussianBlur(light, (0, 0), float(cfg["sigma_px"]), borderType=cv2.BORDER_CONSTANT)


def _background(level: float, tilt: float, shape, rng: np.random.Generator):
    """The background fluorescence; with ``tilt`` > 0 it changes linearly by that share
    from one side of the image to the other (direction random per image): a background
    that is not radially symmetric and, unlike vignetting, does not shade the polymer."""
    if not tilt > 0:
        return level
    H, W = shape
    th = float(rng.uniform(0, 2 * np.pi))
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    t = np.cos(th) * (xx - (W - 1) / 2) + np.sin(th) * (yy - (H - 1) / 2)
    t /= np.abs(np.cos(th)) * (W - 1) + np.abs(np.sin(th)) * (H - 1)  # -0.5 .. 0.5 corner to corner
    return level * (1.0 + tilt * t)


def digitize(counts: np.ndarray, cfg: dict) -> np.ndarray:
    """The camera's 16-bit values of ``counts`` (electrons plus read noise): gain, dark
    offset, rounding and the ADC's range."""
    return np.clip(np.round(counts * cfg["adu_per_e"] + cfg["offset_adu"]), 0, 65535).astype(np.uint16)


def stored(img: np.ndarray, cfg: dict) -> np.ndarray:
    """The image as the lab stores it: 16-bit, or an 8-bit export (``format: png8``) that
    keeps the top byte and drops the rest."""
    return (img >> 8).astype(np.uint8) if cfg.get("format", "tif16") == "png8" else img


def image_print(density_padded: np.ndarray, pad: int, design_px: int, cfg: dict, rng: np.random.Generator, pose=None):
    """Image a print. Returns (uint16 image, pose, 2x3 design->image matrix)."""
    H, W = cfg["image_size"]
    pose = pose or draw_pose(cfg, design_px, rng)
    s = pose["scale"]
    c_design = ((design_px - 1) / 2,) * 2
    c_img = ((W - 1) / 2 + pose["shift_x"], (H - 1) / 2 + pose["shift_y"])
    M = similarity(pose["rotation_deg"], s, c_design, c_img)  # design px (x, y) -> image px
    M_pad = M.copy()
    M_pad[:, 2] -= M[:, :2] @ np.array([pad, pad], float)  # padded-grid px -> image px
    blo, bhi = cfg["blur_px"]
    blur = float(rng.uniform(blo, bhi))
    # optical PSF (in image pixels) plus anti-aliasing when the camera samples coarser
    sig = np.hypot(blur / s, max(0.0, 0.5 * (1 / s - 1)))
    rho = ndimage.gaussian_filter(density_padded, sig)
    warped = cv2.warpAffine(rho.astype(np.float32), M_pad, (W, H), flags=cv2.INTER_LINEAR, borderValue=0.0)

    vlo, vhi = cfg["vignetting"]
    v = float(rng.uniform(vlo, vhi))
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    cy, cx = (H - 1) / 2 + rng.normal(0, 0.05 * H), (W - 1) / 2 + rng.normal(0, 0.05 * W)
    rmax2 = ((H / 2) ** 2 + (W / 2) ** 2)
    vig = 1.0 - v * ((yy - cy) ** 2 + (xx - cx) ** 2) / rmax2
    lamp = max(0.2, 1.0 + cfg["lamp_jitter"] * rng.standard_normal())
    # effects that are off by default; each draws random numbers only when it is on, so
    # the default lab's images stay the same
    warped = _stain(warped, cfg.get("staining"), rng)
    warped = _haze(warped, cfg.get("haze"))
    background = _background(cfg["background"], float(cfg.get("background_tilt") or 0.0), (H, W), rng)
    electrons = cfg["photons"] * lamp * vig * (warped + background)
    counts = rng.poisson(np.maximum(electrons, 0)) + rng.normal(0, cfg["read_noise_e"], size=(H, W))
    img = digitize(counts, cfg)
    pose = dict(pose, blur_px=blur, vignetting=v, lamp=lamp)
    return img, pose, M
