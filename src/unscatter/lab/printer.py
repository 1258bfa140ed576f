"""The virtual printer: mask -> absorbed dose -> polymer density (the lab's physics)."""

from __future__ import annotations

import numpy as np
from scipy import fft, ndimage


def polymer_density(dose: np.ndarray, threshold: float, gel_dose: float) -> np.ndarray:
    """Degree of cure in [0, 1): zero below the gel dose, half of saturation at ``threshold``.

    rho = 1 - exp(-ln2 (D - D_gel) / (T - D_gel)) for D > D_gel. Below the gel dose the
    bioink does not gel and is washed away.
    """
    if not gel_dose < threshold:
        raise ValueError("cure.gel_dose must be below cure.threshold")
    x = np.maximum(dose - gel_dose, 0.0) / (threshold - gel_dose)
    return -np.expm1(-np.log(2.0) * x)


class Printer:
    """Pads the design region, applies illumination, dose response, scattering, cure."""

    def __init__(self, cfg: dict, size: int, pixel_size_um: float):
        self.cfg = cfg
        self.size = size
        self.pixel_um = float(pixel_size_um)
        self.pad = int(cfg["pad_px"])
        n = size + 2 * self.pad
        self.shape = (fft.next_fast_len(n, real=True),) * 2
        self.field = self._illumination()
        self.kernel_ft = self._kernel_ft()
        grow = float(cfg.get("kernel_dose_growth") or 0.0)
        self.wide_ft = self._kernel_ft(cfg["kernel"]["sigma_um"] * (1.0 + grow)) if grow > 0 else None

    # -- optics --------------------------------------------------------------
    def _illumination(self) -> np.ndarray:
        c = self.cfg["illumination"]
        s = self.size
        # X along columns, Y along rows, both -1..1 over the design region's pixel centres
        ax = (np.arange(s) - (s - 1) / 2) / ((s - 1) / 2)
        X, Y = np.meshgrid(ax, ax)
        f = c["c0"] + c["cx"] * X + c["cy"] * Y + c["cx2"] * X**2 + c["cy2"] * Y**2
        f = f + c.get("quartic", 0.0) * (X**2 + Y**2) ** 2
        hs = c.get("hotspot")
        if hs:
            f = f + hs["amplitude"] * np.exp(-((X - hs["x0"]) ** 2 + (Y - hs["y0"]) ** 2) / (2 * hs["width"] ** 2))
        return np.maximum(f, 0.0)

    def _kernel_ft(self, sigma_um: float | None = None) -> np.ndarray:
        """The scattering kernel's rfft2 on the padded grid; ``sigma_um`` replaces the
        core's sigma (deeper layers of a multi-layer print scatter more)."""
        k = self.cfg["kernel"]
        H, W = self.shape
        yy = np.fft.fftfreq(H, 1.0 / H)  # signed pixel offsets with wrap
        xx = np.fft.fftfreq(W, 1.0 / W)
        X, Y = np.meshgrid(xx, yy)
        sig = (k["sigma_um"] if sigma_um is None else sigma_um) / self.pixel_um
        an = k.get("anisotropy") or {}
        ratio = float(an.get("ratio", 1.0))
        th = np.deg2rad(float(an.get("angle_deg", 0.0)))
        u = np.cos(th) * X + np.sin(th) * Y
        v = -np.sin(th) * X + np.cos(th) * Y
        su, sv = sig * np.sqrt(ratio), sig / np.sqrt(ratio)  # same area as the isotropic kernel
        core = np.exp(-0.5 * ((u / su) ** 2 + (v / sv) ** 2))
        core /= core.sum()
        ht = k.get("heavy_tail")
        if ht and ht.get("fraction", 0) > 0:
            lam = ht["length_um"] / self.pixel_um
            tail = np.exp(-np.hypot(X, Y) / lam)
            tail /= tail.sum()
            kern = (1 - ht["fraction"]) * core + ht["fraction"] * tail
        else:
            kern = core
        return fft.rfft2(kern)

    # -- printing ------------------------------------------------------------
    def dose(self, mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Absorbed dose on the padded grid (1 = full grey at the centre, large area)."""
        e = self.exposure(mask)
        if self.wide_ft is not None:  # effect: brighter pixels scatter wider (sigma grows with grey)
            g = np.zeros(self.shape)
            p = self.pad
            g[p : p + self.size, p : p + self.size] = mask.astype(np.float64) / 255.0
            d = fft.irfft2(fft.rfft2(e * (1 - g)) * self.kernel_ft + fft.rfft2(e * g) * self.wide_ft, s=self.shape)
        else:
            d = fft.irfft2(fft.rfft2(e) * self.kernel_ft, s=self.shape)
        ox = self.cfg.get("oxygen_inhibition")
        if ox and ox.get("strength", 0) > 0:
            # effect: oxygen diffusing in from the uncured ink around a feature consumes
            # radicals near its edges: the dose lost grows as the neighbourhood (over
            # length_um) is less exposed, so thin lines and corners lose most
            T = float(self.cfg["cure"]["threshold"])
            near = ndimage.gaussian_filter(np.minimum(d / T, 1.0), float(ox["length_um"]) / self.pixel_um)
            d = d * (1.0 - float(ox["strength"]) * (1.0 - near))
        noise = self.cell_noise(rng)
        scale = 1.0 + self.cfg["cells"]["print_to_print"] * rng.standard_normal()
        return np.maximum(d * (1.0 + noise) * scale, 0.0)

    def exposure(self, mask: np.ndarray) -> np.ndarray:
        """Light delivered into the padded grid before scattering: field x (grey / 255)^gamma."""
        if mask.shape != (self.size, self.size):
            raise ValueError(f"mask must be {self.size}x{self.size}, got {mask.shape}")
        out = np.zeros(self.shape)
        p = self.pad
        g = (mask.astype(np.float64) / 255.0) ** float(self.cfg.get("dose_gamma", 1.0))
        out[p : p + self.size, p : p + self.size] = g * self.field
        return out

    def cell_noise(self, rng: np.random.Generator) -> np.ndarray:
        """Cells absorb and redirect light locally: a relative dose field correlated over a cell."""
        cells = self.cfg["cells"]
        noise = ndimage.gaussian_filter(rng.standard_normal(self.shape), cells["cell_um"] / self.pixel_um / 2)
        return noise * (cells["dose_noise"] / max(noise.std(), 1e-12))

    def density(self, mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Polymer density after the wash, on the padded grid."""
        return self.cure(self.dose(mask, rng))

    def cure(self, dose: np.ndarray) -> np.ndarray:
        """Polymer density after the wash from the absorbed dose (padded grid)."""
        cure = self.cfg["cure"]
        rho = polymer_density(dose, cure["threshold"], cure["gel_dose"])
        off = float(self.cfg.get("edge_offset_um", 0.0)) / self.pixel_um
        r = int(round(abs(off)))
        if r > 0:  # the gel swells (or erodes) after the wash by a fixed distance
            yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
            foot = xx**2 + yy**2 <= r * r
            rho = ndimage.grey_dilation(rho, footprint=foot) if off > 0 else ndimage.grey_erosion(rho, footprint=foot)
        return rho

    def crop(self, padded: np.ndarray) -> np.ndarray:
        p = self.pad
        return padded[p : p + self.size, p : p + self.size]
