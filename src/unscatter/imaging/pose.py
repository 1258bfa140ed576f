"""The pose of a print in its image: hypotheses, refinement, and the choice between them.

A pose is a 2x3 matrix that maps the padded design grid (the mask with ``margin``
pixels of context on every side) to image pixels. Registration of one print:

1. **Coarse hypotheses** (``coarse_candidates``): a grid over rotation and scale with
   FFT cross-correlation for the shift, coarse to fine, keeping several *distinct*
   poses instead of the single best (a grating, a star or a print whose extent is
   unclear has several peaks of nearly equal height).
2. **Refinement** (``refine``): Gauss-Newton on the image against the print template,
   forward-compositional as in Lucas-Kanade / ECC (Baker & Matthews 2004,
   doi:10.1023/B:VISI.0000011205.11775.fd), with the print's own dose, gain and
   offset estimated together with the pose and Huber weights on the residual (parts
   of a print that cure differently from the template's prediction pull less), damped
   as Levenberg-Marquardt where a step would raise the objective. A template of the
   wrong size biases scale when the size is not free; here it is.
3. **Alternatives from the print's self-similarity** (``self_similar_moves``): the
   moves of the design grid (shifts, rotations) under which the predicted print
   nearly maps onto itself, found from its auto-correlation. A grating one pitch off
   or a star one spoke off is such a move; each is refined and tested against the
   best pose.
4. **Evidence** (``evidence``): two poses are compared on the same image pixels, each
   with its own fitted gain, offset and dose. The per-block gains in clipped squared
   residual, e_b, give z = sum(e_b) / sqrt(sum(e_b^2)): z grows as the square root of
   the number of blocks that agree, so a decision needs the evidence spread over the
   print (a period broken at the print's ends, the parts that did not cure), not a
   single dust speck, and needs no noise model. A print of a few small dots spans too
   few blocks for z to reach its bar against any rival; ``contradicted`` finds a part
   the size of a feature that only one of two poses explains (polymer where the other
   predicts no cure near, or a cured part it predicts where the image shows none).
5. **Spread** (``Fit.pose_sd``, ``size_spread``): how well the print fixes its pose,
   from the noise and from how hard its parts pull against each other (a cluster-robust
   estimate over tiles, ``_pose_sd``), and separately how far the pose rests on the
   sizes of its features, which the template predicts worst: one block, or a grating
   printed as one, has a scale that only its size sets.

Refinement works on the window of the grid that the print can reach (the mask's
scattered dose, widened by the blur and a band of background), not the whole grid.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import fft as sfft, ndimage

from .template import PrintTemplate, _gradient, reduction


def similarity(theta_deg: float, scale: float, src_c, dst_c) -> np.ndarray:
    """Rotation by theta and isotropic scale about src_c, moved to dst_c (2x3)."""
    th = np.deg2rad(theta_deg)
    A = scale * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    t = np.asarray(dst_c, float) - A @ np.asarray(src_c, float)
    return np.hstack([A, t[:, None]])


def h3(M: np.ndarray) -> np.ndarray:
    return np.vstack([M, [0.0, 0.0, 1.0]])


def _zn(a: np.ndarray) -> np.ndarray:
    a = a - a.mean()
    return a / (np.linalg.norm(a) + 1e-12)


@functools.lru_cache(maxsize=16)
def _field_points(grid_px: int, margin: int, step: int) -> np.ndarray:
    """The points (2 x n, read-only) over the design region at which ``pose_distance`` compares poses."""
    g = np.arange(margin, grid_px - margin, step, dtype=float)
    X, Y = np.meshgrid(g, g)
    P = np.vstack([X.ravel(), Y.ravel()])
    P.flags.writeable = False
    return P


def pose_moves(M1: np.ndarray, M2: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Where two grid->image poses send the grid points ``P`` (2 x n), the first less
    the second (image px, 2 x n)."""
    return (M1[:, :2] - M2[:, :2]) @ P + (M1[:, 2:3] - M2[:, 2:3])


def pose_distance(M1: np.ndarray, M2: np.ndarray, grid_px: int, margin: int, step: int = 16) -> float:
    """RMS distance (design px) between where two grid->image poses send the design region."""
    d = pose_moves(M1, M2, _field_points(int(grid_px), int(margin), int(step)))
    s = np.sqrt(abs(np.linalg.det(M2[:, :2])))
    return float(np.sqrt(np.mean(np.sum(d * d, axis=0))) / s)


# ------------------------------------------------------------------ 1. coarse search


def _turned(t_small, thetas, scales):
    """The template rotated by each theta and scaled by each scale about its centre (scales
    outer, thetas inner), on a square that holds it at any turn, zero-normalised: yields
    (theta, scale, the square's centre (x, y), the template)."""
    ct = ((t_small.shape[1] - 1) / 2, (t_small.shape[0] - 1) / 2)
    for sc in scales:
        side = int(np.ceil(max(t_small.shape) * sc * 1.42)) + 2
        c_side = ((side - 1) / 2, (side - 1) / 2)
        for th in thetas:
            w = cv2.warpAffine(t_small, similarity(th, sc, ct, c_side), (side, side), flags=cv2.INTER_LINEAR)
            yield float(th), float(sc), c_side, _zn(w).astype(np.float32)


def _grid_search(t_small, Fi, N, thetas, scales):
    """FFT cross-correlation of the rotated, scaled template with the image.

    Returns (score, theta, scale, template-centre position in the small image) for
    every (theta, scale), the shift at the correlation peak."""
    out = []
    for th, sc, c_side, w in _turned(t_small, thetas, scales):
        tz = np.zeros((N, N), np.float32)
        tz[: w.shape[0], : w.shape[1]] = w
        cc = np.fft.irfft2(Fi * np.conj(np.fft.rfft2(tz)), s=(N, N))
        k = int(np.argmax(cc))
        dy, dx = divmod(k, N)
        dy = dy - N if dy > N // 2 else dy
        dx = dx - N if dx > N // 2 else dx
        out.append((float(cc.flat[k]), th, sc, np.array([c_side[0] + dx, c_side[1] + dy])))
    out.sort(key=lambda c: -c[0])
    return out


def _local_search(t_small, img_z, pos0, thetas, scales, radius):
    """``_grid_search`` with the template's centre within ``radius`` px of ``pos0`` (x, y in
    the small image): each (theta, scale)'s correlation is computed only over those shifts
    (OpenCV's ``matchTemplate`` on the part of the zero-padded image they reach), not
    over the whole image."""
    Hs, Ws = img_z.shape
    out, regions = [], {}
    for th, sc, c_side, w in _turned(t_small, thetas, scales):
        side = w.shape[0]
        x0, y0 = (int(round(v)) - radius for v in (pos0[0] - c_side[0], pos0[1] - c_side[1]))  # top-left, first shift
        if side not in regions:  # the image under every shift, one square side at a time
            span = side + 2 * radius
            region = np.zeros((span, span), np.float32)
            ys, xs = slice(max(0, y0), min(Hs, y0 + span)), slice(max(0, x0), min(Ws, x0 + span))
            if ys.stop > ys.start and xs.stop > xs.start:
                region[ys.start - y0:ys.stop - y0, xs.start - x0:xs.stop - x0] = img_z[ys, xs]
            regions[side] = region
        cc = cv2.matchTemplate(regions[side], w, cv2.TM_CCORR)
        k = int(np.argmax(cc))
        dy, dx = divmod(k, cc.shape[1])
        out.append((float(cc.flat[k]), th, sc, np.array([c_side[0] + x0 + dx, c_side[1] + y0 + dy])))
    out.sort(key=lambda c: -c[0])
    return out


def _distinct(cands, count, d_theta, d_logs, d_pos):
    kept = []
    for c in cands:
        if all(abs(c[1] - k[1]) > d_theta or abs(np.log(c[2] / k[2])) > d_logs or np.hypot(*(c[3] - k[3])) > d_pos
               for k in kept):
            kept.append(c)
        if len(kept) == count:
            break
    return kept


FINE_RADIUS = 8  # px of the 128 px grid that the fine search may move a candidate: 4 px of the 64 px grid, on which
# a candidate's shift is within half a pixel plus what a rotation step of 4 deg and a scale step of 8 % move the peak


def coarse_candidates(tpl: np.ndarray, img: np.ndarray, rotation: tuple, scale: tuple, count: int = 3):
    """Up to ``count`` distinct poses (template grid -> image), best first, with their scores.

    A wide grid with the template at 64 px (every shift, by FFT), then a fine grid
    around each distinct candidate at 128 px, its shift within ``FINE_RADIUS`` px of the
    candidate's (``_local_search``). ``rotation`` (deg) and ``scale`` (image px per
    design px) are the ranges searched."""
    lo, hi = scale
    rlo, rhi = rotation
    cands, f_prev = None, 1.0
    for side, dth, dls in ((64, 4.0, 0.08), (128, 1.0, 0.02)):
        f = max(1.0, tpl.shape[0] / side)
        t_small = cv2.resize(tpl, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA)
        i_small = cv2.resize(img, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA)
        Hs, Ws = i_small.shape
        if cands is None:
            N = cv2.getOptimalDFTSize(int(max(Hs, Ws) + hi * max(t_small.shape) * 1.5))
            img_c = np.zeros((N, N), np.float32)
            img_c[:Hs, :Ws] = _zn(i_small)
            n_th = max(1, int(np.ceil((rhi - rlo) / dth)))
            thetas = np.linspace(rlo, rhi, n_th + 1) if rhi > rlo else np.array([rlo])
            scales = np.exp(np.arange(np.log(lo), np.log(hi) + 1e-9, dls)) if hi > lo * np.exp(dls / 2) else np.array([np.sqrt(lo * hi)])
            found = _grid_search(t_small, np.fft.rfft2(img_c), N, thetas, scales)
            cands = _distinct(found, count, 6.0, 0.1, 3.0)
        else:
            img_z, fine = _zn(i_small).astype(np.float32), []
            for _, th0, sc0, pos0 in cands:
                thetas = np.clip(th0 + np.arange(-3, 3 + 1e-9, dth), rlo, rhi)
                scales = np.clip(sc0 * np.exp(np.arange(-0.06, 0.06 + 1e-9, dls)), lo, hi)
                at = (f_prev * pos0 + (f_prev - 1) / 2 - (f - 1) / 2) / f  # the candidate's centre on this grid
                found = _local_search(t_small, img_z, at, np.unique(thetas), np.unique(scales), FINE_RADIUS)
                fine.append(found[0])
            fine.sort(key=lambda c: -c[0])
            cands = _distinct(fine, count, 1.5, 0.02, 2.0)
        f_prev = f
    c_tpl = ((tpl.shape[1] - 1) / 2, (tpl.shape[0] - 1) / 2)
    return [(v, similarity(th, sc, c_tpl, f * pos + (f - 1) / 2)) for v, th, sc, pos in cands]


def refine_ecc(tpl: np.ndarray, img: np.ndarray, M0: np.ndarray, levels=(2, 1)):
    """ECC (Evangelidis & Psarakis 2008, doi:10.1109/TPAMI.2008.113), affine, coarse to
    fine, for the first poses against the blurred mask. Returns (M, rho)."""
    M = M0.astype(np.float32).copy()
    rho = np.nan
    for lv in levels:
        S = np.diag([lv, lv, 1.0]).astype(np.float32)
        Si = np.diag([1 / lv, 1 / lv, 1.0]).astype(np.float32)
        if lv > 1:
            t = cv2.resize(tpl, None, fx=1 / lv, fy=1 / lv, interpolation=cv2.INTER_AREA)
            i = cv2.resize(img, None, fx=1 / lv, fy=1 / lv, interpolation=cv2.INTER_AREA)
            # pixel-centre conventions are absorbed by ECC's translation refinement
            Mlv = (Si @ h3(M) @ S)[:2]
        else:
            t, i, Mlv = tpl, img, M
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100 if lv > 1 else 50, 1e-5)
        rho, Mlv = cv2.findTransformECC(t, i, Mlv.astype(np.float32), cv2.MOTION_AFFINE, crit, None, 3)
        M = (S @ h3(Mlv) @ Si)[:2] if lv > 1 else Mlv
    return M.astype(np.float64), float(rho)


# -------------------------------------------------------------------- 2. refinement


@dataclass
class Fit:
    """A refined pose with the print's own nuisance numbers."""

    M: np.ndarray  # full-resolution grid -> image
    gain: float
    offset: float
    q: np.ndarray  # the print's nuisance numbers, in the order of NUISANCE
    sigma: float  # robust scale of the residual
    pose_sd: float  # standard deviation of the pose, RMS over the design field (design px)
    converged: bool
    iterations: int
    size_sd: float = float("nan")  # pose spread from the print's size not being known (design px; set by the batch)
    # the same without its features' own places (size_spread's place_dose_sd): how far the
    # pose rests on its features' sizes alone, which decides how a stated pixel size holds it
    sizes_sd: float = float("nan")
    joined: bool = False  # refine stopped on reaching one of the poses it was given (``known``)
    # refined with its scale held: ``refine``'s ``scale_prior`` (mean log scale, sd), the batch's or a stated one
    scale_prior: tuple | None = None
    # pose spread from the batch's scatter kernel being known only in shape so well (design px; ``kernel_spread``)
    model_sd: float = 0.0

    @property
    def scale_held(self) -> bool:
        """Refined with its scale held (``scale_prior``)."""
        return self.scale_prior is not None

    def __getattr__(self, name):  # dose, blur, grad_x, grad_y, edge
        if name == "q":  # not set yet (pickle and copy look for methods before the fields are back)
            raise AttributeError(name)
        if name in Q_NAMES[: len(self.q)]:
            return float(self.q[Q_NAMES.index(name)])
        raise AttributeError(name)


def _grid_to_full(f: int) -> np.ndarray:
    """Grid subsampled by f -> full grid (pixel centres: x = f x_s + (f - 1) / 2)."""
    return np.array([[f, 0, (f - 1) / 2], [0, f, (f - 1) / 2], [0, 0, 1.0]])


def _warp(img: np.ndarray, Ms: np.ndarray, shape) -> np.ndarray:
    return cv2.warpAffine(img, Ms.astype(np.float64), shape[::-1], flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)


# The print's own nuisance numbers: name, prior mean (None: the batch template's value of
# that name), prior standard deviation. The priors keep the fit well posed where a print
# cannot tell them apart (dose against gel, edge offset against scale for one feature);
# the pose's spread then shows what the print leaves open.
# (The gel dose is the batch's: with the dose free it only trades against it.)
# Erosion or swelling is the material's, alike for every print of a batch: a print's own
# edge offset only takes up small differences, or it trades against the scale of any
# print that is one feature (a star, a disc, a block).
NUISANCE = (("dose", 1.0, 0.3), ("blur", None, 1.5), ("grad_x", 0.0, 0.15), ("grad_y", 0.0, 0.15), ("edge", 0.0, 0.5),
            ("edge_c2", 0.0, 0.3), ("edge_s2", 0.0, 0.3))
_BOUNDS = {"dose": (0.2, 5.0), "blur": (0.3, 20.0), "grad_x": (-0.5, 0.5), "grad_y": (-0.5, 0.5), "edge": (-6.0, 6.0),
           "edge_c2": (-4.0, 4.0), "edge_s2": (-4.0, 4.0), "bright_x": (-0.5, 0.5), "bright_y": (-0.5, 0.5)}


# In a batch that stains unevenly (its template's ``stain_slope`` above 0), each print also
# has its polymer's brightness slopes across the field: the image is gain (1 + bright_x X +
# bright_y Y) T + offset, their prior sd the batch's stain_slope. A stain brightens one
# side of a print; a fit with one gain puts the dim side's edges inside the bright side's,
# and a print without solid interiors (a fine grating, a star's spokes) shows no field that
# the batch could divide out first (``flatfield.stain_field``).
BRIGHTNESS = ("bright_x", "bright_y")
Q_NAMES = tuple(n for n, _, _ in NUISANCE) + BRIGHTNESS  # a Fit's q, in order (the slopes only where it has them)
STAIN_SLOPE = PrintTemplate.NAMES.index("stain_slope")  # the template number that holds the stain's prior sd
TAIL = PrintTemplate.NAMES.index("tail")  # the template's tail share, its width (tail_sigma) next


def stain_slope(x) -> float:
    """The prior sd of a print's brightness slopes in a batch of template numbers ``x``
    (0: the batch does not stain, and its prints have none)."""
    return float(x[STAIN_SLOPE]) if len(x) > STAIN_SLOPE else 0.0


def _prior(x, override: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Prior means and standard deviations of the nuisance numbers (and the brightness
    slopes where the batch stains); ``override``: name -> (mean, sd) in their place (the
    batch's edge offsets for a print that is one feature)."""
    batch = {"blur": max(float(x[10]), 0.3)}
    override = override or {}
    mean = [override[n][0] if n in override else batch[n] if m is None else m for n, m, _ in NUISANCE]
    sd = [override[n][1] if n in override else sd for n, _, sd in NUISANCE]
    if stain_slope(x) > 0:
        mean, sd = mean + [0.0, 0.0], sd + [stain_slope(x)] * 2
    return np.array(mean), np.array(sd)


def print_template(tmpl, B: np.ndarray, x, q, derivatives: bool = True) -> tuple[np.ndarray, list]:
    """The print's template for nuisance numbers q (order of NUISANCE, then the brightness
    slopes where q holds them) and its derivatives (``derivatives=False``: the template
    alone, and the derivatives that come free with it, those along the edge offsets and
    the slopes; None for the four that cost an image each)."""
    dose, blur, gx, gy, *edge = (float(v) for v in q)
    edge, bright = edge[:3], edge[3:]
    field = 1.0 + gx * tmpl.X + gy * tmpl.Y
    if derivatives:
        T, (dT, dTx, dTy), dTb = tmpl.cure_jacobian(B, x, dose * field, (field, dose * tmpl.X, dose * tmpl.Y), blur, 0.1 * blur)
    else:
        T, dT, dTb, dTx, dTy = tmpl.cure(B, x, dose * field, blur=blur), None, None, None, None
    T, dTe = edge_shifted(T, edge, tmpl.f)
    d = [dT, dTb, dTx, dTy, *dTe]
    if bright:  # the polymer's brightness slopes (BRIGHTNESS): the image's, after the cure and its edges
        shade = 1.0 + bright[0] * tmpl.X + bright[1] * tmpl.Y
        d = [None if v is None else v * shade for v in d] + [T * tmpl.X, T * tmpl.Y]
        T = T * shade
    return T, d


def log_scale(M: np.ndarray) -> float:
    """Log of a pose's scale (image px per grid px): half the log of its linear part's |det|."""
    return float(0.5 * np.log(abs(np.linalg.det(np.asarray(M)[:2, :2]))))


def _log_scale_row(n: int, mode: str) -> np.ndarray:
    """d log scale / d pose step, padded to ``n`` parameters: the first pose number is a
    relative scale change (similarity); affine: the mean of the two diagonal ones."""
    a = np.zeros(n)
    if mode == "affine":
        a[[0, 3]] = 0.5
    else:
        a[0] = 1.0
    return a


def refine(img: np.ndarray, fit_or_M, tmpl, B: np.ndarray, x, mode: str = "similarity", iters: int = 20,
           tol: float = 0.01, spread: bool = True, prior: dict | None = None, scale_prior: tuple | None = None,
           known: list | None = None, region: np.ndarray | None = None, hold_nuisance: bool = False,
           outside=None) -> Fit:
    """Gauss-Newton (maximum a posteriori) on the pose, gain, offset and the print's
    nuisance numbers (``NUISANCE``, with their priors), with Levenberg-Marquardt damping:
    a step that raises the objective (Huber on the residual, the priors, a held scale) by
    more than ``RISE`` is refused and taken again from the same state, damped, and the
    damping eases off as steps succeed (not with ``hold_nuisance``). Undamped, a print
    whose dose trades against its edge offset, or a dim print fitted from the prior's
    dose, overshot to a dose that cures nothing; the priors then pulled every nuisance
    number back and the pose walked off, called settled.

    ``img`` is the corrected image, ``tmpl`` a PrintTemplate (its ``factor`` sets the
    resolution), ``B`` the mask's scattered dose on tmpl's grid, ``x`` the batch's
    template numbers. Minimises sum w (I(M x) - gain T(x; q) - offset)^2 / sigma^2 plus
    the priors' penalties, with Huber weights w; the pose's Jacobian comes from
    gain * grad T, which is noise-free and equals the aligned image's gradient at the
    solution (image noise in the gradient would inflate the normal matrix and shorten
    every step). ``spread=False`` skips the pose's standard deviation (``pose_sd`` nan).
    ``prior`` overrides nuisance priors (``_prior``).

    ``scale_prior`` (mean log scale, its standard deviation) is what the batch knows of the
    scale (image px per design px) when one magnification imaged it (``batch_scale``):
    the scale is held at the mean, and the standard deviation counts in the pose's spread
    (unlike the nuisance priors, it is measured on other prints), so a print whose scale
    its features' sizes would set, or pull off, has its pose.

    ``known``: poses (full-grid matrices) already refined from other starts. A start
    whose steps bring it within ``JOIN_PX`` of one of them stops there (``Fit.joined``):
    it would only end where that one did, after a walk of 2 px steps that is
    most of the work of a start far from its pose.

    ``region``: a boolean image of tmpl's grid; only its pixels count in the residual (the
    surroundings of a mask's registration marks, whatever the rest of the print does).
    ``hold_nuisance``: the nuisance numbers stay at the given fit's (only the pose, gain
    and offset are fitted, and the pose's spread is conditional on them): for a region
    whose features cannot fix them (solid squares, whose dose, blur and edge offset
    trade against each other and run away).

    ``outside(M, gain)``: True for a pose that the caller will not count (turned or scaled
    far beyond the searched ranges, a negative gain). A start whose steps stay there for
    ``OUTSIDE_STEPS`` steps in a row stops (not converged): it would only walk on, to the
    iteration limit, to a pose that is dropped.
    """
    q0, qs = _prior(x, prior)
    held = None if scale_prior is None else tuple(scale_prior)  # the fit records it (``Fit.scale_held``)
    if isinstance(fit_or_M, Fit):
        M, gain, offset, q = fit_or_M.M, fit_or_M.gain, fit_or_M.offset, fit_or_M.q.copy()
        q = np.r_[q, q0[len(q):]][: len(q0)]  # brightness slopes from none where the batch has since found a stain
    else:
        M, gain, offset, q = np.asarray(fit_or_M, float), None, 0.0, q0.copy()
    lo = np.array([_BOUNDS[n][0] for n in Q_NAMES[: len(q0)]])
    hi = np.array([_BOUNDS[n][1] for n in Q_NAMES[: len(q0)]])
    f = tmpl.f
    S = _grid_to_full(f)
    S_inv = np.linalg.inv(S)
    Ms = h3(M) @ S
    scale = float(np.sqrt(abs(np.linalg.det(Ms[:2, :2]))))
    src = cv2.GaussianBlur(img, (0, 0), 0.4 * scale) if scale > 1.2 else img
    n = tmpl.shape[0]
    c = (n - 1) / 2
    corners = np.array([[-c, -c], [c, -c], [-c, c], [c, c]]).T
    # the grid's window that the print can reach: where the mask's scattered dose is, widened
    # by the microscope's blur and a band of background for the offset
    (r0, r1), (c0, c1) = _window(B, int(np.ceil((4 * max(float(x[10]), 1.0) + ROI_BAND_PX) / f)))
    shape = (r1 - r0, c1 - c0)
    # the template is computed on a crop of the grid that holds the window and every pixel
    # the print can cure at (``_cure_crop``), and cut to the window
    (a0, a1), (b0, b1) = _cure_crop(tmpl, B, x, ((r0, r1), (c0, c1)))
    sub, B_sub = tmpl.crop((a0, a1), (b0, b1)), B[a0:a1, b0:b1]
    sl = (slice(r0 - a0, r1 - a0), slice(c0 - b0, c1 - b0))
    g = np.arange(n, dtype=np.float32) - np.float32(c)
    Xg, Yg = np.meshgrid(g[c0:c1], g[r0:r1])
    into = np.array([[1.0, 0, c0], [0, 1.0, r0], [0, 0, 1.0]])  # window -> grid
    counted = None if region is None else np.asarray(region, bool)[r0:r1, c0:c1]
    sigma, it, move, H_data, norm, r, w, npose = float("nan"), 0, float("inf"), None, None, None, None, 0
    cvec = np.array([c, c])

    def step(H, rhs, norm, npose, lam):
        """The step from the normal equations, damped by ``lam`` (Levenberg-Marquardt: a
        larger lam turns it toward the gradient and shortens it), within the trust region."""
        Hl = H + lam * np.diag(np.diag(H)) if lam > 0 else H
        delta = np.linalg.solve(Hl, rhs) / norm
        p = delta[:npose]
        if mode == "affine":
            D, t = np.array([[p[0], p[1]], [p[2], p[3]]]), p[4:6]
        else:
            D, t = np.array([[p[0], -p[1]], [p[1], p[0]]]), p[2:4]
        move = float(np.abs(D @ corners + t[:, None]).max())
        if move > 2.0:  # a trust region: at most 2 grid px a step
            D, t, delta, move = D * 2.0 / move, t * 2.0 / move, delta * 2.0 / move, 2.0
        return (D, t, float(delta[npose]), float(delta[npose + 1]), delta[npose + 2 :]), move

    def stepped(st, dz):  # the state ``st`` moved by the step ``dz``
        (Ms0, gain0, offset0, q0_), (D, t, dg, do, dq_) = st, dz
        A_s, t_s = Ms0[:2, :2], Ms0[:2, 2]
        Ms1 = h3(np.hstack([A_s @ (np.eye(2) + D), (A_s @ (t - D @ cvec) + t_s)[:, None]]))
        return Ms1, gain0 + dg, offset0 + do, q0_ if hold_nuisance else np.clip(q0_ + dq_, lo, hi)

    def cost(a, q, Ms, sigma, stiff):  # the objective that the steps lower (``a``: |residual| where valid, float64)
        k = 2.0 * sigma
        c_ = float(np.where(a <= k, a * a, 2.0 * k * a - k * k).sum()) / sigma**2 + float((((q - q0) / qs) ** 2).sum())
        if scale_prior is not None:
            c_ += stiff * (log_scale(Ms) - float(np.log(f)) - scale_prior[0]) ** 2
        return 0.5 * c_

    # last: the objective, sigma, stiffness, state and normal equations of the last state a
    # step was taken from (the steps from it are judged at its sigma and stiffness); lam: the
    # damping, zero (Gauss-Newton) until a step fails
    last, lam, rejected, stiff, last_move, away = None, 0.0, 0, 0.0, float("inf"), 0
    J = Jw = None  # the Jacobian, transposed (a row a parameter), and its rows weighted: written again each step
    for it in range(1, iters + 1):
        Iw = _warp(src, (Ms @ into)[:2], shape)
        valid = np.isfinite(Iw) if counted is None else np.isfinite(Iw) & counted
        T, dq = print_template(sub, B_sub, x, q, derivatives=not hold_nuisance)
        T, dq = T[sl], [] if hold_nuisance else [d[sl] for d in dq]
        if gain is None:  # first pass: gain and offset by least squares
            A = np.stack([T[valid], np.ones(int(valid.sum()), np.float32)], 1)
            gain, offset = (float(v) for v in np.linalg.lstsq(A, Iw[valid], rcond=None)[0])
        Iw = np.where(valid, Iw, offset + gain * T).astype(np.float32)
        res = Iw - gain * T - offset
        absr = np.abs(res[valid])
        a64 = None if hold_nuisance else absr.astype(np.float64)  # for the objective, which hold_nuisance never judges
        if last is not None and cost(a64, q, Ms, last[1], last[2]) > (1.0 + RISE) * last[0]:
            # the step raised the objective (Gauss-Newton overshot along a curved valley, as
            # dose against edge offset, or to a dose that cures nothing, after which the
            # priors alone would pull the numbers back): back to the last state, damped
            rejected += 1
            if rejected > MAX_REJECTED:  # no step lowers it: the last state stays
                Ms, gain, offset, q = last[3]
                move = last_move
                break
            lam = 1e-2 if lam == 0 else 10.0 * lam
            dz, move = step(*last[4], lam)
            Ms, gain, offset, q = stepped(last[3], dz)
            continue
        r, rejected = res, 0
        lam = 0.0 if lam < 1e-3 else lam / 3.0
        sigma = float(1.4826 * np.median(absr)) + 1e-6
        w = np.where(valid, np.minimum(1.0, 2.0 * sigma / (np.abs(r) + 1e-12)), 0.0).astype(np.float32, copy=False)
        npose = 6 if mode == "affine" else 4
        if J is None:
            J = np.empty((npose + 2 + len(dq), T.size), np.float32)
            Jw = np.empty_like(J)
        _jacobian(J.reshape(len(J), *shape), gain, T, dq, Xg, Yg, mode)
        norm = np.sqrt(np.einsum("ij,ij->i", J, J, dtype=np.float64)) + 1e-9
        J /= norm[:, None].astype(np.float32)
        np.multiply(J, w.ravel()[None, :], out=Jw)
        H_data = (Jw @ J.T).astype(np.float64) / sigma**2
        rhs = -(Jw @ r.ravel()).astype(np.float64) / sigma**2
        if scale_prior is not None:  # held at the batch's (a penalty far stiffer than the data's own precision,
            # which trusts the template's sizes); the pose's spread is then the spread at that scale (the
            # data's pull on the scale, which no longer balances, left out) and the batch's spread's
            a = _log_scale_row(len(J), mode) / norm
            ls = log_scale(Ms) - float(np.log(f))
            stiff = 1e3 * float(np.trace(H_data)) / float(a @ a)
            H_data += stiff * np.outer(a, a)
            rhs -= stiff * a * (ls - scale_prior[0])
        H = H_data.copy()
        kq = slice(npose + 2, None)
        if not hold_nuisance:
            H[kq, kq] += np.diag(1.0 / (qs * norm[kq]) ** 2)
            rhs[kq] -= (q - q0) / (qs**2 * norm[kq])
        H[np.diag_indices_from(H)] += 1e-9 * np.trace(H) / len(H)
        state = (Ms, gain, offset, q)
        if not hold_nuisance:  # the nuisance numbers are what overshoots: held, no step is judged
            last = (cost(a64, q, Ms, sigma, stiff), sigma, stiff, state, (H, rhs, norm, npose))
        dz, move = step(H, rhs, norm, npose, lam)
        if lam > 0:  # settled is judged by the undamped step
            move = step(H, rhs, norm, npose, 0.0)[1]
        last_move = move
        Ms, gain, offset, q = stepped(state, dz)
        if move < tol:
            break
        if known:
            here = (Ms @ S_inv)[:2]
            if any(pose_distance(here, K, tmpl.design_px + 2 * tmpl.margin, tmpl.margin) < JOIN_PX for K in known):
                return Fit(here, float(gain), float(offset), q, sigma, float("nan"), False, it, joined=True,
                           scale_prior=held)
        if outside is not None:
            away = away + 1 if outside((Ms @ S_inv)[:2], gain) else 0
            if away >= OUTSIDE_STEPS:
                break
    converged = move < 0.25  # still moving by a quarter pixel a step: not settled (less is in the pose spread)
    sd = float("nan")
    if spread:
        sd = _pose_sd(H_data, norm, npose, J, w.ravel(), r.ravel(), sigma, shape, max(4, TILE_PX // f), mode, corners) * f
        if scale_prior is not None:
            a = _log_scale_row(npose, mode)
            sd = float(np.hypot(sd, _field_rms(np.outer(a, a) * scale_prior[1] ** 2, mode, corners) * f))
    M_full = (Ms @ S_inv)[:2]
    return Fit(M_full, float(gain), float(offset), q, sigma, sd, converged, it, scale_prior=held)


def _jacobian(J: np.ndarray, gain: float, T: np.ndarray, dq: list, Xg: np.ndarray, Yg: np.ndarray, mode: str) -> None:
    """``refine``'s Jacobian of the residual, a row (an image of the window) a parameter,
    written into ``J``: the pose's from gain * grad T (affine: the four of the linear part,
    then the shift; similarity: scale, turn, shift), then gain, offset and the nuisance
    numbers'. The numbers of the lists of images it was built from before, to the last
    digit, without a new array for every row at every step (the gain a Python float, as
    refine's is: a float32 image times it stays float32)."""
    gain = float(gain)
    gT = gain * T
    gx, gy = (J[4], J[5]) if mode == "affine" else (J[2], J[3])
    _gradient(gT, gy, 0)
    _gradient(gT, gx, 1)
    if mode == "affine":
        for row, (u, v) in zip(J[:4], ((gx, Xg), (gx, Yg), (gy, Xg), (gy, Yg))):
            np.multiply(u, v, out=row)
    else:
        np.multiply(gx, Xg, out=J[0])
        J[0] += gy * Yg
        np.multiply(gy, Xg, out=J[1])
        J[1] -= gx * Yg
    k = 6 if mode == "affine" else 4
    np.negative(T, out=J[k])
    J[k + 1] = -1.0
    for row, d in zip(J[k + 2 :], dq):
        np.multiply(-gain, d, out=row)


# refine: a step that raises the objective by more than this share is refused. The pose's
# steps follow the template's gradient, not the image's (noise-free, and blind to image
# structure the template lacks), so near the solution they may raise the image's residual
# a little; refusing every rise stalled prints short of the pose (an eroding batch's trial
# prints did not converge). Measured on three benchmark seeds' images (768 prints): 1 %
# left 11 silently wrong and 254 failed; no rise at all, 7 and 266; the code before
# (undamped, and the evidence's old clip level), 14 and 266.
RISE = 0.01
MAX_REJECTED = 5  # refine: steps from one state that raise the objective, ever more damped, before refinement stops there
OUTSIDE_STEPS = 3  # refine: steps in a row at poses the caller does not count (``outside``) before a start stops
JOIN_PX = 1.0  # refine: a start this close (RMS over the field, design px) to a pose already refined stops
ROI_BAND_PX = 16  # design px of background around the print that refinement keeps


def _cure_crop(tmpl, B: np.ndarray, x, window: tuple) -> tuple:
    """Rows and columns (start, stop) of the grid on which ``refine`` computes the print
    template: the residual ``window`` and every pixel where the print can cure within the
    nuisance numbers' bounds (dose B above the gel dose at the largest dose and field
    gradients), widened by one cell of the haze's reduced grid and starting on one of its
    cells, so that the template there equals the whole grid's (``PrintTemplate.crop``).
    The cure needs dose x field x B > gel, with dose <= 5 and field <= 1 + 0.5 |X| + 0.5 |Y|
    (under 2.2 over the padded grid)."""
    gel = float(x[1])
    reach = _BOUNDS["dose"][1] * (1.0 + _BOUNDS["grad_x"][1] * float(np.abs(tmpl.X).max()) + _BOUNDS["grad_y"][1] * float(np.abs(tmpl.Y).max()))
    on = B * reach > gel if gel > 0 else np.ones(B.shape, bool)
    rows, cols = np.flatnonzero(on.any(1)), np.flatnonzero(on.any(0))
    (r0, r1), (c0, c1) = window
    if len(rows):
        r0, r1, c0, c1 = min(r0, rows[0]), max(r1, rows[-1] + 1), min(c0, cols[0]), max(c1, cols[-1] + 1)
    d = reduction(tmpl.haze_sigma(x)) if tmpl.haze(x) > 0 else 1
    n0, n1 = B.shape
    return ((max(0, (r0 - d) // d * d), min(n0, r1 + d)), (max(0, (c0 - d) // d * d), min(n1, c1 + d)))


def _window(B: np.ndarray, band: int):
    """Rows and columns (start, stop) of the part of B above 2 % of its maximum, widened by
    ``band``; the whole grid when B is empty."""
    on = B > 0.02 * float(B.max()) if B.max() > 0 else np.ones(B.shape, bool)
    rows, cols = np.flatnonzero(on.any(1)), np.flatnonzero(on.any(0))
    n0, n1 = B.shape
    return ((max(0, rows[0] - band), min(n0, rows[-1] + band + 1)), (max(0, cols[0] - band), min(n1, cols[-1] + band + 1)))


def edge_shifted(T: np.ndarray, edge, factor: int = 1):
    """The template with its edges moved outward, to first order, and the derivatives.

    ``edge`` = (e0, c2, s2), design px: an edge whose normal points at angle t moves by
    e0 + c2 cos 2t + s2 sin 2t, i.e. T + |grad T| e0 + (gx^2 - gy^2) / |grad T| c2 +
    2 gx gy / |grad T| s2. A print that is uniformly larger or smaller than predicted
    (erosion or swelling after the wash, a cure boundary the template misplaces), or
    more so across one direction than the other (anisotropic scattering), is otherwise
    matched by a wrong scale.
    """
    gy, gx = np.gradient(T)
    gxx, gyy = gx * gx, gy * gy
    g = np.sqrt(gxx + gyy)
    inv = 1.0 / np.maximum(g, 1e-12 + 1e-6 * float(g.max()))
    gxx -= gyy
    gxx *= inv
    gy *= 2 * gx  # 2 gx gy, as (2 gx) gy
    gy *= inv
    basis = [g / factor, gxx / factor, gy / factor]
    e0, c2, s2 = (float(v) for v in edge)
    return T + e0 * basis[0] + c2 * basis[1] + s2 * basis[2], basis


# The print's size is what a template predicts worst (the cure boundary of a dose near the
# gel point, erosion, a fine grating that prints as one block). ``size_spread`` asks how
# well the pose is fixed by where the features' edges lie when their sizes are known only
# to a given standard deviation: edge positions off by EDGE_SD (design px), as one over
# EDGE_CORR_PX of edge.
EDGE_SD = 0.4
EDGE_CORR_PX = 16.0
WEAK_EDGE = 0.25  # boundary pixels with less than this share of the median slope do not count
MARGINAL_PEAK = 1.2  # a predicted feature whose peak is below this times the level (60 % of the print's) does not count
SEEN_SHARE = 0.5  # a predicted feature of whose core less than this share is above the level in the image does not count
SEEN_AREA = 0.25  # ... nor one of which less than this share (of all its pixels) is (a block whose joined lines did not print)


def edge_misfit(img: np.ndarray, T: np.ndarray, fit: "Fit") -> float:
    """How far the image's edges lie from the fitted template's, as an RMS displacement
    (grid px): the residual's energy near the edges over the template's gradient energy
    there. ``img`` is the image on ``T``'s grid (NaN outside it). Every residual counts as
    an edge's displacement, the image noise, a stain or a brighter part of a print too,
    so this overstates how far the edges are off; it is used only where it is small
    (``size_spread``'s ``edge_sd``)."""
    P = fit.gain * T.astype(np.float64) + fit.offset
    gy, gx = np.gradient(P)
    g2 = gx * gx + gy * gy
    if not np.isfinite(img).any() or g2.max() <= 0:
        return float("inf")
    win = (cv2.dilate((g2 > 0.05 * g2.max()).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0) & np.isfinite(img)
    return float(np.sqrt(float(np.sum((img[win] - P[win]) ** 2)) / max(float(g2[win].sum()), 1e-12)))


def _boundary(T: np.ndarray) -> tuple:
    """The predicted print's boundary: its level (half its maximum), gradient (x, y,
    magnitude), and the pixels within half a gradient step of the level, less those where
    T falls off at under WEAK_EDGE of the boundary's median slope."""
    lvl = 0.5 * float(T.max())
    gy, gx = np.gradient(T.astype(np.float64))
    g = np.hypot(gx, gy)
    edge = (np.abs(T - lvl) <= 0.5 * g) & (g > 1e-9)
    if edge.any():
        edge &= g >= WEAK_EDGE * float(np.median(g[edge]))
    return lvl, gx, gy, g, edge


def _features(T: np.ndarray, lvl: float) -> tuple:
    """The predicted print's features (4-connected parts of T at or above ``lvl``): their
    labels, count, and every pixel's nearest feature (boundary pixels just outside the
    print belong to it)."""
    lab, count = ndimage.label(T >= lvl)
    if count == 0:
        return lab, 0, lab
    _, (iy, ix) = ndimage.distance_transform_edt(lab == 0, return_indices=True)
    return lab, count, lab[iy, ix]


def seen_shares(lab: np.ndarray, count: int, above: np.ndarray) -> np.ndarray:
    """Per feature of ``lab`` (labels 1..``count``), the share of its core that the image
    shows above the level (``above``): the core is the feature's pixels at least half its
    largest distance from its outline (the middle of a line along its length, the middle
    of a dot or block). A feature that printed smaller than predicted (a dot in a lab that
    erodes, 0.48 of its predicted area seen in seed 454132426's lab 7, which left a ring
    and a dot's print with its turn undetermined) still shows its core; a line that
    printed in pieces, or not at all, does not."""
    inside = lab > 0
    dist = cv2.distanceTransform(inside.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    far = np.zeros(count + 1, np.float32)
    np.maximum.at(far, lab[inside], dist[inside])
    return _label_means(np.where(inside & (dist >= 0.5 * far[lab]), lab, 0), count, above)


def _label_means(lab: np.ndarray, count: int, values: np.ndarray) -> np.ndarray:
    """The mean of ``values`` over each label 1..``count`` of ``lab`` (0 where a label has
    no pixel): bincounts, not ``ndimage.mean``, which sorts the labels."""
    lab = lab.ravel()
    sums = np.bincount(lab, weights=values.ravel().astype(np.float64), minlength=count + 1)[1:]
    return sums / np.maximum(np.bincount(lab, minlength=count + 1)[1:], 1)


def size_spread(T: np.ndarray, mode: str, offset_sd=None, scale_sd: float | None = None, edge_sd: float = EDGE_SD,
                image: np.ndarray | None = None, dose_response: np.ndarray | None = None,
                dose_reference: float | None = None, place_dose_sd: float = 0.0) -> float:
    """The pose's spread (px of ``T``'s grid, RMS over the field) when each feature of the
    predicted print ``T`` may be larger or smaller than predicted, more so across one
    direction than another: per feature an edge offset e0 + c2 cos 2t + s2 sin 2t +
    c4 cos 4t + s4 sin 4t (edge normal angle t; the first three as ``edge_shifted``, the
    4t terms let a block's corners round off apart from its sides) of standard deviations
    ``offset_sd`` (grid px; one number, or one each for e0, c2, s2, the 4t terms as c2 and
    s2; None: unknown). ``scale_sd``: the standard deviation of the log scale that the batch
    knows (one magnification, ``refine``'s ``scale_prior``), or None. ``edge_sd``: how far
    (grid px) one boundary pixel's place may be off, as one over EDGE_CORR_PX of edge.

    A geometric model: the predicted print's boundary (T at half its maximum), each
    boundary pixel displaced along its normal by the pose and by its feature's offsets, a
    feature being a 4-connected part of the predicted print. The offsets are marginalised
    (a Schur complement per feature). Without a bound on the offsets, a single block, disc
    or grating printed as one block has a scale that only its size sets, and the spread
    is large however small the image noise; with one, it is about the offset over the
    feature's radius times the field's. Several features fix the scale by where they lie.

    Each feature may also be larger or smaller as a whole, about its own centre (an edge
    displacement proportional to (x - x_k) . n, of the same standard deviation as e0 at
    the feature's RMS radius): what the template predicts worst is how the parts of one
    feature sit relative to each other (a Siemens star's spoke tips against its spoke
    sides, a block's corners against its sides, the ends of the lines of a grating
    printed as one block), so the scale of a print that is one feature rests on its size,
    however its outline is shaped. Boundary pixels where T falls off at less than a
    quarter of the boundary's median slope (a faint ripple crossing the level inside a
    block) are left out: no image shows them.

    Only features that surely print count. One whose predicted peak is below MARGINAL_PEAK
    times the level (a thin line at the edge of curing, predicted as specks along a
    ridge) may print anywhere along it or not at all; with ``image`` (the print's image on
    ``T``'s grid in ``T``'s units, the fit's gain and offset taken out; NaN outside the
    image) one of whose core (``seen_shares``) less than SEEN_SHARE, or of whose pixels
    less than SEEN_AREA, is above the level in the image did not print as predicted.
    Their edges are left out. Counted, they made a print that is one block and such a
    line count as several features whose places fix its scale, while
    the block's size set it (a lines print of seed 1443771177's lab 5, `ok` 2.4 px off
    with a size spread of 1.0 px: 26 predicted specks along its second line).

    ``dose_response``: dT / d ln(dose) on ``T``'s grid (the template's change with the
    print's dose), and ``dose_reference``: how far the dose moves the edges of the batch's
    prints by which ``edge_sd`` was measured (``dose_sensitivity``: no further than that
    for 9 in 10 of them; px per unit of ln dose). A boundary pixel that the dose moves s
    times as far (s > 1) is off s times ``edge_sd``: cells scatter the light unevenly,
    the lamp's field is known only so well, and the end of a line that barely cured
    moves far with a small change of dose. A pose that rests on such edges (where along
    their length lines lie) is known only that well: a lines print of seed 273897816's
    lab 4 was `ok` 1.91 px off along its lines. The reference is not the median edge:
    that failed a print of our own lab's default run 0.29 px off (docs/registration.md).

    ``place_dose_sd``: each feature may also sit off its predicted place as a whole, by
    this times the median over its boundary of how far the dose moves its edges (a
    translation of the feature, marginalised with its offsets; needs ``dose_response``):
    the dose differs from one side of a feature to the other (the lamp's field and the
    cells' scatter, known only so well), which moves the feature's edges on that side
    further than those on the other. The per-pixel weights above do not hold this: a
    feature's place from a long edge is known to the noise's share of a pixel, however far
    the dose moves it. A print of two features then has its scale known only as well as
    their places (a lines print of seed 235706131's lab 7, of which two lines cured, was
    `ok` 1.88 px off in scale, 0.85 %, at a size spread of 0.72 px). The batch measures it
    on its well-placed prints (``feature_places``); 0 leaves it out.
    """
    n = T.shape[0]
    c = (n - 1) / 2
    corners = np.array([[-c, -c], [c, -c], [-c, c], [c, c]]).T
    lvl, gx, gy, g, edge = _boundary(T)
    ys, xs = np.nonzero(edge)
    if len(xs) < 10:
        return float("inf")
    nx, ny = -gx[edge] / g[edge], -gy[edge] / g[edge]  # outward: T falls off
    X, Y = xs - c, ys - c
    if mode == "affine":
        P = np.stack([nx * X, nx * Y, ny * X, ny * Y, nx, ny], 1)
    else:
        P = np.stack([nx * X + ny * Y, ny * X - nx * Y, nx, ny], 1)
    lab, count, near = _features(T, lvl)
    if count == 0:
        return float("inf")
    k = near[ys, xs]
    # features that surely print: a peak of at least MARGINAL_PEAK x the level (any pixel there, counted by
    # label; ndimage.maximum sorts the labels, 50 ms a call on a grating's hundreds of features)
    good = np.bincount(lab[T >= MARGINAL_PEAK * lvl], minlength=count + 1)[1:] > 0
    if image is not None:
        with np.errstate(invalid="ignore"):
            above = image >= lvl
        good &= (seen_shares(lab, count, above) >= SEEN_SHARE) & (_label_means(lab, count, above) >= SEEN_AREA)
    keep = np.concatenate([[False], good])[k]
    if keep.sum() < 10:
        return float("inf")
    nx, ny, X, Y, P, k = nx[keep], ny[keep], X[keep], Y[keep], P[keep], k[keep]
    c2, s2 = nx * nx - ny * ny, 2 * nx * ny
    Q = np.stack([np.ones_like(nx), c2, s2, c2 * c2 - s2 * s2, 2 * c2 * s2], 1)
    v = edge_sd**2 * EDGE_CORR_PX  # variance of one boundary pixel's place (it counts for 1 / EDGE_CORR_PX of one)
    w = np.ones(len(nx))
    moved = None  # px per unit of ln dose, per boundary pixel
    if dose_response is not None and dose_reference is not None and dose_reference > 0:
        # each boundary pixel weighed by 1 / its place's variance, relative to v: the rows
        # of P and Q (and the size column below) scaled by 1 / its sd over edge_sd
        moved = np.abs(dose_response[ys, xs][keep]) / g[ys, xs][keep]
        w = 1.0 / np.maximum(1.0, moved / dose_reference)
        P, Q = P * w[:, None], Q * w[:, None]
    if offset_sd is None:
        prior = np.zeros((6, 6))
    else:
        sd = np.broadcast_to(np.asarray(offset_sd, float), (3,))
        sd = np.concatenate([sd, sd[1:], sd[:1]])  # cos 4t, sin 4t as the directional part; the feature's size as e0
        prior = np.diag(v / np.maximum(sd, 1e-6) ** 2)
    S = P.T @ P
    order = np.argsort(k, kind="stable")
    bounds = np.flatnonzero(np.diff(k[order])) + 1
    for idx in np.split(order, bounds):
        dx, dy = X[idx] - X[idx].mean(), Y[idx] - Y[idx].mean()
        size = w[idx] * (nx[idx] * dx + ny[idx] * dy) / max(float(np.sqrt(np.mean(dx * dx + dy * dy))), 1.0)
        Pk, Qk, prior_k = P[idx], np.column_stack([Q[idx], size]), prior
        place_sd = 0.0 if moved is None else place_dose_sd * float(np.median(moved[idx]))
        if place_sd > 1e-3:  # the feature's own translation, of that spread
            Qk = np.column_stack([Qk, w[idx] * nx[idx], w[idx] * ny[idx]])
            prior_k = np.pad(prior, ((0, 2), (0, 2)))
            prior_k[6:, 6:] = np.eye(2) * v / place_sd**2
        Apq = Pk.T @ Qk
        S -= Apq @ np.linalg.pinv(Qk.T @ Qk + prior_k, rcond=1e-8, hermitian=True) @ Apq.T
    S = 0.5 * (S + S.T)
    if scale_sd is not None:
        a = _log_scale_row(len(S), mode)
        S += v * np.outer(a, a) / scale_sd**2
    S[np.diag_indices_from(S)] += 1e-9 * np.trace(P.T @ P) / len(S)
    return min(_field_rms(np.linalg.inv(S) * v, mode, corners), 1e6)


KERNEL_TAIL = 0.3  # kernel_spread: the tail share added (the template's fit of a batch may miss a third of it)
KERNEL_WIDTH = 1.2  # ... and the factor the core's width is changed by (measured, not used: kernel_spread)


def _kernel_changed(x, which: str) -> np.ndarray:
    """The template numbers ``x`` with the scatter kernel changed in shape: ``tail`` (its
    share KERNEL_TAIL higher, at least 2.5 core widths wide) or ``wider`` (the core's
    width times KERNEL_WIDTH)."""
    xk = np.array(x, dtype=float)
    i_sigma, i_tail, i_width = (PrintTemplate.NAMES.index(n) for n in ("sigma", "tail", "tail_sigma"))
    if which == "tail":
        # a tail the fit hardly has has no width to speak of: 2.5 core widths then
        xk[i_width] = max(xk[i_width], 2.5 * xk[i_sigma]) if xk[i_tail] >= 0.05 else 2.5 * xk[i_sigma]
        xk[i_tail] = min(max(xk[i_tail], 0.0) + KERNEL_TAIL, PrintTemplate.BOUNDS[i_tail][1])
    else:
        xk[i_sigma] *= KERNEL_WIDTH
    return xk


KERNEL_CHANGES = ("tail", "wider")


def kernel_moves(tmpl: PrintTemplate, m: np.ndarray, B: np.ndarray, x, fit: Fit, mode: str,
                 image: np.ndarray | None = None, band: int = 16) -> tuple[float, dict | None]:
    """How far a print's pose moves with the tail of the batch's scatter kernel, and,
    given the print's ``image``, how far its image says the kernel is off in shape.

    For the kernel's tail share up by KERNEL_TAIL (``_kernel_changed``), the pose part
    of one Gauss-Newton step of the print's fit (``refine``'s objective without its Huber
    weights) from its template T to the changed template Tk, on T's window (``_window``):
    the pose (its scale held only where the print's fit held it, ``Fit.scale_held``),
    gain, offset and the print's nuisance numbers (dose, blur, dose gradient, edge
    offsets, brightness slopes) with their default priors (``_prior``; a print refitted
    with the batch's edge offsets had tighter ones, which would move its pose further:
    the move is then, if anything, low), the data weighed by the fit's gain over its
    residual's scale. Returns the
    move (design px, RMS over the field) and, with ``image`` (the print's image on T's
    grid in the image's units, NaN outside it), change -> k for the tail's change and
    the core's (KERNEL_WIDTH wider), fitted together with the same numbers (the scale
    held only where the print's fit held it): the share of each change (1: all of it)
    that the print's residual holds; None without an image. The batch measures these
    shares before its prints are refitted with a held scale (``scale_held`` still false
    then), so with the scale free.

    A change of the kernel's shape moves an edge by how far its cure level sits from
    half the dose: an edge between full dose and nothing hardly moves, one at a grey
    level or on a grey ramp moves far. Where a print's edges all move alike (a block, a
    grating at one grey level), its dose or edge offset takes the change up and the pose
    stays. Where one part of the pose rests on an edge that moves and the edge opposite
    it does not (a grey ramp, whose cut the dose places: the pose along the ramp rests on
    the ramp's bright end alone), the pose moves with the kernel. Without the priors the
    step is ill-posed: on a grey ramp the pose along the ramp trades against the dose and
    the edge offsets, and which way it goes rests on them."""
    q = fit.q
    T, d = print_template(tmpl, B, x, q, derivatives=True)
    top = float(T.max())
    if top <= 0 or not fit.sigma > 0:
        return float("inf"), None
    n = T.shape[0]
    c = (n - 1) / 2
    corners = np.array([[-c, -c], [c, -c], [-c, c], [c, c]]).T
    (r0, r1), (c0, c1) = _window(T, band)  # the window the print can reach
    win = (slice(r0, r1), slice(c0, c1))
    Tw = T[win].astype(np.float64)
    gy, gx = np.gradient(Tw)
    Y, X = np.mgrid[r0:r1, c0:c1].astype(np.float64) - c
    if mode == "affine":
        moves = [(X, 0 * X), (Y, 0 * X), (0 * X, X), (0 * X, Y), (1 + 0 * X, 0 * X), (0 * X, 1 + 0 * X)]
    else:
        moves = [(X, Y), (-Y, X), (1 + 0 * X, 0 * X), (0 * X, 1 + 0 * X)]
    npose = len(moves)
    # in the image's units: gain T + offset; the nuisance numbers' columns, as refine's, times the gain
    columns = [-fit.gain * (gx * ux + gy * uy) for ux, uy in moves] + [Tw, np.ones_like(Tw)]
    columns += [fit.gain * v[win].astype(np.float64) for v in d]
    changed = {}
    for which in KERNEL_CHANGES if image is not None else ("tail",):
        xk = _kernel_changed(x, which)
        changed[which] = fit.gain * (print_template(tmpl, tmpl.exposure(m, xk), xk, q, derivatives=False)[0][win] - Tw)
    _, qs = _prior(x)
    nq = min(len(d), len(qs))

    def solved(cols, hold: bool, valid=None):
        """The normal matrix of ``cols`` (scaled to unit norm) over the window's pixels
        (``valid``: those only), with the priors and the scale held (``hold``), and the
        columns' norms."""
        A = np.stack([v.ravel() if valid is None else v[valid] for v in cols], 1) / fit.sigma
        norm = np.sqrt((A * A).sum(0)) + 1e-12
        A /= norm
        H = A.T @ A
        H[npose + 2 : npose + 2 + nq, npose + 2 : npose + 2 + nq] += np.diag(1.0 / (qs[:nq] * norm[npose + 2 : npose + 2 + nq]) ** 2)
        if hold:  # held: a penalty on the log scale far stiffer than the data, as refine's
            a = _log_scale_row(len(H), mode) / norm
            H += 1e3 * float(np.trace(H)) / float(a @ a) * np.outer(a, a)
        H[np.diag_indices_from(H)] += 1e-9 * float(np.trace(H)) / len(H)
        return A, H, norm

    A, H, norm = solved(columns, fit.scale_held)  # the scale free unless the print's fit held it (kernel_spread)
    z = np.linalg.solve(H, A.T @ changed["tail"].ravel() / fit.sigma) / norm
    out = _field_rms(np.outer(z[:npose], z[:npose]), mode, corners)
    if image is None:
        return out, None
    seen = image[win].astype(np.float64)
    valid = np.isfinite(seen)
    if valid.sum() < len(columns) + 2:
        return out, None
    A, H, norm = solved(columns + [changed["tail"], changed["wider"]], fit.scale_held, valid)
    r = (seen - fit.gain * Tw - fit.offset)[valid] / fit.sigma
    z = np.linalg.solve(H, A.T @ r) / norm
    return out, {k: float(z[-2 + i]) for i, k in enumerate(KERNEL_CHANGES)}


def kernel_spread(move: float, error: dict) -> float:
    """A print's pose spread from the kernel's shape (design px): its move with the tail
    (``kernel_moves``) times the share of that change by which the batch's kernel is off
    (``kernel_error``). The core's width is measured but not counted: the edges' profiles
    fix it, and in a batch of our own lab whose prints were all within 0.5 px of the truth
    its share measured 1.34 (a core 27 % too narrow, consistent over 5 prints), which
    failed a paper trial print 0.16 px off: the residual that a width change best
    explains there is a misfit of another shape, which does not move the pose.

    The move includes the scale where the print's fit left it free (``Fit.scale_held``
    false: no one magnification of the batch held it, and no stated pixel size, which
    holds only some prints, ``stated_scales``). A Siemens star whose spokes do not cure
    to its centre has its scale set by where they stop, which the kernel's shape sets:
    with the scale held in the step, star prints 1.7 to 5.4 px off, their scale 0.8 to
    2.6 % small, were `ok`, most at a spread of 0.02 px or less. The price is that a paper
    trial print of grey cells, whose scale follows a change of tail (2.7 to 5.4 px for a
    share 0.3 higher) without being off, may fail where its batch's prints hold much of
    the change (docs/registration.md, "The kernel's shape and a free scale", measured). A print's
    scale resting on its features' sizes is ``size_spread``'s, measured on the batch's
    sizes."""
    return float(move * error["tail"]) if np.isfinite(move) else float("inf")  # inf x a share of 0 is no number


KERNEL_UNMEASURED = 0.5  # kernel_error: the share assumed where too few prints measure it


def kernel_error(shares: list, min_prints: int, cap: float = 3.0) -> tuple[dict, int]:
    """How far the batch's kernel is off, in shares of each change (``kernel_moves``' k):
    per change the root of the median of k^2 over the shares that the prints whose
    features place their pose measure, over 0.455 (the median of k^2 for a unit normal):
    their standard deviation where they scatter about zero, 1.48 times their value where
    they agree (it errs toward failing), at most ``cap``. With fewer than ``min_prints``
    prints, KERNEL_UNMEASURED: assumed, as a small batch's size error is (``Settings.size_sd``),
    between our own lab's shares (under 0.25) and those of a lab whose template lacks
    most of its tail (0.6 to 0.9). Returns (change -> share, prints)."""
    rows = [s for s in shares if s is not None and all(np.isfinite(v) for v in s.values())]
    if len(rows) < max(min_prints, 1):
        return {k: KERNEL_UNMEASURED for k in KERNEL_CHANGES}, len(rows)
    return {k: float(min(np.sqrt(np.median([r[k] ** 2 for r in rows]) / 0.455), cap)) for k in KERNEL_CHANGES}, len(rows)


FEATURE_MIN_EDGE = 40  # feature_places: boundary pixels a feature needs for its place to count


def feature_places(image: np.ndarray, T: np.ndarray, dose_response: np.ndarray) -> np.ndarray:
    """How far each feature of the predicted print ``T`` sits off its predicted place in
    ``image`` (on ``T``'s grid in ``T``'s units, NaN outside it; ``size_spread``'s), and how
    far the dose moves its edges. Per feature of at least FEATURE_MIN_EDGE boundary pixels
    (features as ``size_spread``'s), the translation t that best moves T's edges onto the
    image's (least squares on the residual image - T against grad T within 3 px of its
    boundary), the median over its boundary of |dT / d ln dose| / |grad T| (px per unit
    of ln dose), and its number of boundary pixels: an array of rows (|t|^2, moved,
    pixels); none where ``T`` has fewer than 3 features (``place_dose_spread``)."""
    lvl, gx, gy, g, edge = _boundary(T)
    _, count, near = _features(T, lvl)
    none = np.zeros((0, 3))
    if count < 3:
        return none
    band = (cv2.dilate(edge.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0) & np.isfinite(image)
    r = np.where(band, image - T, 0.0)
    k = np.where(band, near, 0).ravel()
    n = count + 1
    sxx, sxy, syy = (np.bincount(k, (a * b).ravel(), n) for a, b in ((gx, gx), (gx, gy), (gy, gy)))
    sxr, syr = (np.bincount(k, (a * r).ravel(), n) for a in (gx, gy))
    ke = near[edge]
    nedge = np.bincount(ke, minlength=n)
    moved = np.abs(dose_response[edge]) / g[edge]
    rows = []
    for f in np.flatnonzero(nedge >= FEATURE_MIN_EDGE):
        det = sxx[f] * syy[f] - sxy[f] ** 2
        if det <= 1e-9 * sxx[f] * syy[f]:
            continue
        tx = -(syy[f] * sxr[f] - sxy[f] * syr[f]) / det
        ty = -(sxx[f] * syr[f] - sxy[f] * sxr[f]) / det
        rows.append((tx * tx + ty * ty, float(np.median(moved[ke == f])), nedge[f]))
    return np.array(rows) if len(rows) >= 3 else none


def place_dose_spread(places: list, edge_sd: float) -> tuple[float, int]:
    """``size_spread``'s ``place_dose_sd`` from ``feature_places`` of a batch's well-placed
    prints: c, the standard deviation per axis of a feature's displacement over how far the
    dose moves its edges. Per feature q = (|t|^2 / 2 - 2 v / n) / moved^2 (v = edge_sd^2
    EDGE_CORR_PX: the noise of t per axis is 2 v / n for n boundary pixels, half of them
    across each axis), of which c^2 is the median over ln 2 (|t|^2 / 2 of a Gaussian
    displacement is exponential: one feature that the template misses, a part of a
    partial print that did not cure, does not set it), times the features' count over the
    count less 2 per print (the pose, fitted to the same image, takes 4 of the 2 n numbers
    that the n features of a print give: its shift, rotation and scale). Returns (c, features);
    (0, 0) without any."""
    rows = [p for p in places if len(p)]
    if not rows:
        return 0.0, 0
    v = edge_sd**2 * EDGE_CORR_PX
    q = np.concatenate([(p[:, 0] / 2 - 2 * v / p[:, 2]) / np.maximum(p[:, 1], 1e-6) ** 2 for p in rows])
    dof = len(q) / sum(len(p) - 2 for p in rows)
    return float(np.sqrt(max(float(np.median(q)), 0.0) / np.log(2) * dof)), len(q)


DOSE_QUANTILE = 0.9  # dose_sensitivity: the share of a print's boundary that its dose moves no further


def dose_sensitivity(T: np.ndarray, dose_response: np.ndarray) -> float:
    """How far the edges of the predicted print ``T`` move with its dose: the DOSE_QUANTILE
    quantile over its boundary (T at half its maximum, as ``size_spread``) of
    |dT / d ln(dose)| / |grad T| (grid px per unit of ln dose); NaN where it has no
    boundary."""
    _, _, _, g, edge = _boundary(T)
    if edge.sum() < 10:
        return float("nan")
    return float(np.quantile(np.abs(dose_response[edge]) / g[edge], DOSE_QUANTILE))


def merged_features(T: np.ndarray, m: np.ndarray, fill: float = 1.2, level: float | None = None) -> bool:
    """Whether the predicted print ``T`` joins parts of the padded mask ``m`` (two or more of
    its 4-connected parts) into one feature that is ``fill`` times or more the exposed area
    within it (a fine grating printed as one block, dots run together): the size of such a
    feature is set by the scatter between its parts, which the template predicts worse
    than an edge's erosion. ``T`` may be an image on the template's grid instead, cut at
    ``level`` (default: half its maximum). A checkerboard, whose squares touch at their
    corners, joins its parts at about its exposed area; a grating of lines three times as
    wide as its gaps, printed as one, at 1.33 times."""
    lab, count = ndimage.label(T >= (0.5 * float(T.max()) if level is None else level))
    if count == 0:
        return False
    area = np.bincount(lab.ravel(), minlength=count + 1)[1:]
    exposed = np.bincount(lab.ravel(), weights=(m > 0).ravel(), minlength=count + 1)[1:]
    parts, n = ndimage.label(m > 0)
    # the mask's parts that each feature holds: distinct (feature, part) pairs
    pairs = np.unique(lab.ravel().astype(np.int64) * (n + 1) + parts.ravel())
    pairs = pairs[(pairs // (n + 1) > 0) & (pairs % (n + 1) > 0)]
    held = np.bincount(pairs // (n + 1), minlength=count + 1)[1:]
    return bool(np.any((area > fill * np.maximum(exposed, 1.0)) & (held >= 2)))


TILE_PX = 32  # design px: the tiles over which the pose spread lets template misfit correlate


def _field_rms(Cp: np.ndarray, mode: str, corners: np.ndarray) -> float:
    """RMS over a grid of field points of the displacement d(x) = G(x) p for a pose
    covariance ``Cp``."""
    g = np.linspace(-1, 1, 5) * corners[0, 1] * -1
    X, Y = np.meshgrid(g, g)
    var = 0.0
    for x_, y_ in zip(X.ravel(), Y.ravel()):
        if mode == "affine":
            G = np.array([[x_, y_, 0, 0, 1, 0], [0, 0, x_, y_, 0, 1]])
        else:
            G = np.array([[x_, -y_, 1, 0], [y_, x_, 0, 1]])
        var += np.trace(G @ Cp @ G.T)
    return float(np.sqrt(max(var / X.size, 0.0)))


def _pose_sd(H, norm, npose, J, w, r, sigma, shape, tile, mode, corners, max_lag: int = 12) -> float:
    """Standard deviation of the pose (grid px, RMS over the field) that the print's data
    alone allow, the nuisance numbers marginalised, and the priors left out (so a pose
    that only a prior holds in place, such as the scale of a single block whose edge
    offset is free, shows as undetermined). The larger of two estimates:

    - **model-based**: the pose block of the pseudo-inverse of the data's normal matrix,
      inflated by the residual's integrated auto-correlation up to ``max_lag`` px (the
      number of pixels that act as one), measured on the weighted residual itself;
    - **cluster-robust** (the sandwich C = H^-1 (sum_t g_t g_t^T) H^-1 with g_t the
      gradient of the misfit from tile t of ``tile`` grid px): it measures how hard the
      parts of the print pull against each other. A template that misplaces the edges of
      a print (a block whose size it does not predict, parts of a partial print that cured
      elsewhere) fits every tile badly in its own direction and the pose is where these
      pulls balance; the sandwich sees the pulls, the noise-based estimate does not.
      With few tiles it is low, hence the other estimate as a floor.
    """
    if H is None:
        return float("inf")
    Hi = np.linalg.pinv(H, rcond=1e-10, hermitian=True)
    C = Hi / np.outer(norm, norm)
    rw = (r * np.sqrt(w)).reshape(shape)
    N = cv2.getOptimalDFTSize(max(rw.shape) + 2 * max_lag)  # padding enough for lags up to max_lag
    F = np.fft.rfft2(rw - rw.mean(), s=(N, N))
    ac = np.fft.fftshift(np.fft.irfft2(F * np.conj(F), s=(N, N)))
    o = N // 2
    ac = ac[o - max_lag : o + max_lag + 1, o - max_lag : o + max_lag + 1]
    kappa = float(np.clip(ac.sum() / max(ac[max_lag, max_lag], 1e-30), 1.0, (2 * max_lag + 1) ** 2))
    model = _field_rms(C[:npose, :npose] * kappa, mode, corners)
    h, wd = shape
    ty, tx = h // tile, wd // tile
    k = J.shape[0]
    wr = (w * r / sigma**2).astype(J.dtype)
    g = (J * wr[None, :]).reshape(k, h, wd)[:, : ty * tile, : tx * tile].reshape(k, ty, tile, tx, tile).sum(axis=(2, 4))
    g = g.reshape(k, -1).T
    g = g[np.abs(g[:, :npose]).sum(1) > 0]  # tiles where the print has edges
    if len(g) < 2:
        return model
    meat = (g.T @ g).astype(np.float64) * len(g) / (len(g) - 1)
    Cs = (Hi @ meat @ Hi) / np.outer(norm, norm)
    return max(model, _field_rms(Cs[:npose, :npose], mode, corners))


# ------------------------------------------------------------------ 3. alternatives


def self_similar_moves(T: np.ndarray, max_shift: int = 64, rotation_span: float = 30.0, min_corr: float = 0.5,
                       count: int = 4, shifts: bool = True, dip: float = 0.0, factor: int = 4) -> list[np.ndarray]:
    """Moves S (3x3, grid -> grid) under which the predicted print T nearly maps onto itself.

    Shifts: local maxima of the normalised auto-correlation of T, high-passed (periods up
    to about 30 px), within ``max_shift`` px.
    Rotations: for each angle, the peak of the cross-correlation of T with T rotated
    about the grid centre (the shift at the peak turns it into a rotation about the
    print's own centre of symmetry, a star's hub). Only moves whose correlation is at
    least ``min_corr`` are kept, the strongest ``count`` of each kind; ``shifts=False``:
    rotations only; a rotation only when the correlation falls by ``dip`` or more between
    no turn and it (a star's spokes over its gaps half-way; a block turned a little
    correlates well at every angle on the way). The rotations are sought at 1 /
    ``factor`` of the resolution (a fine star's spokes merge at a quarter).
    """
    n = T.shape[0]
    moves = []
    if shifts:
        # high-passed: a weak periodic ripple on a large block is a local maximum of the
        # ripple's auto-correlation, not of the block's (which falls off smoothly)
        Tf = T.astype(np.float32)
        z = _zn((Tf - cv2.GaussianBlur(Tf, (0, 0), 12.0)).astype(np.float64))
        N = cv2.getOptimalDFTSize(n + max_shift)
        F = np.fft.rfft2(z, s=(N, N))
        ac = np.fft.fftshift(np.fft.irfft2(F * np.conj(F), s=(N, N)))
        o = N // 2
        win = ac[o - max_shift : o + max_shift + 1, o - max_shift : o + max_shift + 1]
        peaks = (win == ndimage.maximum_filter(win, size=5)) & (win >= min_corr)
        ys, xs = np.nonzero(peaks)
        cand = sorted(((float(win[y, x]), x - max_shift, y - max_shift) for y, x in zip(ys, xs)
                       if np.hypot(x - max_shift, y - max_shift) >= 2.5), reverse=True)
        for v, dx, dy in cand[:count]:
            moves.append(np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]]))
    # rotations, at 1 / ``factor`` of the resolution (quarter: a spoke is wide near a star's rim)
    q = factor
    Tq = cv2.resize(T, None, fx=1 / q, fy=1 / q, interpolation=cv2.INTER_AREA)
    nq = Tq.shape[0]
    Nq = cv2.getOptimalDFTSize(2 * nq)
    # single precision (scipy.fft keeps it; numpy's FFT computes in double): 1.7 times
    # faster, the correlations within 3e-7 of double's and the same peaks (37 benchmark masks)
    Fq = np.conj(sfft.rfft2(_zn(Tq.astype(np.float64)).astype(np.float32), s=(Nq, Nq)))
    cq = ((nq - 1) / 2,) * 2
    prof = []
    for phi in np.arange(-rotation_span, rotation_span + 1e-9, 1.0):
        R = similarity(phi, 1.0, cq, cq)
        Tr = cv2.warpAffine(Tq, R, (nq, nq), flags=cv2.INTER_LINEAR)
        cc = sfft.irfft2(sfft.rfft2(_zn(Tr.astype(np.float64)).astype(np.float32), s=(Nq, Nq)) * Fq, s=(Nq, Nq))
        k = int(np.argmax(cc))
        dy, dx = divmod(k, Nq)
        dy = dy - Nq if dy > Nq // 2 else dy
        dx = dx - Nq if dx > Nq // 2 else dx
        prof.append((phi, float(cc.flat[k]), dx, dy))
    vals = np.array([p[1] for p in prof])
    rot = []
    for i in range(1, len(prof) - 1):
        phi, v, dx, dy = prof[i]
        i0 = len(prof) // 2  # no turn
        between = vals[min(i, i0) : max(i, i0) + 1]
        if abs(phi) >= 3.0 and v >= min_corr and v >= vals[i - 1] and v >= vals[i + 1] and v - between.min() >= dip:
            rot.append((v, phi, dx, dy))
    c = (n - 1) / 2
    for v, phi, dx, dy in sorted(rot, reverse=True)[:count]:
        # T(R x + d) ~ T(x) with R about the grid centre; the inverse move maps T onto itself
        R = h3(similarity(phi, 1.0, (c, c), (c + q * dx, c + q * dy)))
        moves.append(np.linalg.inv(R))
    return moves


# ---------------------------------------------------------------------- 4. evidence


def predicted_image(fit: Fit, T: np.ndarray, image_shape, factor: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The image that a fit predicts (gain T + offset; offset off the print), and the
    footprint of its grid in the image. ``T`` is on the grid subsampled by ``factor``."""
    H, W = image_shape
    Ms = (h3(fit.M) @ _grid_to_full(factor))[:2]
    P = cv2.warpAffine(T, Ms, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    foot = cv2.warpAffine(np.ones_like(T), Ms, (W, H), flags=cv2.INTER_NEAREST, borderValue=0.0) > 0
    return fit.gain * P + fit.offset, foot


def print_level(fit: Fit, T: np.ndarray) -> float:
    """The image level of a fit's cured print above its offset: gain times the median of
    its template over the template's brighter half (a sparse print's dots, a dense one's
    solid). The template's 99th percentile, used before, is the faint halo of a print
    covering under 1 % of the field."""
    top = float(T.max())
    return abs(fit.gain) * float(np.median(T[T >= 0.5 * top])) if top > 0 else 0.0


def evidence(img: np.ndarray, a: tuple, b: tuple, block: int = 8, clip: float = 4.0, factor: int = 1) -> float:
    """How strongly the image prefers fit ``a`` over fit ``b`` (z >> 0: a; z << 0: b).

    ``a`` and ``b`` are (Fit, full-resolution template of that fit). Both are compared
    on the same image pixels (the union of their footprints, where their predictions
    differ), with squared residuals clipped so that no single speck decides. Returns
    z = sum(e_b) / sqrt(sum(e_b^2)) over blocks of ``block`` px (see the module doc).
    """
    Pa, fa = predicted_image(a[0], a[1], img.shape, factor)
    Pb, fb = predicted_image(b[0], b[1], img.shape, factor)
    # only where the two predictions differ: elsewhere both fit the same pixels alike and
    # would add their noise to the denominator alone
    # the print's amplitude (``print_level``) from the weaker of the two fits, so that a
    # collapsed rival (its template nearly flat) does not raise the bar above every pixel
    amp = min(print_level(*a), print_level(*b))
    differ = np.abs(Pa - Pb) > 0.1 * max(amp, 1e-9)
    region = (fa | fb) & np.isfinite(img) & differ
    # clipped at half the print's amplitude (and no less than ``clip`` noise sigmas): a speck
    # cannot decide, but an edge one fit places and the other misses still counts; clipped
    # at the noise alone, both fits would be clipped alike wherever they differ
    s2 = max(0.5 * amp, clip * max(a[0].sigma, b[0].sigma)) ** 2
    ra = np.minimum((img - Pa) ** 2, s2)
    rb = np.minimum((img - Pb) ** 2, s2)
    e = np.where(region, rb - ra, 0.0)
    H, W = e.shape
    Hb, Wb = H // block * block, W // block * block
    eb = e[:Hb, :Wb].reshape(Hb // block, block, Wb // block, block).sum(axis=(1, 3)).ravel()
    den = float(np.sqrt((eb * eb).sum()))
    return float(eb.sum() / den) if den > 0 else 0.0


def contradicted(img: np.ndarray, a: tuple, b: tuple, min_px: int, widen: int = 3) -> tuple[float, float]:
    """The largest part of the print (image px) where the image sides with fit ``a``
    against fit ``b`` beyond any misfit of the template, and the same for ``b`` against
    ``a``. A part for ``a``: polymer that ``a`` predicts cured and ``b`` predicts nowhere
    near (``widen`` px around what it predicts), or a part that ``b`` predicts cured well
    inside (at three quarters of the print's level) where the image shows no polymer and
    ``a`` predicts none. Parts under ``min_px`` do not count; in an image whose fitted
    noise is above an eighth of the print's level no part does.

    ``evidence`` weighs blocks of 8 px, so that a speck cannot decide; a print of a few
    small dots spans so few blocks that no rival reaches a z of 4 against it, however
    clearly the image shows a dot where the rival predicts none. A dot the size of the
    print's features that one pose explains and the other cannot (light cures no polymer
    where the scattered dose is nowhere near the threshold) is such a contradiction.
    """
    Pa, fa = predicted_image(a[0], a[1], img.shape)
    Pb, fb = predicted_image(b[0], b[1], img.shape)
    amp = min(print_level(*a), print_level(*b))
    if not amp > 0 or max(a[0].sigma, b[0].sigma) > 0.125 * amp:  # a noisy image: no part is clear
        return 0.0, 0.0
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * widen + 1, 2 * widen + 1))
    opening = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    off = 0.5 * (a[0].offset + b[0].offset)
    polymer = np.nan_to_num(img, nan=off) - off >= 0.5 * amp
    bare = np.nan_to_num(img, nan=off + amp) - off < 0.25 * amp
    both = fa & fb

    def near(P, f):  # where a fit predicts its print at a quarter of the print's level or more, widened
        return cv2.dilate(((P - f.offset >= 0.25 * amp) & np.isfinite(img)).astype(np.uint8), kernel) > 0

    def inner(P, f):  # where a fit predicts its print well inside: three quarters of its level, eroded
        return cv2.erode((P - f.offset >= 0.75 * amp).astype(np.uint8), kernel) > 0

    def largest(parts):
        parts = cv2.morphologyEx((parts & both).astype(np.uint8), cv2.MORPH_OPEN, opening)
        n, _, stats, _ = cv2.connectedComponentsWithStats(parts, connectivity=8)
        areas = stats[1:, cv2.CC_STAT_AREA]
        big = areas[areas >= min_px]
        return float(big.max()) if len(big) else 0.0

    near_a, near_b = near(Pa, a[0]), near(Pb, b[0])
    for_a = (polymer & near_a & ~near_b) | (bare & inner(Pb, b[0]) & ~near_a)
    for_b = (polymer & near_b & ~near_a) | (bare & inner(Pa, a[0]) & ~near_b)
    return largest(for_a), largest(for_b)


# ---------------------------------------------------------------------- conversions


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


def to_design(M: np.ndarray, margin: int) -> np.ndarray:
    """Template (padded) -> image matrix to design -> image matrix."""
    Md = M.copy()
    Md[:, 2] = M[:, :2] @ np.array([margin, margin], float) + M[:, 2]
    return Md


def transform_rms_px(M_est: np.ndarray, M_true: np.ndarray, design_px: int, step: int = 8) -> float:
    """RMS distance (design pixels) between where two design->image maps send the design field."""
    g = np.arange(0, design_px, step, dtype=float)
    X, Y = np.meshgrid(g, g)
    P = np.vstack([X.ravel(), Y.ravel()])
    d = (M_est[:, :2] - M_true[:, :2]) @ P + (M_est[:, 2:3] - M_true[:, 2:3])
    s = np.sqrt(abs(np.linalg.det(M_true[:, :2])))
    return float(np.sqrt(np.mean(np.sum(d * d, axis=0))) / s)
