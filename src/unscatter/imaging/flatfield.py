"""Flat field, background and the batch's print threshold (registration, steps 1 and 2).

The camera's dark offset is subtracted and a smooth background surface B(x) (a
low-order polynomial) is fitted to the background pixels with one-sided outlier
rejection (polymer is brighter than background). Excitation and detection vignetting
shade background and polymer alike, so the corrected image c = I / B - 1 is polymer
fluorescence in units of the local background: flat across the field and comparable
between the prints of a batch. Where the background is too dark to divide by the batch
falls back to subtraction, c = (I - B) / median(B or noise).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from ..io import check_image_content, read_image_raw
from .template import gaussian


def _poly_basis(shape, degree: int, step: int = 1):
    H, W = shape
    y = (np.arange(0, H, step) - (H - 1) / 2) / (H / 2)
    x = (np.arange(0, W, step) - (W - 1) / 2) / (W / 2)
    X, Y = np.meshgrid(x, y)
    terms = [X**i * Y**j for i in range(degree + 1) for j in range(degree + 1 - i)]
    return np.stack([t.ravel() for t in terms], axis=1)


def fit_background(img: np.ndarray, degree: int = 2, iters: int = 12):
    """Smooth background surface and noise level of the background pixels.

    Fit on a block-averaged copy (fast, less noise); one-sided rejection of bright
    outliers (polymer); noise from the MAD of full-resolution residuals (on the blocks
    kept as background where they are under half of the image).
    """
    H, W = img.shape
    f = max(1, min(H, W) // 96)
    small = cv2.resize(img, (W // f, H // f), interpolation=cv2.INTER_AREA).astype(np.float64)
    A = _poly_basis(small.shape, degree)
    v = small.ravel()
    inl = v <= np.percentile(v, 50)
    coef = None
    for _ in range(iters):
        coef, *_ = np.linalg.lstsq(A[inl], v[inl], rcond=None)
        r = v - A @ coef
        s = 1.4826 * np.median(np.abs(r[inl] - np.median(r[inl]))) + 1e-9
        new = r < 2.5 * s
        if np.array_equal(new, inl):
            break
        inl = new
    # evaluate on the full grid
    Hb = np.zeros((H, W))
    y = (np.arange(H) - (H - 1) / 2) / (H / 2)
    x = (np.arange(W) - (W - 1) / 2) / (W / 2)
    k = 0
    for i in range(degree + 1):
        for j in range(degree + 1 - i):
            Hb += coef[k] * np.outer(y**j, x**i)
            k += 1
    # background pixel noise at full resolution (for SNR decisions); where the fit kept
    # less than half of the image as background, on the blocks it kept: the median pixel is
    # then polymer, and a grating printed as one block over 58 % of the field read a noise
    # of 43 counts against its background's 1.5, and its polymer sank below the threshold
    res = img - Hb
    bg = res[::2, ::2]
    if np.mean(inl) < 0.5:
        kept = cv2.resize(inl.reshape(small.shape).astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST)[::2, ::2] > 0
        bg = bg[kept] if kept.sum() >= 100 else bg
    med = np.median(bg)
    mad = 1.4826 * np.median(np.abs(bg[bg < med + 3 * (np.percentile(bg, 50) - np.percentile(bg, 10) + 1e-6)] - med))
    return Hb.astype(np.float32), float(max(mad, 1e-6)), float(np.mean(inl))


@dataclass
class Corrected:
    id: str
    c: np.ndarray  # corrected image: polymer fluorescence / background
    noise: float  # noise of c in the background
    background: float  # median background (ADU above offset)
    raw_dtype: str
    count: float  # one camera count (ADU) in the units of c, at the median background


def correct_image(mid: str, path: Path, offset: float, s, mode: str | None = None) -> Corrected:
    raw = read_image_raw(path)
    check_image_content(path, raw)
    img = raw.astype(np.float32) - np.float32(offset)
    B, noise, _ = fit_background(img, s.poly_degree)
    bmed = float(np.median(B))
    if mode is None:
        mode = "divide" if bmed > s.min_background_snr * noise else "subtract"
    if mode == "divide":
        c = (img - B) / np.maximum(B, 0.2 * bmed)
        n, count = noise / bmed, 1.0 / max(bmed, 1e-12)
    else:
        scale = max(bmed, noise)
        c = (img - B) / scale
        n, count = noise / scale, 1.0 / scale
    return Corrected(mid, c.astype(np.float32), float(n), bmed, str(raw.dtype), float(count))


def dense_level(corrected: list[Corrected], s) -> tuple[float, float]:
    """The batch's dense-polymer level and the print threshold, in corrected units.

    Pools all images: pixels clearly above background (8 noise levels) are polymer; the
    ``dense_quantile`` of their intensities is the level of dense, fully cured polymer.
    """
    noise = float(np.median([k.noise for k in corrected]))
    vals = []
    for k in corrected:
        sm = cv2.GaussianBlur(k.c, (0, 0), 1.0)[::2, ::2]
        v = sm[sm > 8 * noise]
        vals.append(v)
    pooled = np.concatenate(vals) if vals else np.zeros(0)
    if pooled.size < 50:
        return float("nan"), float("nan")
    dense = float(np.quantile(pooled, s.dense_quantile))
    return dense, s.level * dense


def reference_level(k: Corrected, erode: float = 0.25, min_radius_px: float = 24.0) -> tuple[float, float, int]:
    """The fluorescence of fully cured polymer measured on a dense reference print (batch.yaml
    ``dense_reference``): one large block at full grey exposed well past its cure (3 to 5
    times the trial prints' exposure), imaged as the batch is. The block is the largest
    connected part of the image above half its bright end (the 99.5th percentile, after a
    2 px smoothing against noise); its interior, eroded by ``erode`` of the block's radius
    (away from the edges that scattering and the microscope's blur soften), gives the level
    (its median) and the level's unevenness (the interior's robust sd over its median: a
    stain or the lamp's field across the block). Returns (level, unevenness, interior
    pixels); a ValueError where the image shows no block of at least ``min_radius_px``
    image px (the radius of a disc of its area).

    Measured on 8 random labs (a 320 px square on a 512 px field at 4 times the exposure):
    -14.7 to +4.3 % off the lab's level (median |error| 2.5 %), against -24.7 to +20.4 %
    (median 12.9 %) for the batch's brightest polymer (``dense_level``) of 12 trial prints;
    the worst is a lab whose stain varies by 22 % over 206 px."""
    sm = cv2.GaussianBlur(k.c, (0, 0), 2.0)
    bright = float(np.percentile(sm, 99.5))
    if not (np.isfinite(bright) and bright > 8 * k.noise):
        raise ValueError("its image holds nothing clearly brighter than the background")
    labels, n = ndimage.label(sm > 0.5 * bright)
    sizes = np.bincount(labels.ravel())[1:]
    radius = float(np.sqrt(sizes.max() / np.pi)) if n else 0.0
    if radius < min_radius_px:
        raise ValueError(f"its brightest part is as large as a disc of radius {radius:.0f} image px, less than "
                         f"{min_radius_px:.0f}: a dense reference is one large block (say a square of 5/8 of the field at "
                         "full grey)")
    block = labels == 1 + int(np.argmax(sizes))
    inner = ndimage.binary_erosion(block, iterations=max(1, int(erode * radius)))
    vals = k.c[inner]
    if vals.size < 100:
        raise ValueError("its block has no interior away from its edges to measure")
    level = float(np.median(vals))
    return level, float(1.4826 * np.median(np.abs(vals - level)) / max(level, 1e-12)), int(vals.size)


def stain_ratio(img: np.ndarray, predicted: np.ndarray, offset: float, level: float, top: float = 0.85,
                erode_px: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The ratio of a print's polymer to its fit's prediction over its cured interiors,
    relative to its median there, and those interiors (0 or 1), where a stain shows.

    ``predicted`` is the image that the print's fit predicts (gain T + offset, one gain
    for the whole print; ``img`` and it on one grid, NaN in ``img`` where it has no
    pixel) and ``level`` the print's cured level above ``offset`` (``pose.print_level``).
    The interiors are where the prediction reaches ``top`` of that level, eroded by
    ``erode_px`` so that an edge a pixel off does not count. Why the interiors: a blurred
    edge's half-height lies where it lies whatever the polymer's brightness, but a fit
    with one gain for the whole print puts it where the print's mean brightness would, so
    a dim part's edges are fitted inside the bright part's; the interiors tell brightness
    from place."""
    above = predicted - offset
    inner = (above >= top * level) & np.isfinite(img)
    if erode_px > 0:
        inner = cv2.erode(inner.astype(np.uint8), np.ones((2 * erode_px + 1,) * 2, np.uint8)) > 0
    ratio = np.zeros(img.shape, np.float32)
    if inner.sum() < 50 or not level > 0:
        return ratio, np.zeros(img.shape, np.float32)
    r = (img[inner] - offset) / np.maximum(above[inner], 1e-6 * level)
    med = float(np.median(r))
    if not med > 0:
        return ratio, np.zeros(img.shape, np.float32)
    ratio[inner] = r / med
    return ratio, inner.astype(np.float32)


def stain_field(ratio: np.ndarray, inner: np.ndarray, sigma_px: float, support: float = 0.02) -> tuple[np.ndarray, float]:
    """The polymer's own flat field in one image (uneven staining or photobleaching, which
    brightens or dims the polymer, not the background, smoothly across a print) from its
    interiors' ``ratio`` (``stain_ratio``; ``inner`` their weights): spread by normalised
    convolution of the first order (a plane fitted to the ratio under a Gaussian window of
    ``sigma_px`` px around each pixel: at an interior's edge, where the window's interiors
    lie to one side, a plain weighted mean is off by the stain's slope times their
    distance: 0.7 % at a half plane's edge for a stain of 20 % over 360 px at 16 px, 6 %
    in the unit test's grid of 50 px blocks, and the edges are where the field matters);
    where fewer than ``support`` of the pixels around are interiors it
    falls back to the same over 4 times the width, and from that to 1. Returns the field
    and its robust spread over the interiors (0 where there are none)."""
    if not inner.any():
        return np.ones(ratio.shape, np.float32), 0.0
    f = np.ones(ratio.shape)
    for sig in (4 * sigma_px, sigma_px):  # a wide field first, which the narrow one falls back to where its interiors are few
        f = _local_linear(ratio, inner, sig, f, support)
    f = np.clip(f, 0.25, 4.0).astype(np.float32)
    v = f[inner > 0]
    return f, float(1.4826 * np.median(np.abs(v - np.median(v))))


def _local_linear(v: np.ndarray, w: np.ndarray, sigma: float, prior: np.ndarray, support: float,
                  slope_ridge: float = 0.01) -> np.ndarray:
    """Normalised convolution of the first order (Knutsson and Westin 1993): at each pixel,
    the value at that pixel of the plane a + b x + c y fitted by least squares to ``v``
    with weights ``w`` times a Gaussian window of ``sigma`` px. The plane's level is pulled
    toward ``prior`` with the weight of ``support`` of a full window, its slopes toward 0
    with ``slope_ridge`` of one (x, y in window sigmas), so that a window with few or
    one-sided weights neither divides by nothing nor extrapolates a slope. OpenCV's
    Gaussian filter over the nine moments (``template.gaussian``: on a reduced grid where
    the window is wide; the moments about each pixel are exact for any linear filter, as
    the pixel's own coordinates are constants under it); float64 for the normal equations."""
    H, W = v.shape
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    x = (x - (W - 1) / 2) / sigma
    y = (y - (H - 1) / 2) / sigma
    w = w.astype(np.float64)
    wv = w * v

    def g(a):
        return gaussian(a, sigma, cv2.BORDER_CONSTANT)

    S0, Sx, Sy = g(w), g(w * x), g(w * y)
    Sxx, Sxy, Syy = g(w * x * x), g(w * x * y), g(w * y * y)
    R0, Rx, Ry = g(wv), g(wv * x), g(wv * y)
    # moments about the pixel itself: the plane's level there is its value
    mxx, mxy, myy = Sxx - 2 * x * Sx + x * x * S0, Sxy - x * Sy - y * Sx + x * y * S0, Syy - 2 * y * Sy + y * y * S0
    mx, my = Sx - x * S0, Sy - y * S0
    rx, ry = Rx - x * R0, Ry - y * R0
    # a full window weighs 1 (OpenCV's kernel sums to 1), and its second moments are 1 (x, y in sigmas)
    a00, b0 = S0 + support, R0 + support * prior
    a11, a12, a22 = mxx + slope_ridge, mxy, myy + slope_ridge
    # solve [[a00, mx, my], [mx, a11, a12], [my, a12, a22]] [a, b, c] = [b0, rx, ry] for a (Cramer's rule)
    det = a00 * (a11 * a22 - a12 * a12) - mx * (mx * a22 - a12 * my) + my * (mx * a12 - a11 * my)
    num = b0 * (a11 * a22 - a12 * a12) - mx * (rx * a22 - a12 * ry) + my * (rx * a12 - a11 * ry)
    return num / det
