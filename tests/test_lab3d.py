"""The virtual lab in 3-D (unscatter.lab.layers): multi-layer prints and confocal z-stacks."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from unscatter.io import read_batch_meta, read_print, write_png
from unscatter.lab import Printer, load_config, print_layers
from unscatter.lab.layers import LayerPrinter, axial_weights

SIZE, PX = 96, 2.96


def _cfg(**layers):
    cfg = load_config()
    cfg["printer"]["pad_px"] = 48
    cfg["layers"].update(layers)
    return cfg


def _bridge(L=5, size=SIZE):
    """Two pillars L-1 layers tall and a span across them in the top layer: an overhang."""
    m = np.zeros((L, size, size), np.uint8)
    m[:, 30:66, 10:24] = 255
    m[:, 30:66, 72:86] = 255
    m[-1, 30:66, 10:86] = 255
    return m


def test_one_layer_is_the_2d_lab():
    cfg = _cfg()
    mask = _bridge(1)
    two = Printer(cfg["printer"], SIZE, PX).density(mask[0], np.random.default_rng(3))
    three = LayerPrinter(cfg["printer"], cfg["layers"], SIZE, PX).density(mask, np.random.default_rng(3))
    assert three.shape == (1, *two.shape) and np.array_equal(three[0], two)


def test_light_reaches_down_and_overhangs_grow_with_transparency():
    cfg = load_config()
    thick = {}
    for name, mu in (("clear", 0.0005), ("opaque", 0.05)):
        c = _cfg(absorbance_initiator_per_um=mu, absorbance_cells_per_um=0.0)
        lp = LayerPrinter(c["printer"], c["layers"], SIZE, PX)
        cured = lp.crop(lp.density(_bridge(), np.random.default_rng(0))) >= cfg["microscope"]["level"]
        thick[name] = int(cured[:, 48, 48].sum())  # under the middle of the span
    assert thick["opaque"] == 1  # only the span's own layer
    assert thick["clear"] > 1  # light through the span cured the layers below it


def test_bleaching_lets_more_light_through_older_layers():
    c = _cfg(bleaching=0.5)
    lp = LayerPrinter(c["printer"], c["layers"], SIZE, PX)
    # the same depth (one layer) is more transparent once that layer has been exposed more
    assert lp.transmission(4, 3) < lp.transmission(4, 0) ** (1 / 4)
    assert 0 < lp.transmission(3, 0) < lp.transmission(3, 2) < 1


def test_deeper_layers_scatter_more():
    c = _cfg(scatter_growth_um=10.0)
    lp = LayerPrinter(c["printer"], c["layers"], SIZE, PX)
    k0, k3 = np.abs(lp.kernel_ft(0)), np.abs(lp.kernel_ft(3))
    assert k3[0, 0] == pytest.approx(k0[0, 0])  # both conserve light
    assert k3[5, 5] < k0[5, 5]  # the deeper kernel passes less fine detail


def test_axial_weights_sum_to_one_inside_a_thick_print():
    w = axial_weights(np.array([100.0, 125.0]), 10, 25.0, 8.0)
    assert w.sum(axis=1) == pytest.approx([1.0, 1.0], abs=1e-6)
    assert w[0].argmax() == 3 or w[0].argmax() == 4


def test_print_layers_writes_the_z_stack_contract(tmp_path):
    root = tmp_path / "masks"
    for mid, L in (("bridge", 4), ("tower", 3)):
        m = _bridge(L)
        for i in range(L):
            write_png(root / mid / f"{i:03d}.png", m[i])
    over = dict(printer=dict(pad_px=48), microscope=dict(image_size=[160, 160]),
                layers=dict(layer_um=25, confocal=dict(z_step_um=10, margin_um=20, z_offset_um=5)))
    rows = print_layers(root, tmp_path / "batch", overrides=over, progress=False)
    assert [r["id"] for r in rows] == ["bridge", "tower"]
    meta = read_batch_meta(tmp_path / "batch")
    assert meta.layer_um == 25 and meta.z_step_um == 10
    stack = tifffile.imread(tmp_path / "batch" / "images" / "bridge.tif")
    assert stack.dtype == np.uint16 and stack.ndim == 3 and stack.shape[1:] == (160, 160)
    assert stack.shape[0] == rows[0]["slices"] >= (4 * 25 + 40) // 10
    # the stack is brightest where the print is, dim beyond it (axial blur, a margin each side)
    prof = stack.reshape(len(stack), -1).astype(float).mean(1)
    assert prof.argmax() not in (0, len(prof) - 1) and prof.max() - max(prof[0], prof[-1]) > 30  # ADU, noise ~0.2
    assert sorted(p.name for p in (tmp_path / "batch" / "masks" / "bridge").iterdir()) == [f"{i:03d}.png" for i in range(4)]
    truth = read_print(tmp_path / "batch.truth" / "prints" / "bridge" / "003.png")
    assert truth.shape == (SIZE, SIZE) and truth.any()
