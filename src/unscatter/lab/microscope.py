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
    electrons = cfg["photons"] * lamp * vig * (warped + cfg["background"])
    counts = rng.poisson(np.maximum(electrons, 0)) + rng.normal(0, cfg["read_noise_e"], size=(H, W))
    adu = counts * cfg["adu_per_e"] + cfg["offset_adu"]
    img = np.clip(np.round(adu), 0, 65535).astype(np.uint16)
    pose = dict(pose, blur_px=blur, vignetting=v, lamp=lamp)
    return img, pose, M
