"""What the print of a mask looks like under the microscope: the registration's template.

A blurred mask is a poor template. Prints of grey cells, features under a weaker part
of the field, thin lines and dim corners that do not cure at all, and prints that are
larger or smaller than their mask all differ from the mask, and a pose fitted to a
template of the wrong size trades the size error for scale and shift (1 to 6 px over
the field in our measurements). The print template predicts which parts of a mask cure:

    exposure   E = m (1 + fx X + fy Y + fxx X^2 + fxy X Y + fyy Y^2)
    scattered  B = (1 - tail) G_sigma * E + tail G_tail_sigma * E
    cured      R = 1 - exp(-max(dose B - gel, 0) / k)
    imaged     T = (1 - haze) G_blur * R + haze G_haze_sigma * R

The batch shares the printer's numbers (``NAMES``), fitted once over its prints, so
that they cannot trade off against any one print's pose; each print has its own
``dose`` (lamp and exposure vary between prints), fitted together with its pose by
``pose.refine``. This is a registration nuisance model, not the calibrated printer
model: it only has to put the print's edges where the image has them.
"""

from __future__ import annotations

import copy

import cv2
import numpy as np


def gaussian(a: np.ndarray, sigma: float, border: int = cv2.BORDER_REFLECT_101) -> np.ndarray:
    """G_sigma * a, with OpenCV's ``border`` (reflected by default; ``cv2.BORDER_CONSTANT``:
    zero outside ``a``). A wide kernel (sigma above 6 px) is applied on a grid reduced by
    d = sigma // 3: a box average down, the Gaussian of the remaining width, linear
    interpolation up (their variances, d^2/12 and d^2/6, taken out of sigma^2). Off by less
    than 1 % of the peak from the direct filter, and 20 times faster for the haze and the
    scattering tail, which are 15 to 40 px wide. The reduced grid's cells start at a's
    origin (``reduction``)."""
    if sigma <= 6.0:
        return cv2.GaussianBlur(a, (0, 0), sigma, borderType=border)
    d = reduction(sigma)
    h, w = a.shape
    H, W = -(-h // d) * d, -(-w // d) * d
    p = cv2.copyMakeBorder(a, 0, H - h, 0, W - w, border, value=0) if (H, W) != (h, w) else a
    small = cv2.resize(p, (W // d, H // d), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), np.sqrt(sigma**2 - d * d / 4.0) / d, borderType=border)
    return cv2.resize(small, (W, H), interpolation=cv2.INTER_LINEAR)[:h, :w]


def reduction(sigma: float) -> int:
    """The reduction d of ``gaussian``'s grid for a kernel of ``sigma`` px (1: none)."""
    return int(sigma // 3) if sigma > 6.0 else 1


class PrintTemplate:
    """The print template on the padded design grid, optionally subsampled by ``factor``."""

    NAMES = ("sigma", "gel", "k", "fx", "fy", "fxx", "fxy", "fyy", "tail", "tail_sigma", "blur", "haze", "haze_sigma")
    START = (4.0, 0.3, 0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.1, 15.0, 1.0, 0.05, 30.0)
    # Powell works on these scales (a unit step is a sensible first move for each)
    STEP = (1.0, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 5.0, 0.5, 0.03, 10.0)

    def __init__(self, design_px: int, margin: int, factor: int = 1):
        self.margin, self.f, self.design_px = margin, factor, design_px
        n = (design_px + 2 * margin) // factor
        self.shape = (n, n)
        # pixel centres: x_full = f x_small + (f - 1) / 2; X, Y in [-1, 1] over the design region
        ax = ((np.arange(n) * factor + (factor - 1) / 2) - (design_px + 2 * margin - 1) / 2) / ((design_px - 1) / 2)
        self.X, self.Y = np.meshgrid(ax.astype(np.float32), ax.astype(np.float32))

    def padded(self, mask: np.ndarray) -> np.ndarray:
        m = np.pad(mask.astype(np.float32) / 255.0, self.margin)
        if self.f > 1:
            m = cv2.resize(m, self.shape[::-1], interpolation=cv2.INTER_AREA)
        return m

    def exposure(self, m: np.ndarray, x) -> np.ndarray:
        """The scattered dose B (before the cure), for a padded mask ``m``."""
        sigma, _, _, fx, fy, fxx, fxy, fyy, tail, tail_sigma = (float(v) for v in x[:10])
        X, Y, f = self.X, self.Y, self.f
        e = m * (1 + fx * X + fy * Y + fxx * X * X + fxy * X * Y + fyy * Y * Y)
        b = cv2.GaussianBlur(e, (0, 0), max(sigma, 0.3) / f)
        tail = min(max(tail, 0.0), 0.9)
        if tail > 0:
            b = (1 - tail) * b + tail * gaussian(e, max(tail_sigma, 1.0) / f)
        return b

    def cure(self, B: np.ndarray, x, dose=1.0, blur: float | None = None):
        """The imaged print T for the scattered dose B (``dose`` a number or a map).

        ``blur`` (design px) overrides the batch's microscope blur: focus varies by image."""
        blur = max(float(x[10]) if blur is None else blur, 0.3)
        _, e, _ = self.cured(B, x, dose)
        return self.image(1.0 - e, x, blur)

    @staticmethod
    def cured(B: np.ndarray, x, dose):
        """The cure's dose above the gel point u, its exp(-u / k) and k."""
        gel, k = float(x[1]), max(float(x[2]), 1e-3)
        u = np.maximum(dose * B - gel, 0.0)
        return u, np.exp(-u / k), k

    def image(self, R: np.ndarray, x, blur: float) -> np.ndarray:
        """The microscope: a focus blur and a wide haze (out-of-focus light of a widefield
        image of a thick gel), a share ``haze`` of the light spread over ``haze_sigma``."""
        R = R.astype(np.float32)
        return self.hazed(R, x, self.focus(R, blur))

    def hazed(self, R: np.ndarray, x, F: np.ndarray) -> np.ndarray:
        """The image of R from its focus-blurred image F: the haze's share of the light
        spread over its width."""
        haze = self.haze(x)
        return (1 - haze) * F + haze * gaussian(R, self.haze_sigma(x), cv2.BORDER_CONSTANT) if haze > 0 else F

    def focus(self, R: np.ndarray, blur: float) -> np.ndarray:
        """The focus blur alone (``blur`` in design px)."""
        return cv2.GaussianBlur(R, (0, 0), max(blur, 0.3) / self.f, borderType=cv2.BORDER_CONSTANT)

    def haze(self, x) -> float:
        """The haze's share of the light (0 to 0.5)."""
        return min(max(float(x[11]), 0.0), 0.5)

    def haze_sigma(self, x) -> float:
        """The haze's width on this template's grid."""
        return max(float(x[12]), 2.0) / self.f

    def crop(self, rows: tuple, cols: tuple) -> "PrintTemplate":
        """The same template on the part (start, stop) ``rows`` x ``cols`` of its grid, for a
        scattered dose cut to that part. The microscope images a cured print with zero
        light outside the grid (no mask, no print there), so a crop holding every pixel a
        print can cure at, whose start is a multiple of the haze's reduction
        (``reduction``), images it as the whole grid does."""
        sub = copy.copy(self)
        sub.X, sub.Y = self.X[rows[0]:rows[1], cols[0]:cols[1]], self.Y[rows[0]:rows[1], cols[0]:cols[1]]
        sub.shape = sub.X.shape
        return sub

    def cure_jacobian(self, B: np.ndarray, x, dose, modulations, blur: float, blur_step: float):
        """T for a dose map ``dose`` (scalar or array), its derivatives along each of
        ``modulations`` (d dose / d theta maps): dT/dtheta = G_blur * (exp(-u/k) B / k dD/dtheta),
        and along the blur, a forward difference over ``blur_step`` (the haze, which does
        not depend on the blur, drops out of it)."""
        u, e, k = self.cured(B, x, dose)
        R = (1.0 - e).astype(np.float32)
        F = self.focus(R, blur)
        T = self.hazed(R, x, F)
        dT_blur = (1 - self.haze(x)) * (self.focus(R, blur + blur_step) - F) / blur_step
        base = np.where(u > 0, e * B / k, 0.0)
        return T, [self.image(base * mod, x, blur) for mod in modulations], dT_blur

    def __call__(self, m: np.ndarray, x, dose: float = 1.0, blur: float | None = None) -> np.ndarray:
        return self.cure(self.exposure(m, x), x, dose, blur=blur)


def blurred_mask(mask: np.ndarray, sigma: float, margin: int) -> np.ndarray:
    """The simplest template (the mask blurred by a few pixels), for the first poses."""
    t = np.pad(mask.astype(np.float32) / 255.0, margin)
    return cv2.GaussianBlur(t, (0, 0), sigma)


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    """Normalised cross-correlation over the pixels where both are finite."""
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 10:
        return 0.0
    x, y = a[ok] - a[ok].mean(), b[ok] - b[ok].mean()
    return float((x * y).sum() / (np.sqrt((x * x).sum() * (y * y).sum()) + 1e-12))


def fit_template(tmpl: PrintTemplate, pairs: list, x0, max_evals: int = 600) -> tuple[np.ndarray, float]:
    """The batch's template numbers: maximum mean NCC over prints (scipy's Powell).

    ``pairs``: (padded mask, image warped into padded design coordinates, the print's
    dose), on ``tmpl``'s grid. Powell, because the cure's kink makes the objective only
    piecewise smooth and the evaluation is cheap at quarter resolution.
    """
    from scipy.optimize import minimize

    step = np.asarray(PrintTemplate.STEP)

    def cost(z):
        x = z * step
        return -float(np.mean([ncc(reg, tmpl(m, x, d)) for m, reg, d in pairs]))

    res = minimize(cost, np.asarray(x0, float) / step, method="Powell",
                   options=dict(maxfev=max_evals, xtol=1e-3, ftol=1e-5))
    return res.x * step, -float(res.fun)
