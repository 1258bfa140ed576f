"""The measurement of a print, as a stage after the printer model (calibration).

A calibration compares simulated prints with *measured* ones: the registration
thresholds a microscope image of the polymer, not the cure itself. The microscope
blurs the polymer's density, and the density is not a step at the print's edge: it
rises from nothing at the gel dose through the print level to saturation. Blurring that
profile moves a threshold's level set as scattering does (corners round further, thin
lines and small near-threshold features image below the level and vanish), so a model
fitted to measured prints as if they were the cure itself puts the microscope's blur
into its scattering kernel: on random labs the fitted sigma was up to 40 % too large
where the microscope's blur is comparable to the scattering (``benchmarks/
bench_calibration_bias.py``).

The measurement stage here is applied to the printer model's dose (Eq. 1 unchanged):

    density   rho = 1 - (1 - level)^(max(D / T - g, 0) / (1 - g))   (rho = level at D = T)
    imaged    I   = G_blur * rho                               (the microscope and the
                                                                registration's smoothing)
    measured  P   = I >= level                                 (the registration's level)

``g`` is the gel dose as a share of T (no polymer below it) and ``level`` the share of
saturated polymer at which the registration thresholds (``registration.level``, 0.5,
the print's definition: so with no blur, P = D >= T exactly, Eq. 1's print). ``blur``
is the Gaussian blur between the density and the thresholded image, in design pixels.

Where the numbers come from: ``registration.yaml`` records the microscope blur the
registration measured (``measurement``: the blur of the images, the smoothing it applies
before the threshold, the gel share of its print template), and the blur batch.yaml
states (``microscope_blur_um``: the PSF's Gaussian sigma at the sample, recorded as
``declared_blur_px``), which the calibration then holds instead of fitting it;
``from_registration`` reads them. The printer model never sees the microscope: the stage wraps its evaluator
(``MeasuredMasks``), and ``simulate`` (the calibrated model) prints without it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from .model import FixedMasks, Theta, fast_len, sampled_gaussian_transfer


BLUR = "meas_blur_px"  # the fitted parameter of the stage: the microscope's blur (design px)
BLUR_BOUNDS = (0.0, 4.0)


@dataclass(frozen=True)
class Measurement:
    """The measurement's numbers. ``blur_px``: the microscope's blur (design px), the start
    and, unless ``fit_blur``, the value; ``smoothing_px``: the registration's own smoothing
    before its threshold (known), added in quadrature; ``gel_share``: the gel dose as a
    share of T; ``level``: the registration's level (share of saturated polymer);
    The registration's level is a share of the dense polymer *as imaged*, so a haze
    (out-of-focus light), which dims dense polymer and the print's edges alike, is left
    out: modelled against saturation it moved T by 10 % on hazy labs."""

    blur_px: float = 1.0
    smoothing_px: float = 0.0
    gel_share: float = 0.6
    level: float = 0.5
    fit_blur: bool = True
    blur_bounds: tuple = BLUR_BOUNDS

    def __post_init__(self):
        for k in ("blur_px", "smoothing_px"):
            v = float(getattr(self, k))
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"measurement {k} must be finite and >= 0, got {v}")
        if not 0.0 <= self.gel_share < 1.0:
            raise ValueError(f"gel share must be in [0, 1), got {self.gel_share}")
        if not 0.0 < self.level < 1.0:
            raise ValueError(f"level must be in (0, 1), got {self.level}")

    def with_blur(self, blur_px: float) -> Measurement:
        return replace(self, blur_px=float(blur_px))

    def as_dict(self) -> dict:
        return dict(blur_px=round(float(self.blur_px), 4), smoothing_px=round(float(self.smoothing_px), 4),
                    gel_share=round(float(self.gel_share), 4), level=float(self.level), blur_fitted=bool(self.fit_blur))


def density(dose: torch.Tensor, T: torch.Tensor, gel_share: float, level: float = 0.5) -> torch.Tensor:
    """Polymer density (share of saturation) from the dose: zero below g T, ``level`` at T."""
    T = T.reshape(-1, *([1] * (dose.dim() - 1)))
    u = torch.clamp(dose / T - gel_share, min=0.0) / (1.0 - gel_share)
    return -torch.expm1(u * math.log1p(-level))


def blur(img: torch.Tensor, sigma_px, step: int = 1) -> torch.Tensor:
    """Gaussian blur of (P, B, h, w) samples ``step`` design px apart, zero outside (FFT,
    padded 4 sigma); ``sigma_px`` (design px) a number or a (P,) tensor, one per
    parameter set (differentiable). On a grid coarser than the design's (``step`` > 1,
    the search's samples) the blur is the continuous Gaussian's, exact for an image
    band-limited on that grid."""
    sig = torch.as_tensor(sigma_px, dtype=img.dtype, device=img.device).reshape(-1)
    h, w = img.shape[-2:]
    pad = min(int(math.ceil(4 * float(sig.detach().max()) / step)) + 1, max(h, w))  # wider: light wraps, thinly
    # a 5-smooth FFT size: h + pad itself can hold a large prime (524 = 4 x 131 took 4 times
    # as long as 540 for 16 images)
    Nh, Nw = fast_len(h + pad, 1), fast_len(w + pad, 1)
    fy = torch.fft.fftfreq(Nh, device=img.device, dtype=img.dtype)
    fx = torch.fft.rfftfreq(Nw, device=img.device, dtype=img.dtype)
    s = sig / step
    if step == 1:  # the sampled kernel, as the registration's (OpenCV's) smoothing applies it
        H = sampled_gaussian_transfer(fy, s)[:, :, None] * sampled_gaussian_transfer(fx, s)[:, None, :]  # (S, Nh, Nw//2+1)
    else:  # samples of a smooth image: the continuous Gaussian's transfer (a sampled kernel this narrow is a delta)
        a = 2 * math.pi**2 * s[:, None, None] ** 2
        H = torch.exp(-a * (fy[None, :, None] ** 2 + fx[None, None, :] ** 2))
    H = H[0] if H.shape[0] == 1 else H[:, None]
    return torch.fft.irfft2(torch.fft.rfft2(img, s=(Nh, Nw)) * H, s=(Nh, Nw))[..., :h, :w]


def total_blur(theta: Theta, m: Measurement) -> torch.Tensor:
    """(P,) blur between density and threshold: the microscope's and the registration's."""
    b = theta[BLUR] if BLUR in theta else torch.tensor([float(m.blur_px)])
    return torch.sqrt(b.clamp_min(0.0) ** 2 + float(m.smoothing_px) ** 2)


def measured(dose: torch.Tensor, theta: Theta, m: Measurement, step: int = 1, temperature: float | None = None) -> torch.Tensor:
    """The measured print of a (P, B, h, w) dose sampled every ``step`` design px: hard
    (bool) or smooth (a sigmoid of the imaged density's distance to the level, the
    temperature a share of the level)."""
    rho = density(dose, theta["T"], m.gel_share, m.level)
    img = blur(rho, total_blur(theta, m).to(rho), step)
    if temperature is None:
        return img >= m.level
    return torch.sigmoid((img - m.level) / (temperature * m.level))


class MeasuredModel:
    """A printer model with the measurement's blur as one more parameter (``BLUR``), so
    the calibration's search fits it with the printer's; everything else is the
    printer model's. A held blur (``fit_blur`` false: stated, or the calibration's in
    the diagnosis) is no parameter: the stage's own value is used."""

    def __init__(self, model, m: Measurement):
        self.inner, self.m = model, m

    @property
    def names(self) -> list[str]:
        return list(self.inner.names) + ([BLUR] if self.m.fit_blur else [])

    def theta(self, values, device=None) -> Theta:
        th = self.inner.theta(values, device)
        vals = values.values if hasattr(values, "values") and not isinstance(values, dict) else values
        b = vals.get(BLUR, self.m.blur_px)
        t = b if isinstance(b, torch.Tensor) else torch.as_tensor(np.atleast_1d(np.asarray(b, dtype=np.float64)))
        t = t.to(device=device, dtype=next(iter(th.values())).dtype).reshape(-1)
        P = max(max(v.numel() for v in th.values()), t.numel())
        th = {k: v.expand(P) if v.numel() == 1 else v for k, v in th.items()}
        th[BLUR] = t.expand(P) if t.numel() == 1 else t
        return th

    def __getattr__(self, name):
        return getattr(self.inner, name)


class MeasuredMasks:
    """A ``model.FixedMasks`` whose prints are the measured ones (``measured``).

    ``decimated(f)`` works on every f-th pixel (at most ``max_step``; then every f-th
    pixel of that grid is returned), blurring those samples with the continuous
    Gaussian: the dose there is exact, the density is not band-limited at its gel point,
    so a coarse grid is an approximation, good enough for the search, which the
    refinement and the final check on every pixel correct."""

    def __init__(self, inner: FixedMasks, m: Measurement, max_step: int = 8, _full: FixedMasks | None = None, _f: int = 1):
        self.m = m
        self.max_step = int(max_step)
        self.full = _full if _full is not None else inner
        self.f = _f
        self.inner = inner  # the dose evaluator, every ``step``-th pixel
        self.step = inner.f
        self.sub = self.f // self.step

    # the evaluator's interface (model.FixedMasks) -----------------------------
    @property
    def model(self):
        return self.inner.model

    @property
    def masks(self):
        return self.inner.masks

    @property
    def shape(self):
        return self.inner.shape

    @property
    def full_shape(self):
        return self.full.full_shape

    @property
    def out_hw(self):
        return (-(-self.full.H // self.f), -(-self.full.W // self.f))

    def dropped(self, theta: Theta, f: int) -> float:
        return self.full.dropped(theta, min(int(f), self.max_step))

    def decimated(self, f: int) -> MeasuredMasks:
        f = int(f)
        step = min(f, self.max_step)
        while f % step:
            step //= 2
        inner = self.full.decimated(step) if step > 1 else self.full
        return MeasuredMasks(inner, self.m, self.max_step, _full=self.full, _f=f)

    def subset(self, idx) -> MeasuredMasks:
        full = self.full.subset(idx)
        inner = full.decimated(self.step) if self.step > 1 else full
        return MeasuredMasks(inner, self.m, self.max_step, _full=full, _f=self.f)

    def dose(self, theta: Theta, masks: slice | None = None) -> torch.Tensor:
        return self.inner.dose(theta, masks)[..., :: self.sub, :: self.sub]

    def prints(self, theta: Theta, temperature: float | None = None, masks: slice | None = None) -> torch.Tensor:
        out = measured(self.inner.dose(theta, masks), theta, self.m, self.step, temperature)
        return out[..., :: self.sub, :: self.sub]


def from_registration(meta: dict | None) -> Measurement | None:
    """The measurement a registration.yaml (``meta``) records, or None (an older
    registration, or prints that no registration measured)."""
    if not meta or not isinstance(meta.get("measurement"), dict):
        return None
    mm = meta["measurement"]
    declared = mm.get("declared_blur_px")
    return Measurement(blur_px=float(mm.get("blur_px", 1.0) if declared is None else declared),
                       smoothing_px=float(mm.get("smoothing_px", 0.0)), gel_share=float(mm.get("gel_share", 0.6)),
                       level=float(mm.get("level", 0.5)), fit_blur=declared is None)


__all__ = ["Measurement", "MeasuredMasks", "MeasuredModel", "BLUR", "density", "blur", "measured", "from_registration"]
