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

Later effects (a heavy-tailed kernel term, an anisotropic kernel, a gamma dose
response, illumination beyond quadratic, an edge offset) are new components added to
the list; ``register_model`` names the combination. Everything that simulates a print
(calibration, augmentation, mask optimisation, benchmarks) goes through this module.
"""

from __future__ import annotations

import math
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


Theta = dict  # parameter name -> tensor of shape (P,): P parameter sets at once


class Component:
    """A piece of the printer model that contributes parameters.

    ``stage`` is one of "field", "response", "kernel", "threshold".
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
        raise NotImplementedError


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
        by_stage = {s: [c for c in self.components if c.stage == s] for s in ("field", "response", "kernel", "threshold")}
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
        return self.response.apply(masks, theta)[None] * f[:, None]

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

    def blur_spectrum(self, spectrum: torch.Tensor, theta: Theta, shape, out_hw, scale: float = 1.0) -> torch.Tensor:
        """Kernel applied to (P, B, Nh, Nw//2+1) exposure spectra -> (P, B, H, W) dose."""
        Ht = self.transfer(shape, theta, scale, spectrum.device)
        # irfft2 in two passes, dropping the padding rows in between (less work, same result)
        x = torch.fft.ifft(spectrum * Ht[:, None], dim=-2)[..., : out_hw[0], :]
        return torch.fft.irfft(x, n=shape[1], dim=-1)[..., : out_hw[1]]

    def dose(self, masks: torch.Tensor, theta: Theta, scale: float = 1.0, shape=None) -> torch.Tensor:
        """(P, B, H, W) absorbed dose Gauss_sigma(ReLU(field) * M), zero padded (no wrap)."""
        masks = _as_masks(masks)
        _, H, W = masks.shape
        if shape is None:
            shape = padded_shape((H, W), self.support_px({k: v.detach().cpu() for k, v in theta.items()}), scale)
        spec = torch.fft.rfft2(self.exposure(masks, theta, scale), s=shape)
        return self.blur_spectrum(spec, theta, shape, (H, W), scale)

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

    def __init__(self, model: PrinterModel, masks: torch.Tensor, support_px: float = 48.0):
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
        bases = [ft.basis(self.X, self.Y) for ft in model.fields]
        if all(b is not None for b in bases) and not model.response.params:
            basis = {k: v for b in bases for k, v in b.items()}
            self.basis_names = list(basis)
            M = model.response.apply(self.masks, {})
            # (K, B, Nh, Nw//2+1) complex, stored as real pairs for one matrix product
            spec = torch.stack([torch.fft.rfft2(v[None] * M, s=self.shape) for v in basis.values()])
            self.spectra = torch.view_as_real(spec).contiguous()

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
            new.spectra = torch.view_as_real(self._band(torch.view_as_complex(self.spectra), f)).contiguous()
        return new

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
        if self.spectra is not None:
            new.spectra = self.spectra[:, idx].contiguous()
        return new

    def dose(self, theta: Theta, masks: slice | None = None) -> torch.Tensor:
        """(P, B, h, w) absorbed dose for P parameter sets (at every f-th pixel); ``masks``
        restricts it to a block of the masks (smaller temporaries)."""
        if self.support_px + 1e-6 < self.model.support_px({k: v.detach().cpu() for k, v in theta.items()}):
            raise ValueError("a kernel is wider than this evaluator's padding; build it with a larger support_px")
        sl = masks if masks is not None else slice(None)
        M = self.masks[sl]
        if not self.fast:
            d = self.model.dose(M, theta, shape=self.full_shape)
            return d[..., :: self.f, :: self.f]
        K = len(self.basis_names)
        c = torch.stack([theta[k] for k in self.basis_names], dim=1)  # (P, K)
        P = c.shape[0]
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
        return self.model.blur_spectrum(spec, theta, self.shape, self.out_hw, self.f)

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
    if name not in _MODELS:
        raise KeyError(f"unknown printer model {name!r}; known: {model_names()}")
    return PrinterModel(_MODELS[name](), name=name)


register_model("eq1", lambda: [QuadraticField(), LinearDose(), GaussianKernel(), Threshold()])  # Guan et al. 2022, Eq. 1


def eq1() -> PrinterModel:
    """The paper's simulator, Eq. 1."""
    return get_model("eq1")


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
        d = dict(
            model=self.model,
            equation=EQUATION + "  (Guan et al. 2022, Eq. 1)",
            components=[c.name for c in m.components],
            coordinates=COORDINATES,
            gauge=self.gauge,
            pixel_size_um=self.pixel_size_um,
            parameters=params,
        )
        derived = {}
        if self.pixel_size_um and "sigma_px" in self.values:
            derived["sigma_um"] = float(self.values["sigma_px"]) * float(self.pixel_size_um)
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


def load_params(path) -> Params:
    """Read a params.yaml written by ``save_params`` (checked; errors name the file)."""
    from .io import InputError, read_yaml

    path = Path(path)
    d = read_yaml(path)
    name = d.get("model", "eq1")
    if name not in _MODELS:
        raise InputError(path, f"unknown model {name!r}; known: {model_names()}")
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
        bounds[k] = (float(e.get("lower", spec.bounds[0])), float(e.get("upper", spec.bounds[1])))
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
    info = {k: v for k, v in d.items() if k not in _STRUCTURAL}
    if extras:
        info["parameter_extras"] = extras
    return Params(name, values, bounds, tuple(fixed), float(pix) if pix else None, info)


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


def simulate(params, masks, device=None, batch: int = 8, temperature: float | None = None) -> np.ndarray:
    """Prints of uint8 masks under one parameter set: bool (B, H, W), or (H, W) for one mask.

    ``params``: a Params or a path to params.yaml. With ``temperature`` the smooth
    print (float32 in (0, 1)) is returned instead.
    """
    if not isinstance(params, Params):
        params = load_params(params)
    device = device or default_device()
    single = not isinstance(masks, (list, tuple)) and np.asarray(masks).ndim == 2
    m = params.build()
    theta = m.theta(params.values, device)
    t = masks_to_tensor(masks, "cpu")
    out = []
    with torch.no_grad():
        for i in range(0, t.shape[0], batch):
            p = m.prints(t[i : i + batch].to(device), theta, temperature)[0]
            out.append(p.cpu().numpy())
    res = np.concatenate(out) if out else np.zeros((0,) + tuple(t.shape[1:]), bool)
    return res[0] if single else res
