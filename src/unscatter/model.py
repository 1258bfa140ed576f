"""The printer simulator: Guan et al. 2022, Eq. 1, as one batched PyTorch model.

    P = Threshold_T( Gauss_sigma( ReLU(c1 X^2 + c2 Y^2 + c3 X + c4 Y + c0) * M ) )   # Guan et al. 2022, Eq. 1

Conventions (the virtual lab uses the same ones):

- ``M = mask / 255`` in [0, 1]; 255 is 100 % dose.
- X runs along the mask's columns, Y along its rows; both are normalised to [-1, 1] over
  the pixel centres of the design region (the mask), so X = -1 is the centre of the
  first column and X = +1 the centre of the last.
- ``sigma_px`` is the standard deviation of the scattering kernel in design (DMD)
  pixels; the kernel is the sampled Gaussian normalised to sum 1.
- The design region is all the light there is: the exposure is zero outside the mask,
  and the convolution is linear (zero padded by at least 4 sigma on each side), so light
  never wraps around from one border to the opposite one.
- Gauge: Eq. 1 is unchanged under (c0..c4, T) -> (k c0..k c4, k T), so the seven
  parameters are not all identifiable. By default c0 is fixed to 1: the field is
  relative to its value at the centre, and T is the threshold dose in units of the
  full-grey dose at the field centre (over a large area). c0 can be freed (the paper's
  seven-parameter fit) with ``default_params(free_c0=True)``.

The model is a list of components, each contributing named parameters with bounds:

- field terms (summed, then the ReLU):      ``QuadraticField`` (Eq. 1)
- dose response of the grey level:          ``LinearDose`` (Eq. 1: the mask multiplies)
- kernel terms (summed in Fourier space, weighted, normalised): ``GaussianKernel``
- the print stage (dose -> print):          ``Threshold`` (hard, or a sigmoid with a
  temperature for gradients)

- dose terms after the kernel (optional):    ``EdgeOffset``

Effects beyond Eq. 1 (``EFFECTS``: heavy_tail, anisotropy, dose_nonlinearity,
illumination_field, edge_offset) are components added to the list or replacing one;
a model with effects is named ``"eq1+heavy_tail+edge_offset"`` (``get_model``,
``model_with_effects``, ``extend_params``) and its params.yaml round-trips like Eq. 1's.
``register_model`` names other combinations. Multi-layer (3-D) prints: ``layer_dose`` and
``layer_prints`` stack layer masks with depth attenuation and depth-growing scatter
(``DEPTH_PARAMS``); one layer is the 2-D model exactly. Everything that simulates a print
(calibration, augmentation, mask optimisation, benchmarks) goes through this module.
"""

from __future__ import annotations

import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

EQUATION = "P = Threshold_T(Gauss_sigma(ReLU(c1 X^2 + c2 Y^2 + c3 X + c4 Y + c0) * M))"
COORDINATES = (
    "X along mask columns, Y along mask rows, both normalised to [-1, 1] over the pixel "
    "centres of the design region; M = mask / 255; sigma_px in design (DMD) pixels"
)
GAUGE_FIXED = (
    "Eq. 1 is invariant under (c0..c4, T) -> (k c0..k c4, k T). c0 is fixed to 1, so the "
    "field is relative to the field centre and T is the threshold dose in units of the "
    "full-grey dose at the field centre."
)
GAUGE_FREE = (
    "Eq. 1 is invariant under (c0..c4, T) -> (k c0..k c4, k T). c0 is free here (the "
    "paper's seven-parameter fit): the values are one point on a line of equivalent fits; "
    "divide c and T by c0 to compare them."
)

# --------------------------------------------------------------------------- devices


def default_device() -> torch.device:
    """The GPU when there is one; everything also runs on the CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def keep_freed_memory() -> bool:
    """Let this process keep the memory it frees, for its next temporaries (glibc only).

    Each evaluation of a fit on the CPU allocates and frees tensors of a few MB (spectra,
    their products and gradients). By default glibc serves an allocation above its mmap
    threshold (128 KB at first) with fresh pages and returns freed heap memory to the
    system past its trim threshold, so every evaluation faults its temporaries' pages in
    again, which costs more than the arithmetic on them. Raising the mmap threshold to
    32 MB (its largest) and the trim threshold to 1 GB (``mallopt``) keeps them: the
    diagnosis's evaluation with its gradient (24 prints at every 4th pixel, one torch
    thread) took 47 ms before and 28 ms after, at every 2nd pixel 204 and 136 ms. The
    process's resident memory then stays near its peak instead of falling after each
    evaluation. The numbers computed do not change.

    Called by the stages that fit (calibration, diagnosis) and their worker processes;
    nothing happens off glibc, or with the environment variable UNSCATTER_MALLOC=default.
    Returns whether it took effect."""
    global _HEAP_KEPT
    if _HEAP_KEPT:
        return True
    if os.environ.get("UNSCATTER_MALLOC", "").lower() == "default" or not sys.platform.startswith("linux"):
        return False
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
        M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # malloc.h
        _HEAP_KEPT = bool(libc.mallopt(M_MMAP_THRESHOLD, 32 << 20)) and bool(libc.mallopt(M_TRIM_THRESHOLD, 1 << 30))
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        _HEAP_KEPT = False
    return _HEAP_KEPT


_HEAP_KEPT = False

DTYPE = torch.float32


# ------------------------------------------------------------------------ parameters


@dataclass(frozen=True)
class ParamSpec:
    """One named model parameter with its default, search bounds and meaning."""

    name: str
    default: float
    bounds: tuple[float, float]
    unit: str
    doc: str
    # the model repeats itself over this change of the parameter (an angle); where the
    # bounds span exactly one period the search wraps across them instead of stopping
    # there (``periods``)
    period: float | None = None


Theta = dict  # parameter name -> tensor of shape (P,): P parameter sets at once


class Component:
    """A piece of the printer model that contributes parameters.

    ``stage`` is one of "field", "response", "kernel", "dose" (after the kernel), "threshold".
    """

    stage: str = ""
    name: str = ""
    params: tuple[ParamSpec, ...] = ()


class FieldTerm(Component):
    """A term of the illumination field (summed over terms before the ReLU)."""

    stage = "field"

    def field(self, X: torch.Tensor, Y: torch.Tensor, theta: Theta) -> torch.Tensor:
        """(P, H, W) contribution for coordinate rows X (1, W) and columns Y (H, 1)."""
        raise NotImplementedError

    def basis(self, X: torch.Tensor, Y: torch.Tensor) -> dict | None:
        """If the term is linear in its parameters: name -> (H, W) map; else None."""
        return None


class QuadraticField(FieldTerm):
    """Eq. 1's basic light absorption matrix c1 X^2 + c2 Y^2 + c3 X + c4 Y + c0."""

    name = "quadratic_field"
    params = (
        ParamSpec("c0", 1.0, (0.2, 2.0), "relative dose", "field at the centre (fixed to 1 by default: the gauge)"),
        # +-0.25 each keeps the field >= 0 over the design region (with c0 = 1): a lamp
        # field that vanishes inside the region is not plausible. Wider bounds work too
        # (the ReLU then acts), at a cost in speed.
        ParamSpec("c1", 0.0, (-0.25, 0.25), "relative dose", "coefficient of X^2"),
        ParamSpec("c2", 0.0, (-0.25, 0.25), "relative dose", "coefficient of Y^2"),
        ParamSpec("c3", 0.0, (-0.25, 0.25), "relative dose", "coefficient of X"),
        ParamSpec("c4", 0.0, (-0.25, 0.25), "relative dose", "coefficient of Y"),
    )

    def basis(self, X, Y):
        H, W = Y.shape[0], X.shape[1]
        one = torch.ones(H, W, dtype=X.dtype, device=X.device)
        return {"c0": one, "c1": (X**2).expand(H, W), "c2": (Y**2).expand(H, W), "c3": X.expand(H, W), "c4": Y.expand(H, W)}

    def field(self, X, Y, theta):
        b = self.basis(X, Y)
        return sum(theta[k][:, None, None] * v for k, v in b.items())


class DoseResponse(Component):
    """Grey level -> relative dose delivered by the DMD (before the field multiplies)."""

    stage = "response"

    def apply(self, M: torch.Tensor, theta: Theta) -> torch.Tensor:
        """(B, H, W) for a response without parameters, else (P, B, H, W)."""
        raise NotImplementedError

    def expansion(self):
        """For a response with parameters: ([phi_j(M) -> (B, H, W)], a(theta) -> (P, J)) such
        that response = sum_j a_j phi_j(M) (to float precision), or None. It lets
        ``FixedMasks`` keep precomputed spectra."""
        return None


class LinearDose(DoseResponse):
    """Eq. 1: the dose is proportional to the grey level, M = mask / 255."""

    name = "linear_dose"

    def apply(self, M, theta):
        return M


class KernelTerm(Component):
    """A scattering kernel term, given by its transfer function (normalised to 1 at f = 0).

    The model's kernel is sum_i w_i K_i / sum_i w_i, so adding a term keeps the total
    light constant.
    """

    stage = "kernel"

    def weight(self, theta: Theta) -> torch.Tensor:
        """(P,) relative weight of this term."""
        return torch.ones_like(next(iter(theta.values())))

    def transfer(self, fy: torch.Tensor, fx: torch.Tensor, theta: Theta) -> torch.Tensor:
        """(P, len(fy), len(fx)) for frequencies in cycles per design pixel."""
        raise NotImplementedError

    def support_px(self, values: dict) -> float:
        """Radius (design pixels) beyond which the kernel is negligible (pad by this)."""
        raise NotImplementedError


def sampled_gaussian_transfer(f: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """DFT of the sampled 1-D Gaussian exp(-n^2 / 2 sigma^2), normalised to sum 1.

    ``f``: (N,) frequencies in cycles per sample (design pixel); ``sigma``: (P,) in
    samples. Returns (P, N). By Poisson summation this is the periodised continuous transfer function;
    for narrow kernels the direct sum over taps converges faster. Both are exact to
    float precision in their ranges, differentiable in sigma, and match
    scipy.ndimage.gaussian_filter and the lab's discrete kernel.
    """
    s = sigma.clamp_min(1e-3)[:, None]
    f = f[None, :]
    k = torch.arange(-3, 4, dtype=f.dtype, device=f.device)[:, None, None]
    a = 2 * math.pi**2 * s[None] ** 2
    wide = torch.exp(-a * (f[None] + k) ** 2).sum(0) / torch.exp(-a * k**2).sum(0)
    n = torch.arange(-4, 5, dtype=f.dtype, device=f.device)[:, None, None]
    taps = torch.exp(-(n**2) / (2 * s[None] ** 2))
    narrow = (taps * torch.cos(2 * math.pi * f[None] * n)).sum(0) / taps.sum(0)
    return torch.where(s >= 0.5, wide, narrow)


class GaussianKernel(KernelTerm):
    """Eq. 1's isotropic Gaussian scattering kernel Gauss_sigma."""

    name = "gaussian_kernel"
    params = (ParamSpec("sigma_px", 3.0, (0.25, 12.0), "design pixels", "standard deviation of the scattering kernel"),)

    def transfer(self, fy, fx, theta):
        sig = theta["sigma_px"]
        return sampled_gaussian_transfer(fy, sig)[:, :, None] * sampled_gaussian_transfer(fx, sig)[:, None, :]

    def support_px(self, values):
        return 4.0 * float(values["sigma_px"])


class Threshold(Component):
    """Eq. 1's Threshold_T: cured where the absorbed dose reaches T.

    The smooth variant sigmoid((D - T) / (temperature * T)) takes its temperature as a
    fraction of T, so it does not depend on the gauge; it tends to the hard threshold
    as the temperature goes to 0.
    """

    stage = "threshold"
    name = "threshold"
    params = (ParamSpec("T", 0.5, (0.05, 1.5), "relative dose", "cure threshold of the absorbed dose"),)

    def apply(self, dose: torch.Tensor, theta: Theta, temperature: float | None) -> torch.Tensor:
        T = theta["T"].reshape(-1, *([1] * (dose.dim() - 1)))
        if temperature is None:
            return dose >= T
        return torch.sigmoid((dose - T) / (temperature * T))


class DoseTerm(Component):
    """A change of the absorbed dose after the kernel (before the threshold), computed from
    the blurred dose and its gradient: ``apply(dose, gy, gx, theta)``, all (P, B, H, W),
    gradients per design pixel."""

    stage = "dose"

    def apply(self, dose, gy, gx, theta: Theta) -> torch.Tensor:
        raise NotImplementedError

    def gradient(self, dose, gy, gx, hyy, hxy, hxx, theta: Theta) -> tuple:
        """(gy, gx) of ``apply``'s result, from the dose's gradient and Hessian."""
        raise NotImplementedError


# ---------------------------------------------------------------- effect components
#
# Each effect beyond Eq. 1 is a component (or the replacement of one) whose neutral
# parameter values give Eq. 1 back exactly; ``EFFECTS`` below names them for the
# residual diagnosis (unscatter.diagnosis).


class HeavyTailKernel(KernelTerm):
    """A second, wide scattering term: a share ``tail_fraction`` of the light is scattered
    with the exponential kernel exp(-r / tail_length_px) (normalised), the rest with the
    core kernel: K = (1 - f) K_core + f K_tail.

    Residual signature under Eq. 1: the print depends on the mask's density over tens to
    hundreds of um. Prints swell where the mask is dense at large radii (100-300 um) and
    shrink in sparse neighbourhoods; small isolated features print too small and large
    ones too big, so the residual trends with the local mask density at large radii, and
    the print/mask spectrum ratio is lower at low frequencies than the core Gaussian's.
    """

    name = "heavy_tail"
    params = (
        ParamSpec("tail_fraction", 0.0, (0.0, 0.6), "share of the light", "share of the light in the wide (exponential) kernel term"),
        ParamSpec("tail_length_px", 10.0, (2.0, 40.0), "design pixels", "decay length of the exponential kernel term"),
    )
    formula = "K = (1 - tail_fraction) Gauss_sigma + tail_fraction Exp_tail_length"

    def weight(self, theta):
        f = theta["tail_fraction"].clamp(0.0, 0.95)
        return f / (1 - f)  # the core term has weight 1: K = (1 - f) core + f tail

    def transfer(self, fy, fx, theta):
        lam = theta["tail_length_px"].clamp_min(0.1)[:, None, None]
        f2 = fy[None, :, None] ** 2 + fx[None, None, :] ** 2
        return (1 + (2 * math.pi) ** 2 * lam**2 * f2) ** -1.5  # 2-D transform of exp(-r / lambda)

    def support_px(self, values):
        # light beyond 3 lengths wraps only after 6 (the padding is 2 x support): < 2 % of the tail
        return 3.0 * float(values["tail_length_px"])


class EllipticalGaussianKernel(KernelTerm):
    """An elliptical Gaussian core kernel: axes sigma_px sqrt(aniso_ratio) along
    ``aniso_angle_deg`` (from the X axis towards Y) and sigma_px / sqrt(aniso_ratio) across
    it (the same area as the isotropic kernel of sigma_px). Replaces ``GaussianKernel``.

    Residual signature under Eq. 1: the error depends on the edge orientation. Edges
    whose normal lies along the major axis print too far out, edges along it print too
    short; corners and round features stretch along one direction.
    """

    name = "anisotropy"
    params = (
        GaussianKernel.params[0],
        # the angle wraps at +-90 deg (the kernel repeats every 180 deg). Until 2026-12-01 it ran -45 to 45 deg, where
        # (r, 45 + d) is the kernel (1 / r, -45 + d): a fit whose ellipse lay near 45 deg stopped on the angle's bound,
        # cut off from the same kernel a step away. The ratio still runs either side of 1: a fit that starts with the
        # long axis across the prints' passes through a round kernel to the other side (with the ratio bounded at 1
        # one fold fit stopped there, round). So each kernel is written twice, (r, a) and (1 / r, a + 90 deg);
        # ``canonical`` writes it once, for spreads and means (docs/diagnosis.md, "A kernel's angle wraps")
        ParamSpec("aniso_ratio", 1.0, (0.5, 2.0), "", "sigma_major / sigma_minor of the kernel (< 1: the axis is across aniso_angle_deg)"),
        ParamSpec("aniso_angle_deg", 0.0, (-90.0, 90.0), "degrees", "direction of the kernel's axis of sigma_px sqrt(aniso_ratio)",
                  period=180.0),
    )
    formula = "Gauss_sigma elliptical: sigma sqrt(ratio) along aniso_angle, sigma / sqrt(ratio) across"

    def transfer(self, fy, fx, theta):
        s = theta["sigma_px"].clamp_min(1e-3)
        r = theta["aniso_ratio"].clamp_min(0.05)
        th = theta["aniso_angle_deg"] * (math.pi / 180)
        su2 = (s**2 * r)[:, None, None]
        sv2 = (s**2 / r)[:, None, None]
        c, sn = torch.cos(th)[:, None, None], torch.sin(th)[:, None, None]
        num = 0.0
        den = 0.0
        # periodised continuous transfer (the sampled kernel), like sampled_gaussian_transfer
        for ky in (-1, 0, 1):
            for kx in (-1, 0, 1):
                Fy = fy[None, :, None] + ky
                Fx = fx[None, None, :] + kx
                u = c * Fx + sn * Fy
                v = -sn * Fx + c * Fy
                num = num + torch.exp(-2 * math.pi**2 * (su2 * u**2 + sv2 * v**2))
                U, V = c * kx + sn * ky, -sn * kx + c * ky
                den = den + torch.exp(-2 * math.pi**2 * (su2 * U**2 + sv2 * V**2))
        return num / den

    def support_px(self, values):
        r = float(values.get("aniso_ratio", 1.0))
        return 4.0 * float(values["sigma_px"]) * math.sqrt(max(r, 1.0 / max(r, 1e-6)))


class GammaDose(DoseResponse):
    """A nonlinear grey-level response: the dose of grey level g is (g / 255)^dose_gamma.
    Replaces ``LinearDose``.

    Residual signature under Eq. 1: the error depends on the mask's grey level. Grey
    features print too small (gamma > 1) or too big (gamma < 1) while full-grey (255)
    features fit; the residual vs grey level of the nearest lit mask pixel slopes.
    """

    name = "dose_nonlinearity"
    params = (ParamSpec("dose_gamma", 1.0, (0.5, 2.0), "", "exponent of the grey level's dose (1: linear, Eq. 1)"),)
    formula = "M -> M^dose_gamma"
    # Lagrange interpolation of M^gamma in gamma at Chebyshev nodes over this range (wider
    # than the bounds: the refinement may look outside them): relative error < 2e-4 for
    # grey levels >= 96, and exact at 0 and 255
    NODES_RANGE = (0.25, 2.75)
    NODES = 6

    def apply(self, M, theta):
        g = theta["dose_gamma"].reshape(-1, 1, 1, 1)
        m = M.clamp_min(1e-6)[None]
        return torch.where(M[None] > 0, torch.exp(g * torch.log(m)), torch.zeros_like(m))

    def _nodes(self):
        lo, hi = self.NODES_RANGE
        n = self.NODES
        k = np.arange(n)
        return (lo + hi) / 2 + (hi - lo) / 2 * np.cos((2 * k + 1) * math.pi / (2 * n))

    def expansion(self):
        nodes = [float(x) for x in self._nodes()]

        def phi(g):
            return lambda M: torch.where(M > 0, torch.exp(g * torch.log(M.clamp_min(1e-6))), torch.zeros_like(M))

        def coef(theta):
            gam = theta["dose_gamma"]
            cols = []
            for j, gj in enumerate(nodes):
                a = torch.ones_like(gam)
                for m, gm in enumerate(nodes):
                    if m != j:
                        a = a * (gam - gm) / (gj - gm)
                cols.append(a)
            return torch.stack(cols, dim=1)

        return [phi(g) for g in nodes], coef


class IlluminationField(FieldTerm):
    """Illumination beyond Eq. 1's quadratic: the lowest-order terms it lacks, with
    R^2 = X^2 + Y^2: ill_xy X Y + ill_xr2 X R^2 + ill_yr2 Y R^2 + ill_r4 R^4 (added to the
    quadratic field; linear in its parameters, so the fast evaluator keeps its spectra).

    Residual signature under Eq. 1: the error depends on the position in the field:
    prints are too big where the lamp is brighter than the quadratic fit (e.g. the
    corners under a positive R^4 term, a hotspot) and too small where it is dimmer; the
    residual map averaged over prints (vs DMD coordinates) is smooth and non-zero.
    """

    name = "illumination_field"
    params = (
        ParamSpec("ill_xy", 0.0, (-0.25, 0.25), "relative dose", "coefficient of X Y"),
        ParamSpec("ill_xr2", 0.0, (-0.25, 0.25), "relative dose", "coefficient of X (X^2 + Y^2)"),
        ParamSpec("ill_yr2", 0.0, (-0.25, 0.25), "relative dose", "coefficient of Y (X^2 + Y^2)"),
        # R^4 reaches 4 in the corners: +-0.25 spans a corner 1.0 dimmer or brighter
        ParamSpec("ill_r4", 0.0, (-0.25, 0.25), "relative dose", "coefficient of (X^2 + Y^2)^2"),
    )
    formula = "field + ill_xy X Y + ill_xr2 X R^2 + ill_yr2 Y R^2 + ill_r4 R^4"

    def basis(self, X, Y):
        H, W = Y.shape[0], X.shape[1]
        R2 = X**2 + Y**2
        return {"ill_xy": (X * Y).expand(H, W), "ill_xr2": (X * R2).expand(H, W), "ill_yr2": (Y * R2).expand(H, W),
                "ill_r4": (R2**2).expand(H, W)}

    def field(self, X, Y, theta):
        b = self.basis(X, Y)
        return sum(theta[k][:, None, None] * v for k, v in b.items())


class EdgeOffset(DoseTerm):
    """Swelling (+) or erosion (-) of the print after the wash by ``edge_offset_px`` design
    pixels, normal to its edges: to first order the print dilated by d is where
    D + d |grad D| >= T, which this term gives (smooth, so the refinement and the mask
    optimisation differentiate through it; exact for a dose scaled by a factor).

    Residual signature under Eq. 1: a constant signed band along every print edge,
    independent of grey level, density and position: the residual vs signed distance to
    the edge is one-signed on both sides of the edge (prints too big everywhere, or too
    small), and small gaps close (or thin lines vanish) more than T and sigma can explain.
    """

    name = "edge_offset"
    params = (ParamSpec("edge_offset_px", 0.0, (-4.0, 4.0), "design pixels", "post-wash edge displacement (+ swelling, - erosion)"),)
    formula = "D -> D + edge_offset |grad D|"

    def apply(self, dose, gy, gx, theta):
        d = theta["edge_offset_px"].reshape(-1, *([1] * (dose.dim() - 1)))
        return dose + d * torch.sqrt(gx**2 + gy**2 + 1e-12)

    def gradient(self, dose, gy, gx, hyy, hxy, hxx, theta):
        # grad (D + d |grad D|) = grad D + d H grad D / |grad D|
        d = theta["edge_offset_px"].reshape(-1, *([1] * (dose.dim() - 1)))
        n = torch.sqrt(gx**2 + gy**2 + 1e-12)
        ny, nx = gy / n, gx / n
        return gy + d * (hyy * ny + hxy * nx), gx + d * (hxy * ny + hxx * nx)


# ------------------------------------------------------------------------- geometry


def design_coords(n: int, scale: float = 1.0, device=None, dtype=DTYPE) -> torch.Tensor:
    """Normalised coordinate of the centres of ``n`` grid pixels, each ``scale`` design
    pixels wide: -1 at the first design pixel centre, +1 at the last."""
    size = n * scale  # the design region in design pixels
    centre = torch.arange(n, dtype=torch.float64) * scale + (scale - 1) / 2  # grid pixel centre in design px
    half = (size - 1) / 2
    x = (centre - half) / half if half > 0 else torch.zeros(n, dtype=torch.float64)
    return x.to(device=device, dtype=dtype)


def fast_len(n: int, multiple: int = 2) -> int:
    """Smallest 5-smooth multiple of ``multiple`` that is >= n (fast FFT sizes)."""
    m = max(int(n), multiple)
    m += -m % multiple
    while True:
        r = m
        for p in (2, 3, 5):
            while r % p == 0:
                r //= p
        if r == 1:
            return m
        m += multiple


def padded_shape(shape: tuple[int, int], support_px: float, scale: float = 1.0, multiple: int = 2) -> tuple[int, int]:
    """FFT grid for a linear convolution: the region plus 2 x support (>= 4 sigma a side).

    The region sits at the grid's origin; the zeros behind it are the padding on both
    sides (circularly), so light needs to travel 2 x support to wrap around.
    """
    pad = int(math.ceil(2 * support_px / scale)) + 2
    return fast_len(shape[0] + pad, multiple), fast_len(shape[1] + pad, multiple)


# ---------------------------------------------------------------------------- model


class PrinterModel:
    """A printer simulator built from components; ``eq1()`` is the paper's Eq. 1.

    All methods are batched: ``masks`` is (B, H, W) in [0, 1] and ``theta`` maps each
    parameter name to a (P,) tensor (P parameter sets); results are (P, B, H, W).
    """

    def __init__(self, components: list[Component], name: str = "custom"):
        self.name = name
        self.components = list(components)
        stages = ("field", "response", "kernel", "dose", "threshold")
        unknown = sorted({c.stage for c in self.components} - set(stages))
        if unknown:
            raise ValueError(f"unknown component stage(s) {unknown}; known: {list(stages)}")
        by_stage = {s: [c for c in self.components if c.stage == s] for s in stages}
        for s in ("field", "kernel"):
            if not by_stage[s]:
                raise ValueError(f"a printer model needs at least one {s} term")
        for s in ("response", "threshold"):
            if len(by_stage[s]) != 1:
                raise ValueError(f"a printer model needs exactly one {s} component, got {len(by_stage[s])}")
        self.fields: list[FieldTerm] = by_stage["field"]
        self.response: DoseResponse = by_stage["response"][0]
        self.kernels: list[KernelTerm] = by_stage["kernel"]
        self.threshold: Threshold = by_stage["threshold"][0]
        self.dose_terms: list[DoseTerm] = by_stage["dose"]
        specs: dict[str, ParamSpec] = {}
        for c in self.components:
            for p in c.params:
                if p.name in specs:
                    raise ValueError(f"parameter {p.name!r} is contributed by two components")
                specs[p.name] = p
        self.specs = specs

    # -- parameters -----------------------------------------------------------
    @property
    def names(self) -> list[str]:
        return list(self.specs)

    def theta(self, values, device=None) -> Theta:
        """(P,) tensors from a Params, a dict of floats, or a dict of sequences."""
        if isinstance(values, Params):
            values = values.values
        out = {}
        for k in self.names:
            if k not in values:
                raise KeyError(f"missing parameter {k!r} for model {self.name!r}")
            v = values[k]
            t = v if isinstance(v, torch.Tensor) else torch.as_tensor(np.atleast_1d(np.asarray(v, dtype=np.float64)))
            out[k] = t.to(device=device, dtype=DTYPE).reshape(-1)
        P = max(t.numel() for t in out.values())
        return {k: t.expand(P) if t.numel() == 1 else t for k, t in out.items()}

    def support_px(self, values) -> float:
        """Padding radius in design pixels: the widest kernel term (values: dict of floats/arrays)."""
        vals = values.values if isinstance(values, Params) else values
        sup = 0.0
        for kt in self.kernels:
            sub = {p.name: float(np.max(np.asarray(_numpy(vals[p.name])))) for p in kt.params}
            sup = max(sup, kt.support_px(sub))
        return max(sup, 1.0)

    # -- Eq. 1 piece by piece ---------------------------------------------------
    def coords(self, H: int, W: int, scale: float = 1.0, device=None):
        X = design_coords(W, scale, device)[None, :]
        Y = design_coords(H, scale, device)[:, None]
        return X, Y

    def field(self, X, Y, theta: Theta) -> torch.Tensor:
        """(P, H, W) illumination field before the ReLU: the sum of the field terms."""
        return sum(ft.field(X, Y, theta) for ft in self.fields)

    def exposure(self, masks: torch.Tensor, theta: Theta, scale: float = 1.0) -> torch.Tensor:
        """(P, B, H, W) ReLU(field) * response(M): the light delivered before scattering."""
        _, H, W = masks.shape
        X, Y = self.coords(H, W, scale, masks.device)
        f = torch.relu(self.field(X, Y, theta))  # Guan et al. 2022, Eq. 1: light is non-negative
        r = self.response.apply(masks, theta)  # (B, H, W), or (P, B, H, W) for a response with parameters
        return (r[None] if r.dim() == 3 else r) * f[:, None]

    def transfer(self, shape: tuple[int, int], theta: Theta, scale: float = 1.0, device=None) -> torch.Tensor:
        """(P, Nh, Nw//2+1) transfer function of the kernel on an rfft2 grid whose pixel
        is ``scale`` design pixels."""
        Nh, Nw = shape
        fy = torch.fft.fftfreq(Nh, device=device, dtype=DTYPE) / scale  # cycles per design pixel
        fx = torch.fft.rfftfreq(Nw, device=device, dtype=DTYPE) / scale
        num = 0.0
        den = 0.0
        for kt in self.kernels:
            w = kt.weight(theta)[:, None, None]
            num = num + w * kt.transfer(fy, fx, theta)
            den = den + w
        return num / den

    def blur_spectrum(self, spectrum: torch.Tensor, theta: Theta, shape, out_hw, scale: float = 1.0,
                      gradient: bool = False):
        """Kernel applied to (P, B, Nh, Nw//2+1) exposure spectra -> (P, B, H, W) dose.

        Dose terms (stage "dose", e.g. ``EdgeOffset``) then act on the blurred dose and
        its gradient (per design pixel), both taken from the same spectrum. ``gradient``:
        return (dose, gy, gx), the gradient of the returned dose (the dose terms' by the
        chain rule, from the blurred dose's Hessian, taken from the same spectrum)."""
        Ht = self.transfer(shape, theta, scale, spectrum.device)
        spec = spectrum * Ht[:, None]
        # irfft2 in two passes, dropping the padding rows in between (less work, same result)
        x = torch.fft.ifft(spec, dim=-2)[..., : out_hw[0], :]
        dose = torch.fft.irfft(x, n=shape[1], dim=-1)[..., : out_hw[1]]
        if not self.dose_terms and not gradient:
            return dose
        Nh, Nw = shape
        fy = torch.fft.fftfreq(Nh, device=spec.device, dtype=DTYPE) / scale
        fx = torch.fft.rfftfreq(Nw, device=spec.device, dtype=DTYPE) / scale
        fy = torch.where(fy.abs() >= 0.5 / scale - 1e-9, 0.0, fy)  # no derivative at the Nyquist frequency
        fx = torch.where(fx >= 0.5 / scale - 1e-9, 0.0, fx)
        gx = torch.fft.irfft(x * (2j * math.pi * fx), n=Nw, dim=-1)[..., : out_hw[1]]
        xy = torch.fft.ifft(spec * (2j * math.pi * fy)[:, None], dim=-2)[..., : out_hw[0], :]
        gy = torch.fft.irfft(xy, n=Nw, dim=-1)[..., : out_hw[1]]
        grad = (gy, gx)
        if gradient and self.dose_terms:  # the returned dose's gradient: the chain rule through the Hessian
            if len(self.dose_terms) > 1:
                raise NotImplementedError("the gradient of more than one dose term")
            wy, wx = (2j * math.pi * fy)[:, None], 2j * math.pi * fx
            hxx = torch.fft.irfft(x * wx * wx, n=Nw, dim=-1)[..., : out_hw[1]]
            hxy = torch.fft.irfft(xy * wx, n=Nw, dim=-1)[..., : out_hw[1]]
            hyy = torch.fft.irfft(torch.fft.ifft(spec * wy * wy, dim=-2)[..., : out_hw[0], :], n=Nw, dim=-1)[..., : out_hw[1]]
            grad = self.dose_terms[0].gradient(dose, gy, gx, hyy, hxy, hxx, theta)
        for t in self.dose_terms:
            dose = t.apply(dose, gy, gx, theta)
        return (dose, *grad) if gradient else dose

    def dose(self, masks: torch.Tensor, theta: Theta, scale: float = 1.0, shape=None, gradient: bool = False):
        """(P, B, H, W) absorbed dose Gauss_sigma(ReLU(field) * M), zero padded (no wrap);
        ``gradient``: (dose, gy, gx) (``blur_spectrum``)."""
        masks = _as_masks(masks)
        _, H, W = masks.shape
        if shape is None:
            shape = padded_shape((H, W), self.support_px({k: v.detach().cpu() for k, v in theta.items()}), scale)
        spec = torch.fft.rfft2(self.exposure(masks, theta, scale), s=shape)
        return self.blur_spectrum(spec, theta, shape, (H, W), scale, gradient=gradient)

    def prints(self, masks: torch.Tensor, theta: Theta, temperature: float | None = None, scale: float = 1.0) -> torch.Tensor:
        """(P, B, H, W) prints: bool (hard threshold) or in (0, 1) (smooth, temperature > 0)."""
        if temperature is not None and temperature <= 0:
            raise ValueError("temperature must be > 0 (use None for the hard threshold)")
        return self.threshold.apply(self.dose(masks, theta, scale), theta, temperature)

    def __repr__(self):
        return f"PrinterModel({self.name!r}, components={[c.name for c in self.components]})"


def _numpy(v):
    if isinstance(v, torch.Tensor):
        return v.detach().cpu().numpy()
    return v


def _as_masks(masks) -> torch.Tensor:
    if not isinstance(masks, torch.Tensor):
        raise TypeError("masks must be a torch tensor (B, H, W) in [0, 1]; use simulate() for uint8 arrays")
    if masks.dim() == 2:
        masks = masks[None]
    if masks.dim() != 3:
        raise ValueError(f"masks must be (B, H, W), got shape {tuple(masks.shape)}")
    return masks


# -------------------------------------------------------------- fixed-masks evaluator


class FixedMasks:
    """Simulate one set of masks under many parameter sets, fast.

    Calibration evaluates the same masks for every individual. When the field terms
    are linear in their parameters and the dose response has none, the exposure's
    spectrum is a weighted sum of precomputed spectra (rfft2 of basis_k * M, e.g.
    M, X^2 M, Y^2 M, X M, Y M for Eq. 1), so one individual costs one kernel multiply
    and one inverse FFT per mask. Parameter sets whose field goes negative somewhere
    (where the ReLU acts) are computed directly. Otherwise it falls back to
    ``PrinterModel.dose``. Results equal ``model.dose`` to float precision.

    ``decimated(f)`` gives the dose at every f-th pixel (rows and columns 0, f, 2f, ...)
    from the low-frequency block of the same spectra: exact for a dose band-limited
    below 1 / (2 f) cycles per pixel, which the kernel makes it when sigma >~ 1.5 f
    (the dropped part is at most exp(-pi^2 sigma^2 / (2 f^2)) of the exposure's
    spectrum). The cost is that of an f-times smaller grid, and comparing these samples
    with the measured print's pixels is an unbiased subsample of the full objective.
    """

    def __init__(self, model: PrinterModel, masks: torch.Tensor, support_px: float = 48.0, cache: dict | None = None):
        """``cache``: a dict shared by evaluators of the same masks whose models differ only
        in terms that need no spectra of their own (kernels, dose terms: the diagnosis's
        candidates): the spectra are computed once per set of basis maps and kept there
        (not for a response expansion, whose many terms would stay in memory)."""
        self.model = model
        self.masks = _as_masks(masks)
        _, self.H, self.W = self.masks.shape
        self.support_px = float(support_px)
        self.full_shape = padded_shape((self.H, self.W), support_px, multiple=8)  # divisible by 2, 4, 8
        self.f = 1
        self.shape = self.full_shape
        self.out_hw = (self.H, self.W)
        self.X, self.Y = model.coords(self.H, self.W, 1.0, self.masks.device)
        self.basis_names: list[str] | None = None
        self.spectra = None
        self.response_terms = None  # (J, coefficients(theta) -> (P, J)) of a response expansion
        # where the spectra are cached, the cache and their key there: their decimations and
        # subsets (``decimated``, ``subset``) are kept beside them, under keys that say how
        # they derive from them, for the next evaluator of the same masks
        self._cache, self._key = None, None
        bases = [ft.basis(self.X, self.Y) for ft in model.fields]
        expansion = model.response.expansion() if model.response.params else None
        if all(b is not None for b in bases) and (not model.response.params or expansion is not None):
            basis = {k: v for b in bases for k, v in b.items()}
            self.basis_names = list(basis)
            key = self.spectra_key(model, (self.H, self.W), self.support_px)
            if expansion is None and cache is not None and key in cache:
                self.spectra = cache[key]
            else:
                if expansion is None:
                    responses = [model.response.apply(self.masks, {})]
                else:  # response = sum_j a_j(theta) phi_j(M): spectra of basis_k * phi_j(M)
                    phis, coef = expansion
                    responses = [phi(self.masks) for phi in phis]
                    self.response_terms = (len(phis), coef)
                # (K, B, Nh, Nw//2+1) complex (K = bases x response terms), as real pairs for one matrix product
                spec = torch.stack([torch.fft.rfft2(v[None] * r, s=self.shape) for v in basis.values() for r in responses])
                self.spectra = torch.view_as_real(spec).contiguous()
                if expansion is None and cache is not None:
                    cache[key] = self.spectra
            if expansion is None and cache is not None:
                self._cache, self._key = cache, key

    @staticmethod
    def spectra_key(model: PrinterModel, hw: tuple, support_px: float) -> tuple | None:
        """The key under which an evaluator of ``model`` on masks of ``hw`` (H, W) with
        ``support_px`` keeps its spectra in a shared cache (its padded grid, field terms and
        dose response), or None where it keeps none (a dose response with parameters).
        Evaluators of one key share the spectra and what derives from them."""
        if model.response.params:
            return None
        return (padded_shape(hw, support_px, multiple=8), tuple(type(ft).__name__ for ft in model.fields), model.response.name)

    @property
    def fast(self) -> bool:
        return self.spectra is not None

    def _band(self, spec: torch.Tensor, f: int) -> torch.Tensor:
        """Low-frequency block of full-grid rfft2 spectra (..., Nh, Nw//2+1) for grid/f,
        scaled so the smaller inverse FFT returns the dose samples."""
        if f == 1:
            return spec
        nh, nw = self.full_shape[0] // f, self.full_shape[1] // f
        rows = torch.cat([torch.arange(nh // 2), torch.arange(self.full_shape[0] - nh // 2, self.full_shape[0])]).to(spec.device)
        return spec.index_select(-2, rows)[..., : nw // 2 + 1] / (f * f)

    def decimated(self, f: int) -> FixedMasks:
        """The same evaluator returning the dose at every f-th pixel (see the class doc)."""
        f = int(f)
        if f < 1 or self.full_shape[0] % f or self.full_shape[1] % f:
            raise ValueError(f"decimation factor {f} must divide the FFT grid {self.full_shape}")
        if self.f != 1:
            raise ValueError("decimate the full-resolution evaluator")
        new = object.__new__(FixedMasks)
        new.__dict__.update(self.__dict__)
        new.f = f
        new.shape = (self.full_shape[0] // f, self.full_shape[1] // f)
        new.out_hw = (-(-self.H // f), -(-self.W // f))
        if self.spectra is not None:
            new.spectra = self._derived(("band", f), lambda: torch.view_as_real(
                self._band(torch.view_as_complex(self.spectra), f)).contiguous())
            new._key = None if self._key is None else (*self._key, ("band", f))
        return new

    def _derived(self, how: tuple, compute):
        """Spectra derived from this evaluator's (``how``: the derivation), from the cache
        where an evaluator of the same masks and basis derived them before; the derived
        evaluator's key set accordingly by the caller (``_key``). The diagnosis builds
        an evaluator per candidate in each worker, and cuts its objectives to each fold:
        with Eq. 1's 5 spectra of 32 masks on a 768 x 768 grid, the bands for every 4th
        and every 2nd pixel and the fold subsets took 0.7 s per evaluator, for the same
        numbers each time."""
        if self._cache is None:
            return compute()
        key = (*self._key, how)
        if key not in self._cache:
            self._cache[key] = compute()
        return self._cache[key]

    def dropped(self, theta: Theta, f: int) -> float:
        """Largest kernel transfer at or beyond the Nyquist frequency of every f-th pixel
        sampling: how far ``decimated(f)`` is from exact for these parameters."""
        if f == 1:
            return 0.0
        Ht = self.model.transfer(self.full_shape, theta, 1.0, self.masks.device).abs()
        fy = torch.fft.fftfreq(self.full_shape[0], device=Ht.device).abs()[:, None]
        fx = torch.fft.rfftfreq(self.full_shape[1], device=Ht.device)[None, :]
        out = (fy >= 0.5 / f) | (fx >= 0.5 / f)
        return float(Ht[:, out].max())

    def subset(self, idx) -> FixedMasks:
        """The same evaluator restricted to masks ``idx``."""
        idx = torch.as_tensor(np.asarray(idx), dtype=torch.long, device=self.masks.device)
        new = object.__new__(FixedMasks)
        new.__dict__.update(self.__dict__)
        new.masks = self.masks[idx]
        if self.spectra is not None and self.f == 1:
            # at full resolution (a prediction, or a stage that decimates after it) it is not
            # kept: each is used once, and the full spectra are the largest
            new.spectra, new._cache, new._key = self.spectra[:, idx].contiguous(), None, None
        elif self.spectra is not None:
            new.spectra = self._derived(("subset", tuple(idx.tolist())), lambda: self.spectra[:, idx].contiguous())
            new._key = None if self._key is None else (*self._key, ("subset", tuple(idx.tolist())))
        return new

    def dose(self, theta: Theta, masks: slice | None = None, gradient: bool = False):
        """(P, B, h, w) absorbed dose for P parameter sets (at every f-th pixel); ``masks``
        restricts it to a block of the masks (smaller temporaries). ``gradient``: (dose,
        gy, gx), the returned dose's gradient per design pixel from the same spectrum
        (``PrinterModel.blur_spectrum``)."""
        if self.support_px + 1e-6 < self.model.support_px({k: v.detach().cpu() for k, v in theta.items()}):
            raise ValueError("a kernel is wider than this evaluator's padding; build it with a larger support_px")
        sl = masks if masks is not None else slice(None)
        M = self.masks[sl]
        if not self.fast:
            out = self.model.dose(M, theta, shape=self.full_shape, gradient=gradient)
            sub = (Ellipsis, slice(None, None, self.f), slice(None, None, self.f))
            return tuple(t[sub] for t in out) if gradient else out[sub]
        K = self.spectra.shape[0]
        c = torch.stack([theta[k] for k in self.basis_names], dim=1)  # (P, K)
        P = c.shape[0]
        if self.response_terms is not None:
            J, coef = self.response_terms
            c = (c[:, :, None] * coef(theta)[:, None, :].to(c)).reshape(P, K)
        if masks is None:  # sum_k c_pk spectrum_k as one matrix product
            spec = (c @ self.spectra.reshape(K, -1)).reshape(P, *self.spectra.shape[1:])
        else:  # a block: accumulate over k on views (no copy of the spectra)
            S = self.spectra[:, sl]
            spec = sum(c[:, k, None, None, None, None] * S[k][None] for k in range(K))
        spec = torch.view_as_complex(spec)
        # where the field goes negative the ReLU acts and the field is not linear in c
        neg = self._negative_field(theta)
        if neg.numel():
            sub = {k: v[neg] for k, v in theta.items()}
            direct = self._band(torch.fft.rfft2(self.model.exposure(M, sub), s=self.full_shape), self.f)
            spec = spec.index_put((neg,), direct)
        return self.model.blur_spectrum(spec, theta, self.shape, self.out_hw, self.f, gradient=gradient)

    def prints(self, theta: Theta, temperature: float | None = None, masks: slice | None = None) -> torch.Tensor:
        return self.model.threshold.apply(self.dose(theta, masks), theta, temperature)

    def _negative_field(self, theta: Theta) -> torch.Tensor:
        """Indices of the parameter sets whose field is negative somewhere on the grid.

        The field is smooth: a 65 x 65 lattice (edges included) screens it, and only sets
        that come near zero there are checked on every pixel.
        """
        with torch.no_grad():
            th = {k: v.detach() for k, v in theta.items()}
            ix = torch.linspace(0, self.W - 1, min(self.W, 65), device=self.X.device).round().long()
            iy = torch.linspace(0, self.H - 1, min(self.H, 65), device=self.Y.device).round().long()
            coarse = self.model.field(self.X[:, ix], self.Y[iy], th).amin(dim=(1, 2))
            near = (coarse < 0.1 * coarse.abs().max().clamp_min(1e-6)).nonzero().flatten()
            if not near.numel():
                return near
            sub = {k: v[near] for k, v in th.items()}
            return near[self.model.field(self.X, self.Y, sub).amin(dim=(1, 2)) < 0]


# --------------------------------------------------------------------- named models

_MODELS: dict = {}


def register_model(name: str, factory) -> None:
    """Name a combination of components (``factory()`` -> list of components)."""
    _MODELS[name] = factory


def model_names() -> list[str]:
    return sorted(_MODELS)


def get_model(name: str = "eq1") -> PrinterModel:
    """A named model, or a named model with effects: ``"eq1+heavy_tail+edge_offset"``."""
    if name in _MODELS:
        return PrinterModel(_MODELS[name](), name=name)
    base, effects = split_model_name(name)
    components = _MODELS[base]()
    for e in effects:
        components = EFFECTS[e].compose(components)
    return PrinterModel(components, name=name)


def is_model(name: str) -> bool:
    """Whether ``get_model(name)`` knows the name (a registered model, with or without effects)."""
    try:
        split_model_name(name)
    except KeyError:
        return False
    return True


register_model("eq1", lambda: [QuadraticField(), LinearDose(), GaussianKernel(), Threshold()])  # Guan et al. 2022, Eq. 1


def eq1() -> PrinterModel:
    """The paper's simulator, Eq. 1."""
    return get_model("eq1")


# ------------------------------------------------------------------- effect library


@dataclass(frozen=True)
class Effect:
    """A named physical effect beyond Eq. 1: how it changes a model's component list.

    ``component`` is the class that carries its parameters (its docstring says which
    residual signature the effect explains); at its parameters' defaults the extended
    model equals the model it extends.
    """

    name: str
    component: type
    compose: object  # list of components -> list of components

    @property
    def params(self) -> tuple:
        return self.component.params

    @property
    def signature(self) -> str:
        doc = self.component.__doc__ or ""
        i = doc.find("Residual signature")
        return " ".join(doc[i:].split()) if i >= 0 else ""


def _add(cls):
    def compose(components):
        if any(isinstance(c, cls) for c in components):
            raise ValueError(f"the model already has {cls.name!r}")
        i = max((j for j, c in enumerate(components) if c.stage == cls.stage), default=len(components) - 1)
        return components[: i + 1] + [cls()] + components[i + 1 :]

    return compose


def _replace(old_cls, new_cls):
    def compose(components):
        hits = [i for i, c in enumerate(components) if type(c) is old_cls]
        if not hits:
            raise ValueError(f"effect {new_cls.name!r} replaces {old_cls.name!r}, which the model does not have")
        return [new_cls() if type(c) is old_cls else c for c in components]

    return compose


EFFECTS: dict[str, Effect] = {}


def register_effect(effect: Effect) -> None:
    """Add an effect to the library (names are the diagnosis' candidate names)."""
    if "+" in effect.name:
        raise ValueError("effect names cannot contain '+'")
    EFFECTS[effect.name] = effect


register_effect(Effect("heavy_tail", HeavyTailKernel, _add(HeavyTailKernel)))
register_effect(Effect("anisotropy", EllipticalGaussianKernel, _replace(GaussianKernel, EllipticalGaussianKernel)))
register_effect(Effect("dose_nonlinearity", GammaDose, _replace(LinearDose, GammaDose)))
register_effect(Effect("illumination_field", IlluminationField, _add(IlluminationField)))
register_effect(Effect("edge_offset", EdgeOffset, _add(EdgeOffset)))


def effect_names() -> list[str]:
    """The library's effects, in its order (the order of a composite model's name)."""
    return list(EFFECTS)


def split_model_name(name: str) -> tuple[str, list[str]]:
    """``"eq1+heavy_tail"`` -> ("eq1", ["heavy_tail"]); KeyError for unknown parts."""
    base, *effects = str(name).split("+")
    if base not in _MODELS:
        raise KeyError(f"unknown model {base!r}; known: {model_names()}")
    for e in effects:
        if e not in EFFECTS:
            raise KeyError(f"unknown effect {e!r} in model {name!r}; known: {effect_names()}")
    if len(set(effects)) != len(effects):
        raise KeyError(f"an effect appears twice in model {name!r}")
    return base, effects


def model_with_effects(model: str, effects) -> str:
    """The canonical name of ``model`` plus ``effects`` (library order, no repeats)."""
    base, have = split_model_name(model)
    want = set(have) | set(effects)
    for e in want:
        if e not in EFFECTS:
            raise KeyError(f"unknown effect {e!r}; known: {effect_names()}")
    return "+".join([base] + [e for e in EFFECTS if e in want])


def extend_params(params: Params, effects) -> Params:
    """``params`` of a model with ``effects`` added at their neutral defaults: the same
    printer, as the warm start of a fit of the extended model."""
    name = model_with_effects(params.model, effects)
    m = get_model(name)
    values, bounds = {}, {}
    for k, spec in m.specs.items():
        values[k] = float(params.values[k]) if k in params.values else float(spec.default)
        bounds[k] = tuple(params.bounds[k]) if k in params.bounds else tuple(float(x) for x in spec.bounds)
    info = {k: v for k, v in params.info.items() if k == "parameter_extras"}
    return Params(name, values, bounds, tuple(params.fixed), params.pixel_size_um, info)


def periods(params: "Params") -> dict:
    """name -> period of the parameters of ``params`` that wrap (``ParamSpec.period``):
    those whose bounds span exactly their period. Bounds narrower than a period (a params
    file from before the angle wrapped, or bounds set by hand) bound the search as any
    other parameter's do."""
    specs = get_model(params.model).specs
    out = {}
    for k, (lo, hi) in params.bounds.items():
        per = getattr(specs.get(k), "period", None)
        if per and abs((hi - lo) - per) <= 1e-9 * per:
            out[k] = float(per)
    return out


def canonical(values: dict, wrap: dict | None = None) -> dict:
    """``values`` (numbers or arrays) with an elliptical kernel written as the search writes
    it: its long axis along ``aniso_angle_deg`` (a ratio r < 1 at angle a is the kernel 1 / r
    at a + 90 deg), the angle within -90..90 deg. The same printer. With ``wrap`` (``periods``
    of the values' params) only where the angle wraps: bounds of an older params file
    (-45..45 deg) keep the values as they are."""
    if "aniso_ratio" not in values or "aniso_angle_deg" not in values or (wrap is not None and "aniso_angle_deg" not in wrap):
        return dict(values)
    r, a = np.asarray(values["aniso_ratio"], float), np.asarray(values["aniso_angle_deg"], float)
    flip = r < 1
    r, a = np.where(flip, 1.0 / np.maximum(r, 1e-12), r), np.where(flip, a + 90.0, a)
    a = (a + 90.0) % 180.0 - 90.0
    if r.ndim == 0:
        r, a = float(r), float(a)
    return {**values, "aniso_ratio": r, "aniso_angle_deg": a}


def unwrapped(values, period: float | None, centre: float | None = None) -> np.ndarray:
    """``values`` of a parameter that repeats every ``period`` (None: as they are), each
    moved by whole periods to within half a period of ``centre`` (default: their median,
    taken about the first), so that their spread is taken across the wrap (an angle of 89
    deg and one of -89 deg are 2 deg apart)."""
    v = np.asarray(values, float)
    if not period or v.size == 0:
        return v
    if centre is None:
        centre = float(np.median(unwrapped(v, period, float(v.flat[0]))))
    return v - period * np.round((v - float(centre)) / period)


# ------------------------------------------------------------------- params.yaml


@dataclass
class Params:
    """Parameter values of a named model, with bounds and the fixed (gauge) parameters.

    ``info`` carries everything else params.yaml holds (fit, data, uncertainty, ...)
    through a load/save round trip; ``info["parameter_extras"]`` holds the extra keys
    of each parameter's entry (e.g. std, q05, q95, on_bound).
    """

    model: str
    values: dict
    bounds: dict
    fixed: tuple = ("c0",)
    pixel_size_um: float | None = None
    info: dict = field(default_factory=dict)

    @property
    def free(self) -> list[str]:
        return [k for k in self.values if k not in self.fixed]

    def build(self) -> PrinterModel:
        return get_model(self.model)

    def with_values(self, **values) -> Params:
        v = dict(self.values)
        for k, x in values.items():
            if k not in v:
                raise KeyError(f"unknown parameter {k!r}")
            v[k] = float(x)
        return Params(self.model, v, dict(self.bounds), tuple(self.fixed), self.pixel_size_um, dict(self.info))

    @property
    def gauge(self) -> str:
        return GAUGE_FIXED if "c0" in self.fixed else GAUGE_FREE

    def to_dict(self) -> dict:
        m = self.build()
        params = {}
        for k, spec in m.specs.items():
            lo, hi = self.bounds[k]
            params[k] = dict(value=float(self.values[k]), fixed=k in self.fixed, lower=float(lo), upper=float(hi), unit=spec.unit, doc=spec.doc)
            params[k].update(self.info.get("parameter_extras", {}).get(k, {}))
        extra = [c.formula for c in m.components if getattr(c, "formula", None)]
        d = dict(
            model=self.model,
            equation=EQUATION + "  (Guan et al. 2022, Eq. 1)" + "".join(f"; {f}" for f in extra),
            components=[c.name for c in m.components],
            coordinates=COORDINATES,
            gauge=self.gauge,
            pixel_size_um=self.pixel_size_um,
            parameters=params,
        )
        derived = {}
        if self.pixel_size_um and "sigma_px" in self.values:
            derived["sigma_um"] = float(self.values["sigma_px"]) * float(self.pixel_size_um)
        for k in ("tail_length_px", "edge_offset_px"):
            if self.pixel_size_um and k in self.values:
                derived[k.replace("_px", "_um")] = float(self.values[k]) * float(self.pixel_size_um)
        if "c0" in self.values and "c0" not in self.fixed and self.values["c0"] > 0:
            # the gauge-free numbers: comparable between fits (c0 = 1 convention)
            c0 = float(self.values["c0"])
            derived["per_c0"] = {k: float(self.values[k]) / c0 for k in ("c1", "c2", "c3", "c4", "T") if k in self.values}
        if derived:
            d["derived"] = derived
        d.update({k: v for k, v in self.info.items() if k not in d and k != "parameter_extras"})
        return d


def default_params(model: str = "eq1", free_c0: bool = False, bounds: dict | None = None, pixel_size_um=None) -> Params:
    """Defaults and bounds from the components; c0 fixed to 1 unless ``free_c0``."""
    m = get_model(model)
    values = {k: float(s.default) for k, s in m.specs.items()}
    bnds = {k: tuple(float(x) for x in s.bounds) for k, s in m.specs.items()}
    for k, b in (bounds or {}).items():
        if k not in bnds:
            raise ValueError(f"bounds given for unknown parameter {k!r}; model {model!r} has {list(bnds)}")
        lo, hi = (float(x) for x in b)
        if not lo < hi:
            raise ValueError(f"bounds for {k!r} must be lower < upper, got {b}")
        bnds[k] = (lo, hi)
    fixed = () if free_c0 or "c0" not in values else ("c0",)
    return Params(model, values, bnds, fixed, pixel_size_um)


def save_params(path, params: Params, **info) -> None:
    """Write params.yaml: values, bounds, fixed parameters and the gauge, plus ``info``."""
    from .io import write_yaml

    p = params
    if info:
        p = Params(params.model, params.values, params.bounds, params.fixed, params.pixel_size_um, {**params.info, **info})
    write_yaml(path, p.to_dict())


_STRUCTURAL = ("model", "equation", "components", "coordinates", "gauge", "pixel_size_um", "parameters", "derived")


# The params file in a model folder: a calibration's, or a diagnosis's selected model.
PARAMS_FILES = ("params.yaml", "model.yaml")


def params_path(path) -> Path:
    """The params file a path names: the file itself, or the one in a model folder
    (``calibration/<model>/params.yaml`` or ``diagnosis/model.yaml``)."""
    from .io import InputError

    path = Path(path)
    if not path.is_dir():
        return path
    for name in PARAMS_FILES:
        if (path / name).is_file():
            return path / name
    raise InputError(path, f"a model folder holds {' or '.join(PARAMS_FILES)}; this one has neither")


def load_params(path, check_prints: bool = True) -> Params:
    """Read a params.yaml written by ``save_params`` (checked; errors name the file).
    ``path`` may also be a model folder (``params_path``).

    Every value must lie within its bounds (a kernel far wider than any fit allows would
    try to allocate terabytes), the effects a model.yaml lists must be the model's, and
    with ``check_prints`` the printer must cure a fully exposed large square
    (``check_prints_something``): a model that prints nothing would make every
    compensation an all-white mask without a word.
    """
    from .io import InputError, read_yaml

    path = params_path(path)
    d = read_yaml(path)
    name = d.get("model", "eq1")
    try:
        _, effects = split_model_name(name)
    except KeyError as exc:
        raise InputError(path, f"{exc.args[0]} (effects are added as 'eq1+effect')") from None
    listed = d.get("effects")
    if listed is not None:
        if not isinstance(listed, list) or any(e not in EFFECTS for e in listed):
            raise InputError(path, f"effects {listed!r}: each must be one of {effect_names()}")
        if not set(listed) <= set(effects):  # a diagnosis lists the effects it added to its base model
            raise InputError(path, f"effects {listed} are not all in the model {name!r}")
    m = get_model(name)
    ps = d.get("parameters")
    if not isinstance(ps, dict):
        raise InputError(path, "missing 'parameters' mapping")
    unknown = sorted(set(ps) - set(m.specs))
    if unknown:
        raise InputError(path, f"parameters {unknown} are not parameters of model {name!r}")
    values, bounds, fixed, extras = {}, {}, [], {}
    for k, spec in m.specs.items():
        if k not in ps:
            raise InputError(path, f"parameter {k!r} missing")
        e = ps[k]
        if not isinstance(e, dict):
            e = {"value": e}
        try:
            v = float(e["value"])
        except (KeyError, TypeError, ValueError):
            raise InputError(path, f"parameter {k!r} needs a numeric 'value'") from None
        if not math.isfinite(v):
            raise InputError(path, f"parameter {k!r} is not finite ({v})")
        values[k] = v
        try:
            bounds[k] = lo, hi = (float(e.get("lower", spec.bounds[0])), float(e.get("upper", spec.bounds[1])))
        except (TypeError, ValueError):
            raise InputError(path, f"parameter {k!r}: 'lower' and 'upper' must be numbers") from None
        slack = 1e-9 * max(1.0, abs(lo), abs(hi))  # a value written on its bound reads back on it
        if not lo - slack <= v <= hi + slack:
            raise InputError(path, f"parameter {k!r} = {v:g} lies outside its bounds [{lo:g}, {hi:g}]")
        if e.get("fixed", False):
            fixed.append(k)
        more = {x: y for x, y in e.items() if x not in ("value", "fixed", "lower", "upper", "unit", "doc")}
        if more:
            extras[k] = more
    if values.get("sigma_px", 1.0) < 0:
        raise InputError(path, "sigma_px must be >= 0")
    if values.get("T", 1.0) <= 0:
        raise InputError(path, "the threshold T must be > 0")
    pix = d.get("pixel_size_um")
    if pix is not None and (isinstance(pix, bool) or not isinstance(pix, (int, float)) or not pix > 0):
        raise InputError(path, f"pixel_size_um must be a positive number, found {pix!r}")
    info = {k: v for k, v in d.items() if k not in _STRUCTURAL}
    if extras:
        info["parameter_extras"] = extras
    params = Params(name, values, bounds, tuple(fixed), float(pix) if pix else None, info)
    if check_prints:
        check_prints_something(params, path)
    return params


# A fully exposed square of this side (the paper's design region, Guan et al. 2022) must cure.
FULL_DOSE_SIDE = 512


def check_prints_something(params: Params, source) -> None:
    """InputError naming ``source`` when ``params`` cures nothing under a fully exposed
    FULL_DOSE_SIDE square (e.g. c0 <= 0, or T above any dose the field delivers)."""
    from .io import InputError

    m = params.build()
    reach = m.support_px(params.values)
    if not reach <= 8 * FULL_DOSE_SIDE:  # the padding alone would take gigabytes
        raise InputError(source, f"the scattering kernel reaches {reach:.3g} design pixels: not a printer's "
                                 "(check the kernel's parameters and their bounds)")
    full = np.full((FULL_DOSE_SIDE, FULL_DOSE_SIDE), 255, np.uint8)
    with torch.no_grad():
        dose = m.dose(masks_to_tensor(full, "cpu"), m.theta(params.values, "cpu"))[0]
    peak = float(dose.max())
    if not peak >= params.values["T"]:
        raise InputError(source, f"this printer prints nothing: a fully exposed {FULL_DOSE_SIDE}x{FULL_DOSE_SIDE} square "
                                 f"reaches a dose of {peak:.3g}, below the threshold T = {params.values['T']:.3g} "
                                 "(check c0 and T)")


# ------------------------------------------------------------------------- simulate


def masks_to_tensor(masks, device=None) -> torch.Tensor:
    """uint8 mask(s) (H, W), (B, H, W) or a list -> (B, H, W) float in [0, 1]."""
    if isinstance(masks, (list, tuple)):
        masks = np.stack([np.asarray(m) for m in masks])
    a = np.asarray(masks)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3:
        raise ValueError(f"masks must be (H, W) or (B, H, W), got shape {a.shape}")
    if a.dtype == np.uint8:
        t = torch.from_numpy(a.astype(np.float32) / 255.0)
    elif a.dtype == bool:
        t = torch.from_numpy(a.astype(np.float32))
    else:
        t = torch.from_numpy(np.asarray(a, np.float32))
        if t.numel() and (t.min() < 0 or t.max() > 1):
            raise ValueError("float masks must lie in [0, 1] (M = mask / 255)")
    return t.to(device or default_device())


def simulate(params, masks, device=None, batch: int = 8, temperature: float | None = None, dose_noise: float = 0.0,
             noise_px: float = 2.0, rng=None) -> np.ndarray:
    """Prints of uint8 masks under one parameter set: bool (B, H, W), or (H, W) for one mask.

    ``params``: a Params or a path to params.yaml. With ``temperature`` the smooth
    print (float32 in (0, 1)) is returned instead. With ``dose_noise`` the dose is
    multiplied by 1 + dose_noise x a unit-variance Gaussian field correlated over
    ``noise_px`` pixels (as cells scatter it) before the threshold: noisy prints of the
    model itself, for tests and benchmarks of its fits (``rng``: a numpy Generator or
    seed; None draws a fresh one).
    """
    if not isinstance(params, Params):
        params = load_params(params)
    device = device or default_device()
    single = not isinstance(masks, (list, tuple)) and np.asarray(masks).ndim == 2
    m = params.build()
    theta = m.theta(params.values, device)
    t = masks_to_tensor(masks, "cpu")
    out = []
    if dose_noise:
        from scipy import ndimage

        rng = np.random.default_rng(rng)
    with torch.no_grad():
        for i in range(0, t.shape[0], batch):
            dose = m.dose(t[i : i + batch].to(device), theta)
            if dose_noise:
                n = np.stack([ndimage.gaussian_filter(rng.standard_normal(dose.shape[2:]), noise_px) for _ in range(dose.shape[1])])
                n = torch.as_tensor(n / n.std(axis=(1, 2), keepdims=True), dtype=dose.dtype, device=dose.device)
                dose = dose * (1 + dose_noise * n)
            out.append(m.threshold.apply(dose, theta, temperature)[0].cpu().numpy())
    res = np.concatenate(out) if out else np.zeros((0,) + tuple(t.shape[1:]), bool)
    return res[0] if single else res


# ------------------------------------------------------------------ multi-layer (3-D)
#
# A multi-layer print: layer masks exposed one after the other, bottom first. The light
# of each layer goes into the material below its own layer (the layers cured before it),
# attenuated with depth (Beer-Lambert) and scattered sideways more the deeper it goes.
# A voxel gathers dose from its own layer's exposure and from every layer exposed after
# it; it cures where the accumulated dose reaches T. With one layer this is the 2-D model
# exactly (depth 0: no attenuation, no extra scatter).

DEPTH_PARAMS = (
    ParamSpec("att_length_um", 300.0, (10.0, 5000.0), "um",
              "attenuation length of the light in the material (Beer-Lambert: exp(-depth / att_length_um))"),
    ParamSpec("diffusion_um", 2.0, (0.0, 50.0), "um^2 per um",
              "lateral scatter grows with depth like diffusion: extra Gaussian variance = diffusion_um * depth"),
)
DEPTH_CUTOFF = 1e-4  # the padding covers the scatter down to where exp(-depth / att_length) is this small


def _depth_tensor(depth: dict, name: str, P: int, device) -> torch.Tensor:
    v = depth[name]
    t = v if isinstance(v, torch.Tensor) else torch.as_tensor(np.atleast_1d(np.asarray(v, dtype=np.float64)))
    t = t.to(device=device, dtype=DTYPE).reshape(-1)
    return t.expand(P) if t.numel() == 1 else t


def layer_dose(model: PrinterModel, layers, theta: Theta, depth: dict, layer_um: float, pixel_size_um: float,
               scale: float = 1.0) -> torch.Tensor:
    """(P, L, H, W) accumulated dose of each layer of a multi-layer print.

    ``layers``: (L, H, W) layer masks in [0, 1] (or uint8), bottom first; ``theta``: the
    2-D model's parameters (P sets); ``depth``: ``att_length_um`` and ``diffusion_um``
    (floats or (P,) tensors, ``DEPTH_PARAMS``); ``layer_um``: layer thickness;
    ``pixel_size_um``: the DMD pixel at the sample; ``scale``: design pixels per grid
    pixel (a coarse grid, as ``PrinterModel.dose`` takes it).

    Layer j gets, from the exposure of each layer l >= j at depth d = (l - j) layer_um,
    exp(-d / att_length_um) x [2-D kernel * Gaussian(variance = diffusion_um d)] of that
    layer's exposure (field x dose response x mask); the 2-D model's dose terms and
    threshold then act on the sum. Attenuation and the depth Gaussian both multiply by the
    same factor q(f) per layer of depth, so in Fourier space the sum over the layers above
    is one backward recursion, acc_j = E_j + q acc_(j+1): 2 L FFTs and L multiplications,
    however far the light reaches.
    """
    M = _as_masks(layers)
    L, H, W = M.shape
    P = max(t.numel() for t in theta.values())
    att = _depth_tensor(depth, "att_length_um", P, M.device)
    diff = _depth_tensor(depth, "diffusion_um", P, M.device)
    # pad for the scatter down to where the light is spent (or the bottom layer)
    reach_um = min((L - 1) * float(layer_um), float(att.detach().max()) * -math.log(DEPTH_CUTOFF))
    extra_px = math.sqrt(max(float(diff.detach().max()) * reach_um, 0.0)) / float(pixel_size_um)
    support = model.support_px({k: v.detach().cpu() for k, v in theta.items()}) + 4.0 * extra_px
    shape = padded_shape((H, W), support, scale)
    spec = torch.fft.rfft2(model.exposure(M, theta, scale), s=shape)  # (P, L, Nh, Nw//2+1)
    if L > 1:
        fy = torch.fft.fftfreq(shape[0], device=M.device, dtype=DTYPE) / scale  # cycles per design pixel
        fx = torch.fft.rfftfreq(shape[1], device=M.device, dtype=DTYPE) / scale
        f2 = fy[:, None] ** 2 + fx[None, :] ** 2
        var_px = diff * float(layer_um) / float(pixel_size_um) ** 2  # (P,) extra variance per layer, design px^2
        q = torch.exp(-float(layer_um) / att)[:, None, None] * torch.exp(-2 * math.pi**2 * var_px[:, None, None] * f2)
        accs = [spec[:, L - 1]]
        for j in range(L - 2, -1, -1):
            accs.append(spec[:, j] + q * accs[-1])
        spec = torch.stack(accs[::-1], dim=1)
    return model.blur_spectrum(spec, theta, shape, (H, W), scale)


def layer_prints(model: PrinterModel, layers, theta: Theta, depth: dict, layer_um: float, pixel_size_um: float,
                 temperature: float | None = None, scale: float = 1.0) -> torch.Tensor:
    """(P, L, H, W) voxel print of a multi-layer print: each layer's accumulated dose
    (``layer_dose``) through the 2-D model's threshold (hard, or smooth with a temperature)."""
    if temperature is not None and temperature <= 0:
        raise ValueError("temperature must be > 0 (use None for the hard threshold)")
    return model.threshold.apply(layer_dose(model, layers, theta, depth, layer_um, pixel_size_um, scale), theta,
                                 temperature)
