"""The virtual lab in 3-D: multi-layer prints and a confocal microscope.

Printing: the layer masks are exposed one after the other, bottom first. The light of
each layer goes into the layers cured before it (below): it is absorbed by the
photo-initiator and by the cells, and scattered sideways more the deeper it goes. The
photo-initiator bleaches, so a layer that has been exposed many times lets more light
through. Each voxel cures by the dose it has gathered from every exposure after it was
printed (the 2-D lab's polymer density, cell noise and post-wash swelling per layer).
Richer than the model in unscatter.model.layer_dose on purpose: absorption that changes
with exposure (bleaching), a heavy-tailed kernel whose tail does not widen with depth
while its core does, a saturating cure, cell noise in every layer.

Imaging: a confocal z-stack (one 16-bit page a slice, ``z_step_um`` apart) at an unknown
lateral pose and an unknown z offset of the print's bottom; the axial blur (Gaussian,
``axial_sigma_um``) is wider than the lateral one; deeper slices are dimmer.

Only unscatter.lab and its tests read the config (``default.yaml``, section ``layers``).
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import cv2
import numpy as np
from scipy import fft, ndimage
from scipy.special import ndtr

from .microscope import digitize, draw_pose, similarity
from .printer import Printer

LIGHT_CUTOFF = 1e-4  # deeper layers than where the transmission falls below this get no light


class LayerPrinter:
    """Prints a stack of layer masks (L, S, S) into polymer density (L, S + 2 pad, ...)."""

    def __init__(self, printer_cfg: dict, layers_cfg: dict, size: int, pixel_size_um: float):
        self.printer = Printer(printer_cfg, size, pixel_size_um)
        self.cfg = layers_cfg
        self.dz = float(layers_cfg["layer_um"])
        self._kernels: dict[int, np.ndarray] = {0: self.printer.kernel_ft}

    def transmission(self, exposed_layer: int, target_layer: int) -> float:
        """Share of the light of layer ``exposed_layer``'s exposure that reaches
        ``target_layer`` below it: through the layers in between (and the target's upper
        half is ignored, as in 2-D), each absorbing by initiator and cells; the initiator
        of a layer exposed n times before is bleached to (1 - bleaching)^n."""
        c = self.cfg
        mu = 0.0
        for i in range(target_layer, exposed_layer):
            times = exposed_layer - i  # exposures layer i has had before this one
            mu += c["absorbance_cells_per_um"] + c["absorbance_initiator_per_um"] * (1 - c["bleaching"]) ** times
        return math.exp(-mu * self.dz)

    def kernel_ft(self, k: int) -> np.ndarray:
        """The kernel at k layers of depth: the core's sigma^2 grows by growth_um x depth."""
        if k not in self._kernels:
            s0 = float(self.printer.cfg["kernel"]["sigma_um"])
            sig = math.sqrt(s0**2 + float(self.cfg["scatter_growth_um"]) * k * self.dz)
            self._kernels[k] = self.printer._kernel_ft(sig)
        return self._kernels[k]

    def density(self, layers: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(L, padded) polymer density after the wash. With one layer: the 2-D lab's
        ``Printer.density`` exactly (same random numbers)."""
        p = self.printer
        L = len(layers)
        spectra = [fft.rfft2(p.exposure(m)) for m in layers]
        out = np.empty((L, *p.shape))
        noises = [p.cell_noise(rng) for _ in range(L)]
        scale = 1.0 + p.cfg["cells"]["print_to_print"] * rng.standard_normal()
        for j in range(L):
            acc = spectra[j] * self.kernel_ft(0)
            for l in range(j + 1, L):
                t = self.transmission(l, j)
                if t < LIGHT_CUTOFF:
                    break
                acc = acc + t * spectra[l] * self.kernel_ft(l - j)
            dose = np.maximum(fft.irfft2(acc, s=p.shape) * (1.0 + noises[j]) * scale, 0.0)
            out[j] = p.cure(dose)
        return out

    def crop(self, padded: np.ndarray) -> np.ndarray:
        q = self.printer.pad
        s = self.printer.size
        return padded[..., q : q + s, q : q + s]


def axial_weights(z_um: np.ndarray, layers: int, layer_um: float, sigma_um: float) -> np.ndarray:
    """(Nz, L) share of the axial PSF at focal depth z that falls in each layer (the
    confocal's axial response, a Gaussian of ``sigma_um``, integrated over the layer)."""
    lo = np.arange(layers) * layer_um
    z = np.asarray(z_um, float)[:, None]
    return ndtr((lo[None] + layer_um - z) / sigma_um) - ndtr((lo[None] - z) / sigma_um)


def image_stack(density_padded: np.ndarray, pad: int, design_px: int, pixel_size_um: float, layer_um: float,
                mic: dict, conf: dict, rng: np.random.Generator):
    """A confocal z-stack of a multi-layer print: (uint16 (Nz, H, W), pose, 2x3 matrix).

    The stack starts ``margin_um`` below the print's bottom plus an unknown offset and
    covers the print and ``margin_um`` above it; the pose (rotation, scale, shift) is
    drawn as the 2-D microscope draws it and is the same for every slice."""
    L = density_padded.shape[0]
    H, W = mic["image_size"]
    pose = draw_pose(mic, design_px, rng)
    z_off = float(rng.uniform(-conf["z_offset_um"], conf["z_offset_um"]))
    z0 = -float(conf["margin_um"]) + z_off
    nz = int(math.ceil((L * layer_um + 2 * conf["margin_um"]) / conf["z_step_um"])) + 1
    z = z0 + np.arange(nz) * float(conf["z_step_um"])
    w = axial_weights(z, L, layer_um, float(conf["axial_sigma_um"]))  # (Nz, L)
    s = pose["scale"]
    M = similarity(pose["rotation_deg"], s, ((design_px - 1) / 2,) * 2,
                   ((W - 1) / 2 + pose["shift_x"], (H - 1) / 2 + pose["shift_y"]))
    M_pad = M.copy()
    M_pad[:, 2] -= M[:, :2] @ np.array([pad, pad], float)
    lateral = float(conf["lateral_sigma_um"]) / pixel_size_um  # in DMD pixels
    rho = np.stack([ndimage.gaussian_filter(d, lateral) for d in density_padded])
    vig = float(rng.uniform(*mic["vignetting"]))
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    v = 1.0 - vig * ((yy - (H - 1) / 2) ** 2 + (xx - (W - 1) / 2) ** 2) / ((H / 2) ** 2 + (W / 2) ** 2)
    out = np.empty((nz, H, W), np.uint16)
    for k in range(nz):
        sl = np.tensordot(w[k], rho, axes=1)
        warped = cv2.warpAffine(sl.astype(np.float32), M_pad, (W, H), flags=cv2.INTER_LINEAR, borderValue=0.0)
        depth = max(z[k], 0.0)
        bright = math.exp(-depth / float(conf["signal_length_um"]))  # deeper slices are dimmer
        lamp = max(0.2, 1.0 + float(conf["slice_jitter"]) * rng.standard_normal())
        e = mic["photons"] * lamp * v * (bright * warped + mic["background"])
        counts = rng.poisson(np.maximum(e, 0)) + rng.normal(0, mic["read_noise_e"], size=(H, W))
        out[k] = digitize(counts, mic)
    return out, dict(pose, z0_um=z0, z_offset_um=z_off, slices=nz, vignetting=vig), M


def layer_ids(folder: Path) -> list[Path]:
    """The layer masks of a multi-layer mask folder, bottom first (sorted by name)."""
    return sorted(p for p in Path(folder).glob("*.png") if not p.name.startswith("."))


def run_layers(mask_root: Path, out_batch: Path, truth_dir: Path, cfg: dict, progress=True, inputs=(),
               source="lab config") -> list[dict]:
    """Print and image every multi-layer mask folder ``mask_root/<id>/`` (layer PNGs,
    bottom first) into the batch ``out_batch`` (masks/<id>/, images/<id>.tif z-stacks,
    batch.yaml with layer_um and z_step_um) and its truth (prints/<id>/ voxel prints a
    layer, density/<id>.npy, transforms.tsv with the pose and the z offset)."""
    import tifffile
    from tqdm import tqdm

    from ..io import InputError, check_batch_meta, output_dir, read_mask, write_png, write_tsv, write_yaml
    from .run import mask_rng

    folders = sorted(p for p in Path(mask_root).iterdir() if p.is_dir() and not p.name.startswith("."))
    if not folders:
        raise InputError(mask_root, "no multi-layer mask folders (<id>/ with one PNG a layer) to print")
    lay, conf, mic = cfg["layers"], cfg["layers"]["confocal"], cfg["microscope"]
    meta = dict(cfg["batch"], layer_um=float(lay["layer_um"]), z_step_um=float(conf["z_step_um"]))
    if mic.get("declare_offset", True):
        meta["camera_offset_adu"] = mic["offset_adu"]
    meta["notes"] = f"virtual lab, multi-layer prints, seed {cfg['seed']}"
    check_batch_meta(meta, source)
    stacks = {}
    for f in folders:
        files = layer_ids(f)
        if not files:
            raise InputError(f, "no layer masks (.png) in this print's folder")
        stacks[f.name] = (files, np.stack([read_mask(p) for p in files]))
        if stacks[f.name][1].shape[1] != stacks[f.name][1].shape[2]:
            raise InputError(f, "layer masks must be square")
    size = next(iter(stacks.values()))[1].shape[1]
    printer = LayerPrinter(cfg["printer"], lay, size, meta["pixel_size_um"])
    level = float(mic["level"])
    rows = []
    with (output_dir(out_batch, command="lab print", inputs=[mask_root, *inputs, truth_dir]) as batch,
          output_dir(truth_dir, command="lab print", inputs=[mask_root, *inputs, out_batch]) as truth_out):
        for sub in (batch / "masks", batch / "images", truth_out / "prints", truth_out / "density"):
            sub.mkdir()
        for mid, (files, layers) in tqdm(stacks.items(), desc="virtual lab: printing layers", disable=not progress):
            if layers.shape[1:] != (size, size):
                raise InputError(mask_root / mid, f"layers are {layers.shape[1:]}, the batch's are {size}x{size}")
            rng = mask_rng(cfg["seed"], mid)
            rho = printer.density(layers, rng)
            truth = printer.crop(rho) >= level
            img, pose, M = image_stack(rho, printer.printer.pad, size, meta["pixel_size_um"], lay["layer_um"], mic,
                                       conf, rng)
            (batch / "masks" / mid).mkdir()
            (truth_out / "prints" / mid).mkdir()
            for i, p in enumerate(files):
                shutil.copyfile(p, batch / "masks" / mid / p.name)
                write_png(truth_out / "prints" / mid / f"{i:03d}.png", truth[i])
            tifffile.imwrite(batch / "images" / f"{mid}.tif", img, photometric="minisblack")
            np.save(truth_out / "density" / f"{mid}.npy", printer.crop(rho).astype(np.float32))
            rows.append(dict(id=mid, layers=len(files), **pose, m00=M[0, 0], m01=M[0, 1], m02=M[0, 2], m10=M[1, 0],
                             m11=M[1, 1], m12=M[1, 2], solid_fraction=float(truth.mean())))
        write_yaml(batch / "batch.yaml", meta)
        write_tsv(truth_out / "transforms.tsv", rows)
        write_yaml(truth_out / "lab_config.yaml", cfg)
    return rows
