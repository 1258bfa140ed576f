"""Registration and thresholding of fluorescence images of prints (stage 'registration').

A microscope image shows a print at an unknown rotation, scale and offset, under
vignetting, background and noise, with no fiducial marks. For each print of a batch:

1. **Flat-field and background.** The camera's dark offset (``camera_offset_adu`` in
   batch.yaml, 0 if absent) is subtracted. A smooth background surface B(x) (a
   low-order polynomial) is fitted to the background pixels with one-sided outlier
   rejection (polymer is brighter than background). Excitation and detection vignetting
   shade background and polymer alike, so the corrected image c = I / B - 1 is
   polymer fluorescence in units of the local background: flat across the field and
   comparable between the prints of a batch. Where the background is too dark to
   divide by (below ``min_background_snr`` noise levels) the batch falls back to
   subtraction, c = (I - B) / median(B or noise).
2. **One threshold per batch.** The print is where polymer density is at least
   ``level`` times that of dense, fully cured polymer. The dense level is estimated once
   for the whole batch (the upper quantile of pooled foreground intensities), so a print
   of low polymer density is *not* re-thresholded as if it were dense, as a per-image
   Otsu would do. An image with (almost) nothing above the batch threshold is an
   **empty** print: it is written as an all-void print and never registered to noise.
3. **Registration from the mask.** The template is the mask blurred by a few pixels (a
   print is a blurred, thresholded copy of its mask). A coarse search over rotation and
   scale with FFT cross-correlation for the shift (phase-correlation start), then ECC
   refinement (OpenCV ``findTransformECC``, affine, two pyramid levels). In the default
   similarity mode the affine result is projected onto rotation + isotropic scale.
4. **QC.** Rotation and scale within the configured ranges, ECC converged, template
   correlation at least ``min_score``, and the print inside the image. A print that
   fails is marked ``failed`` in qc.tsv with the reason and no print is written for it.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from .io import InputError, check_image_content, open_batch, read_image_raw, read_mask, read_yaml, write_png, write_rgb, write_tsv, write_yaml

log = logging.getLogger(__name__)


class RegistrationError(RuntimeError):
    """One or more prints failed registration QC."""


@dataclass
class Settings:
    mode: str = "similarity"  # or "affine"
    level: float = 0.5  # print = density >= level * dense polymer
    min_score: float = 0.6
    rotation_max_deg: float = 20.0
    scale_range: tuple = (0.6, 1.6)  # image px per mask px
    min_coverage: float = 0.995
    poly_degree: int = 2
    min_background_snr: float = 5.0
    min_print_px: int = 30  # mask px above threshold for a print to count as non-empty
    template_sigma: float = 2.0  # mask px
    dense_quantile: float = 0.9
    skip_failed: bool = False
    threads: int = 2
    extra: dict = field(default_factory=dict)


# --------------------------------------------------------------------- flat field


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
    outliers (polymer); noise from the MAD of full-resolution residuals.
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
    # background pixel noise at full resolution (for SNR decisions)
    res = img - Hb
    bg = res[::2, ::2]
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


def correct_image(mid: str, path: Path, offset: float, s: Settings, mode: str | None = None) -> Corrected:
    raw = read_image_raw(path)
    check_image_content(path, raw)
    img = raw.astype(np.float32) - np.float32(offset)
    B, noise, _ = fit_background(img, s.poly_degree)
    bmed = float(np.median(B))
    if mode is None:
        mode = "divide" if bmed > s.min_background_snr * noise else "subtract"
    if mode == "divide":
        c = (img - B) / np.maximum(B, 0.2 * bmed)
        n = noise / bmed
    else:
        scale = max(bmed, noise)
        c = (img - B) / scale
        n = noise / scale
    return Corrected(mid, c.astype(np.float32), float(n), bmed, str(raw.dtype))


# -------------------------------------------------------------------- registration


def _template(mask: np.ndarray, sigma: float, margin: int) -> np.ndarray:
    t = np.pad(mask.astype(np.float32) / 255.0, margin)
    return cv2.GaussianBlur(t, (0, 0), sigma)


def _similarity(theta_deg: float, scale: float, src_c, dst_c) -> np.ndarray:
    th = np.deg2rad(theta_deg)
    A = scale * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    t = np.asarray(dst_c, float) - A @ np.asarray(src_c, float)
    return np.hstack([A, t[:, None]])


def _zn(a: np.ndarray) -> np.ndarray:
    a = a - a.mean()
    return a / (np.linalg.norm(a) + 1e-12)


def _grid_search(t_small, i_small, thetas, scales, hi):
    """FFT cross-correlation of the warped template with the image for every (theta, scale).

    Returns candidates (score, theta, scale, template-centre position in the image)."""
    Hs, Ws = i_small.shape
    N = cv2.getOptimalDFTSize(int(max(Hs, Ws) + hi * max(t_small.shape) * 1.5))
    img_c = np.zeros((N, N), np.float32)
    img_c[:Hs, :Ws] = _zn(i_small)
    Fi = np.fft.rfft2(img_c)
    ct = ((t_small.shape[1] - 1) / 2, (t_small.shape[0] - 1) / 2)
    out = []
    for sc in scales:
        side = int(np.ceil(max(t_small.shape) * sc * 1.42)) + 2
        c_side = ((side - 1) / 2, (side - 1) / 2)
        for th in thetas:
            w = cv2.warpAffine(t_small, _similarity(th, sc, ct, c_side), (side, side), flags=cv2.INTER_LINEAR)
            tz = np.zeros((N, N), np.float32)
            tz[:side, :side] = _zn(w)
            cc = np.fft.irfft2(Fi * np.conj(np.fft.rfft2(tz)), s=(N, N))
            k = int(np.argmax(cc))
            dy, dx = divmod(k, N)
            dy = dy - N if dy > N // 2 else dy
            dx = dx - N if dx > N // 2 else dx
            out.append((float(cc.flat[k]), float(th), float(sc), np.array([c_side[0] + dx, c_side[1] + dy])))
    out.sort(key=lambda c: -c[0])
    return out


def coarse_pose(tpl: np.ndarray, img: np.ndarray, s: Settings):
    """Rotation and scale by grid search, shift by FFT cross-correlation (phase-correlation
    start), coarse to fine: a wide grid with the template at 64 px, then a fine grid around
    the two best candidates at 128 px. Returns a 2x3 template->image matrix, peak score.
    """
    lo, hi = s.scale_range
    cands = None
    for side, dth, dls in ((64, 4.0, 0.08), (128, 1.0, 0.02)):
        f = max(1.0, tpl.shape[0] / side)
        t_small = cv2.resize(tpl, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA)
        i_small = cv2.resize(img, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA)
        if cands is None:
            thetas = np.arange(-s.rotation_max_deg, s.rotation_max_deg + 1e-9, dth)
            scales = np.exp(np.arange(np.log(lo), np.log(hi) + 1e-9, dls))
            cands = _grid_search(t_small, i_small, thetas, scales, hi)
        else:
            found = []
            for _, th0, sc0, _ in cands[:2]:
                thetas = th0 + np.arange(-3, 3 + 1e-9, dth)
                scales = sc0 * np.exp(np.arange(-0.06, 0.06 + 1e-9, dls))
                found += _grid_search(t_small, i_small, thetas, scales, hi)
            found.sort(key=lambda c: -c[0])
            cands = found
    v, th, sc, pos = cands[0]
    c_tpl = ((tpl.shape[1] - 1) / 2, (tpl.shape[0] - 1) / 2)
    c_img = f * pos + (f - 1) / 2  # pixel centres: x_full = f x_small + (f - 1) / 2
    return _similarity(th, sc, c_tpl, c_img), v


def refine_ecc(tpl: np.ndarray, img: np.ndarray, M0: np.ndarray, levels=(2, 1)):
    """ECC (Evangelidis & Psarakis 2008), affine, coarse to fine. Returns (M, rho)."""
    M = M0.astype(np.float32).copy()
    rho = np.nan
    for lv in levels:
        if lv > 1:
            t = cv2.resize(tpl, None, fx=1 / lv, fy=1 / lv, interpolation=cv2.INTER_AREA)
            i = cv2.resize(img, None, fx=1 / lv, fy=1 / lv, interpolation=cv2.INTER_AREA)
            S = np.diag([lv, lv, 1.0]).astype(np.float32)
            Si = np.diag([1 / lv, 1 / lv, 1.0]).astype(np.float32)
            # pixel-centre conventions are absorbed by ECC's translation refinement
            Mlv = (Si @ np.vstack([M, [0, 0, 1]]) @ S)[:2]
        else:
            t, i, Mlv = tpl, img, M
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100 if lv > 1 else 50, 1e-5)
        rho, Mlv = cv2.findTransformECC(t, i, Mlv.astype(np.float32), cv2.MOTION_AFFINE, crit, None, 3)
        if lv > 1:
            S = np.diag([lv, lv, 1.0]).astype(np.float32)
            Si = np.diag([1 / lv, 1 / lv, 1.0]).astype(np.float32)
            M = (S @ np.vstack([Mlv, [0, 0, 1]]) @ Si)[:2]
        else:
            M = Mlv
    return M.astype(np.float64), float(rho)


def project_similarity(M: np.ndarray, center) -> np.ndarray:
    """Nearest rotation + isotropic scale to the affine part; the centre maps as before."""
    A = M[:, :2]
    a = 0.5 * (A[0, 0] + A[1, 1])
    b = 0.5 * (A[1, 0] - A[0, 1])
    As = np.array([[a, -b], [b, a]])
    c = np.asarray(center, float)
    t = (A @ c + M[:, 2]) - As @ c
    return np.hstack([As, t[:, None]])


def pose_of(M: np.ndarray, design_px: int, image_shape) -> dict:
    """Rotation (deg), scale and centre shift (image px) of a design->image matrix."""
    A = M[:, :2]
    scale = float(np.sqrt(abs(np.linalg.det(A))))
    rot = float(np.rad2deg(np.arctan2(A[1, 0] - A[0, 1], A[0, 0] + A[1, 1])))
    c = (design_px - 1) / 2
    p = A @ np.array([c, c]) + M[:, 2]
    H, W = image_shape
    return dict(rotation_deg=rot, scale=scale, shift_x=float(p[0] - (W - 1) / 2), shift_y=float(p[1] - (H - 1) / 2))


class PrintTemplate:
    """What a print of a mask looks like, for registration: the mask under a smooth
    field, scattered by a Gaussian core plus a wider Gaussian tail, turned into polymer
    density by a saturating cure above a gel dose, then blurred by the microscope.

    A blurred mask alone is a poor template: prints of grey cells, peripheral features
    under a weaker field and small features eroded by scattering all differ from the
    mask, and ECC absorbs the difference into scale and shift (1 to 6 px over the field
    in our measurements). The template's parameters are properties of the printer, so
    they are fitted once per batch, jointly over its prints (Powell on the mean
    correlation at quarter resolution), which keeps them from trading off against each
    image's pose. It is a registration nuisance model, not the calibrated printer model.
    """

    NAMES = ("sigma", "gel", "k", "field_r2", "field_bx", "field_by", "tail", "tail_sigma")
    START = (4.0, 0.3, 0.2, 0.0, 0.0, 0.0, 0.1, 15.0)

    def __init__(self, design_px: int, margin: int, factor: int = 1):
        self.margin, self.f, self.design_px = margin, factor, design_px
        n = (design_px + 2 * margin) // factor
        ax = ((np.arange(n) * factor + (factor - 1) / 2) - (design_px + 2 * margin - 1) / 2) / ((design_px - 1) / 2)
        self.X, self.Y = np.meshgrid(ax.astype(np.float32), ax.astype(np.float32))
        self.R2 = self.X**2 + self.Y**2

    def padded(self, mask: np.ndarray) -> np.ndarray:
        m = np.pad(mask.astype(np.float32) / 255.0, self.margin)
        if self.f > 1:
            m = cv2.resize(m, None, fx=1 / self.f, fy=1 / self.f, interpolation=cv2.INTER_AREA)
        return m

    def __call__(self, m: np.ndarray, x) -> np.ndarray:
        sigma, gel, k, r2, bx, by, tail, tail_sigma = (float(v) for v in x)
        f = self.f
        e = m * (1 + r2 * self.R2 + bx * self.X + by * self.Y)
        b = cv2.GaussianBlur(e, (0, 0), max(sigma, 0.3) / f)
        tail = min(max(tail, 0.0), 0.9)
        if tail > 0:
            b = (1 - tail) * b + tail * cv2.GaussianBlur(e, (0, 0), max(tail_sigma, 1.0) / f)
        r = -np.expm1(-np.maximum(b - gel, 0) / max(k, 1e-3))
        return cv2.GaussianBlur(r.astype(np.float32), (0, 0), 1.0 / f)


def fit_template(tmpl: PrintTemplate, pairs: list, x0, max_evals: int = 400) -> tuple[np.ndarray, float]:
    """Template parameters maximising the mean NCC over prints (scipy's Powell).

    ``pairs``: (padded mask, image warped into padded design coordinates), on tmpl's grid.
    """
    from scipy.optimize import minimize

    def cost(x):
        return -float(np.mean([ncc(reg, tmpl(m, x)) for m, reg in pairs]))

    res = minimize(cost, np.asarray(x0, float), method="Powell", options=dict(maxfev=max_evals, xtol=1e-3, ftol=1e-5))
    return res.x, -float(res.fun)


def to_design(M: np.ndarray, margin: int) -> np.ndarray:
    """Template (padded) -> image matrix to design -> image matrix."""
    Md = M.copy()
    Md[:, 2] = M[:, :2] @ np.array([margin, margin], float) + M[:, 2]
    return Md


def warp_to_design(c: np.ndarray, M: np.ndarray, design_px: int) -> np.ndarray:
    return cv2.warpAffine(c, M.astype(np.float64), (design_px, design_px), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)


def threshold_print(c: np.ndarray, M: np.ndarray, thr: float, design_px: int):
    """The corrected image in design coordinates and the print: smoothed against noise
    over about one image pixel, then the batch threshold. Returns (registered, print)."""
    reg = warp_to_design(c, M, design_px)
    scale = np.sqrt(abs(np.linalg.det(M[:, :2])))
    reg_s = cv2.GaussianBlur(np.nan_to_num(reg, nan=0.0), (0, 0), max(0.5, 0.6 / scale))
    return reg, reg_s >= thr


def coverage(M: np.ndarray, mask: np.ndarray, image_shape, margin_px=8) -> float:
    """Share of the mask's exposed area (plus a margin) that lands inside the image."""
    exposed = ndimage.binary_dilation(mask > 0, iterations=margin_px)
    ys, xs = np.nonzero(exposed[::2, ::2])
    if len(xs) == 0:
        return 1.0
    pts = M[:, :2] @ np.vstack([2 * xs, 2 * ys]).astype(float) + M[:, 2:3]
    H, W = image_shape
    inside = (pts[0] >= 0) & (pts[0] <= W - 1) & (pts[1] >= 0) & (pts[1] <= H - 1)
    return float(inside.mean())


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 10:
        return 0.0
    x, y = a[ok] - a[ok].mean(), b[ok] - b[ok].mean()
    return float((x * y).sum() / (np.sqrt((x * x).sum() * (y * y).sum()) + 1e-12))


# ------------------------------------------------------------------- thresholding


def dense_level(corrected: list[Corrected], s: Settings) -> tuple[float, float]:
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


# --------------------------------------------------------------------------- batch


def _overlay(reg: np.ndarray, mask: np.ndarray, printed: np.ndarray, dense: float) -> np.ndarray:
    from .metrics import edges

    g = np.nan_to_num(reg, nan=0.0) / (1.2 * dense if dense > 0 else 1.0)
    g = (np.clip(g, 0, 1) * 255).astype(np.uint8)
    rgb = np.stack([g, g, g], axis=-1)
    e_mask = ndimage.binary_dilation(edges(mask > 127))
    rgb[e_mask] = (255, 40, 40)  # the mask's contour, red
    rgb[edges(printed)] = (40, 220, 40)  # the thresholded print's contour, green
    return rgb


MARGIN = 32  # design px of context around the design region in templates


def register_batch(batch_dir, out_dir, mode="similarity", level=0.5, min_score=0.6, skip_failed=False, progress=True, **kw) -> list[dict]:
    """Register and threshold every image of a batch; write prints, qc.tsv, overlays."""
    from tqdm import tqdm

    s = Settings(mode=mode, level=level, min_score=min_score, skip_failed=skip_failed, **kw)
    if mode not in ("similarity", "affine"):
        raise ValueError(f"mode must be 'similarity' or 'affine', not {mode!r}")
    batch = open_batch(batch_dir)
    meta_raw = read_yaml(Path(batch_dir) / "batch.yaml")
    offset = float(meta_raw.get("camera_offset_adu", 0) or 0)
    out_dir = Path(out_dir)
    (out_dir / "overlays").mkdir(parents=True, exist_ok=True)
    ids = batch.ids
    masks = {mid: read_mask(batch.masks[mid]) for mid in ids}
    shapes = {m.shape for m in masks.values()}
    sh = next(iter(shapes))
    if len(shapes) != 1 or sh[0] != sh[1]:
        raise InputError(Path(batch_dir) / "masks", f"masks must all be square and of one size, found {sorted(shapes)}")
    design_px = sh[0]
    pool = ThreadPoolExecutor(s.threads)
    bar = tqdm(total=5 * len(ids), desc=f"registering {Path(batch_dir).name}", unit="step", disable=not progress)

    def pmap(fn, items):
        out = []
        for r in pool.map(fn, items):
            out.append(r)
            bar.update(1)
        return out

    # 1. flat field: one mode for the whole batch, so units agree between prints
    corr = pmap(lambda mid: correct_image(mid, batch.images[mid], offset, s, "divide"), ids)
    ff_mode = "divide" if all(k.noise < 1.0 / s.min_background_snr for k in corr) else "subtract"
    if ff_mode == "subtract":
        corr = list(pool.map(lambda mid: correct_image(mid, batch.images[mid], offset, s, "subtract"), ids))
    corr = {k.id: k for k in corr}

    # 2. one threshold for the batch; empty prints are recognised before registration
    dense, thr = dense_level(list(corr.values()), s)
    log.info("flat field: %s; dense polymer level %.3g, threshold %.3g (level %.2f)", ff_mode, dense, thr, s.level)
    smooth = {mid: cv2.GaussianBlur(k.c, (0, 0), 1.0) for mid, k in corr.items()}
    empty = set()
    for mid, k in corr.items():
        n_above = int(np.count_nonzero(smooth[mid] > max(thr, 6 * k.noise))) if np.isfinite(thr) else 0
        if n_above < s.min_print_px:
            empty.add(mid)
    todo = [mid for mid in ids if mid not in empty and masks[mid].max() > 0]
    bar.total = 2 * len(ids) + 3 * len(todo)
    bar.refresh()

    # 3. pose with a blurred-mask template, then with the batch's print template
    def first_pose(mid):
        tpl = _template(masks[mid], s.template_sigma, MARGIN)
        M0, cc = coarse_pose(tpl, smooth[mid], s)
        try:
            M, _ = refine_ecc(tpl, smooth[mid], M0)
            return M, True
        except cv2.error:
            return M0, False

    poses = dict(zip(todo, pmap(first_pose, todo)))
    full = PrintTemplate(design_px, MARGIN)
    quarter = PrintTemplate(design_px, MARGIN, factor=4)
    x = np.array(PrintTemplate.START)
    tshape = (design_px + 2 * MARGIN,) * 2
    fit_ids = todo[:: max(1, len(todo) // 12)][:12]  # a spread of prints is enough to fit 8 numbers
    for it in range(2):
        def pair(mid):
            reg = cv2.warpAffine(smooth[mid], poses[mid][0], tshape[::-1], flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
            return quarter.padded(masks[mid]), cv2.resize(reg, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)

        if fit_ids:
            x, fit = fit_template(quarter, list(pool.map(pair, fit_ids)), x)
            log.info("print template (round %d): %s, mean NCC %.4f", it + 1, dict(zip(PrintTemplate.NAMES, np.round(x, 4))), fit)

        def refine(mid):
            M, ok = poses[mid]
            try:
                M, _ = refine_ecc(full(full.padded(masks[mid]), x), smooth[mid], M, (1,))
                return M, ok
            except cv2.error:
                return M, False

        poses = dict(zip(todo, pmap(refine, todo)))
    p = dict(zip(PrintTemplate.NAMES, (float(v) for v in x)))

    # 4. warp, threshold, QC, write
    def finish(mid):
        k, mask = corr[mid], masks[mid]
        row = dict(id=mid, status="ok", reason="", rotation_deg="", scale="", shift_x="", shift_y="", score="",
                   threshold=thr, dense_level=dense, flatfield=ff_mode, coverage="", solid_fraction="",
                   mask=os.path.relpath(batch.masks[mid].resolve(), out_dir.resolve()), image=str(batch.images[mid]))
        if mid in empty:
            printed = np.zeros((design_px, design_px), bool)
            row.update(status="empty", reason="no polymer above the batch threshold", solid_fraction=0.0)
            write_png(out_dir / f"{mid}.png", printed)
            write_rgb(out_dir / "overlays" / f"{mid}.png", _overlay(np.zeros(printed.shape), mask, printed, 1.0))
            return row
        if mask.max() == 0:
            row.update(status="failed", reason="polymer in the image but the mask is all zero")
            return row
        M, converged = poses[mid]
        if s.mode == "similarity":
            M = project_similarity(M, ((tshape[1] - 1) / 2, (tshape[0] - 1) / 2))
        M = to_design(M, MARGIN)
        pose = pose_of(M, design_px, k.c.shape)
        reg, printed = threshold_print(k.c, M, thr, design_px)
        tpl = full(full.padded(mask), x)[MARGIN:-MARGIN, MARGIN:-MARGIN]
        score = ncc(reg, tpl)
        cov = coverage(M, mask, k.c.shape)
        row.update(**{kk: round(v, 4) for kk, v in pose.items()}, score=round(score, 4), coverage=round(cov, 4))
        for a in range(2):
            for b in range(3):
                row[f"m{a}{b}"] = float(M[a, b])
        reasons = []
        if not converged:
            reasons.append("ECC refinement did not converge")
        if abs(pose["rotation_deg"]) > s.rotation_max_deg:
            reasons.append(f"rotation {pose['rotation_deg']:.1f} deg beyond +-{s.rotation_max_deg}")
        if not s.scale_range[0] <= pose["scale"] <= s.scale_range[1]:
            reasons.append(f"scale {pose['scale']:.3f} outside {tuple(s.scale_range)}")
        if score < s.min_score:
            reasons.append(f"registration score {score:.2f} below {s.min_score}")
        if cov < s.min_coverage:
            reasons.append(f"print extends beyond the image (only {100 * cov:.1f} % in view)")
        row["solid_fraction"] = round(float(printed.mean()), 5)
        write_rgb(out_dir / "overlays" / f"{mid}.png", _overlay(reg, mask, printed, dense))
        if reasons:
            row.update(status="failed", reason="; ".join(reasons))
            return row
        write_png(out_dir / f"{mid}.png", printed)
        return row

    rows = pmap(finish, ids)
    bar.close()
    pool.shutdown()
    cols = ["id", "status", "reason", "rotation_deg", "scale", "shift_x", "shift_y", "score", "coverage", "threshold",
            "dense_level", "flatfield", "solid_fraction", "mask", "image"] + [f"m{a}{b}" for a in range(2) for b in range(3)]
    write_tsv(out_dir / "qc.tsv", rows, cols)
    write_yaml(out_dir / "batch.yaml", dict(meta_raw, source_batch=str(Path(batch_dir))))
    write_yaml(out_dir / "registration.yaml", dict(settings=dict(mode=s.mode, level=s.level, min_score=s.min_score),
                                                   flatfield=ff_mode, dense_level=dense, threshold=thr, print_template=p))
    contact_sheet(out_dir / "overlays", rows, out_dir / "overlays.png")
    failed = [r for r in rows if r["status"] == "failed"]
    for r in failed:
        log.warning("%s: registration failed: %s", r["id"], r["reason"])
    if failed and not s.skip_failed:
        raise RegistrationError(
            f"{len(failed)} of {len(rows)} prints in {batch_dir} failed registration QC "
            f"({'; '.join(r['id'] + ': ' + r['reason'] for r in failed)}). See {out_dir / 'qc.tsv'} and the overlays; "
            "re-image them, remove them from the batch, or set registration.skip_failed to go on without them."
        )
    return rows


def contact_sheet(overlay_dir: Path, rows: list[dict], out_path: Path, thumb: int = 160, cols: int = 8) -> None:
    """All overlays of a batch on one page, each labelled with its id and QC status."""
    from PIL import Image, ImageDraw

    n = len(rows)
    ncols = min(cols, max(n, 1))
    nrows = (n + ncols - 1) // ncols
    sheet = Image.new("RGB", (ncols * thumb, nrows * (thumb + 14)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    colour = {"ok": (0, 120, 0), "empty": (90, 90, 90), "failed": (200, 0, 0)}
    for i, r in enumerate(rows):
        x, y = (i % ncols) * thumb, (i // ncols) * (thumb + 14)
        p = overlay_dir / f"{r['id']}.png"
        if p.is_file():
            with Image.open(p) as im:
                sheet.paste(im.convert("RGB").resize((thumb, thumb)), (x, y + 14))
        draw.text((x + 2, y + 1), f"{r['id']} {r['status']}", fill=colour.get(r["status"], (0, 0, 0)))
    out_path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out_path)


def transform_rms_px(M_est: np.ndarray, M_true: np.ndarray, design_px: int, step: int = 8) -> float:
    """RMS distance (design pixels) between where two design->image maps send the design field."""
    g = np.arange(0, design_px, step, dtype=float)
    X, Y = np.meshgrid(g, g)
    P = np.vstack([X.ravel(), Y.ravel()])
    d = (M_est[:, :2] - M_true[:, :2]) @ P + (M_est[:, 2:3] - M_true[:, 2:3])
    s = np.sqrt(abs(np.linalg.det(M_true[:, :2])))
    return float(np.sqrt(np.mean(np.sum(d * d, axis=0))) / s)
