"""Augmentation masks and the Zarr dataset of masks and simulated prints."""

import numpy as np
import pytest
import zarr

import unscatter
from unscatter.augment import FORMAT, augment, open_dataset, split_indices
from unscatter.io import InputError
from unscatter.masks import (
    AUGMENT_FAMILIES,
    augmentation_families,
    augmentation_mask,
    family_counts,
    horizontal_lines,
    vertical_lines,
)
from unscatter.model import default_params, save_params, simulate


@pytest.fixture(scope="module")
def params_yaml(tmp_path_factory):
    """A plausible calibrated Eq. 1: sigma ~4 px, T 0.5, c0 = 1, a slightly curved field."""
    p = default_params(pixel_size_um=2.96).with_values(c1=-0.06, c2=-0.04, c3=0.03, c4=-0.02, sigma_px=4.0, T=0.5)
    path = tmp_path_factory.mktemp("calib") / "params.yaml"
    save_params(path, p)
    return path


@pytest.fixture(scope="module")
def store(params_yaml, tmp_path_factory):
    out = tmp_path_factory.mktemp("aug") / "eq1.zarr"
    summary = augment(params_yaml, out, count=30, seed=4, size=256, workers=2, progress=False)
    return out, summary


# ------------------------------------------------------------------------- families


@pytest.mark.parametrize("family", list(AUGMENT_FAMILIES))
def test_every_family_draws_nonempty_uint8_masks(family):
    for i in range(5):
        m = augmentation_mask(family, seed=3, index=i, size=256)
        assert m.shape == (256, 256) and m.dtype == np.uint8
        assert m.max() > 0


def test_families_are_seeded_and_distinct():
    a = augmentation_mask("vasculature", seed=1, index=7)
    assert np.array_equal(a, augmentation_mask("vasculature", seed=1, index=7))
    assert not np.array_equal(a, augmentation_mask("vasculature", seed=2, index=7))
    assert not np.array_equal(a, augmentation_mask("vasculature", seed=1, index=8))


def test_horizontal_lines_are_the_vertical_family_turned():
    v = vertical_lines(np.random.default_rng(5), 128)
    h = horizontal_lines(np.random.default_rng(5), 128)
    assert np.array_equal(h, v.T)
    # vertical lines: every column inside the lines' window is constant along the rows it covers
    rows = np.flatnonzero(v.any(axis=1))
    assert (v[rows] == v[rows[0]]).all()


def test_family_counts_are_exact_and_proportional():
    c = family_counts(4000)
    assert sum(c.values()) == 4000 and set(c) == set(AUGMENT_FAMILIES)
    assert max(c.values()) - min(c.values()) <= 1
    assert family_counts(10, {"circles": 7, "vasculature": 3}) == {"circles": 7, "vasculature": 3}
    assert family_counts(9, {"circles": 2, "vasculature": 1}) == {"circles": 6, "vasculature": 3}
    with pytest.raises(ValueError, match="unknown augmentation family"):
        family_counts(10, ["triangles"])
    labels = augmentation_families(700, seed=0)
    assert len(set(labels[:70])) == len(AUGMENT_FAMILIES)  # a prefix mixes every family


def test_split_is_ten_percent_disjoint_and_seeded():
    train, test = split_indices(4000)
    assert len(train) == 3600 and len(test) == 400  # Guan et al. 2022: 3,600 / 400
    assert not set(train) & set(test) and len(set(train) | set(test)) == 4000
    assert np.array_equal(split_indices(4000, seed=0)[1], test)
    assert not np.array_equal(split_indices(4000, seed=1)[1], test)


# --------------------------------------------------------------------------- store


def test_store_layout_dtypes_and_chunks(store):
    path, _ = store
    g = zarr.open_group(str(path), mode="r")
    assert g["masks"].shape == (30, 256, 256) and g["masks"].dtype == np.uint8
    assert g["prints"].shape == (30, 256, 256) and g["prints"].dtype == np.bool_
    assert g["masks"].chunks == (1, 256, 256) and g["prints"].chunks == (1, 256, 256)
    train, test = g["train"][:], g["test"][:]
    assert len(test) == 3 and len(train) == 27
    assert sorted(np.concatenate([train, test]).tolist()) == list(range(30))
    assert g["family"].shape == (30,)


def test_store_attributes(store, params_yaml):
    path, summary = store
    a = dict(zarr.open_group(str(path), mode="r").attrs)
    assert a["format"] == FORMAT and a["complete"] is True
    assert a["unscatter_version"] == unscatter.__version__
    assert a["seed"] == 4 and a["count"] == 30 and a["size"] == 256
    assert a["params"]["parameters"]["sigma_px"]["value"] == pytest.approx(4.0)
    assert a["params"]["model"] == "eq1"
    assert sum(a["families"].values()) == 30 and list(a["family_names"]) == list(AUGMENT_FAMILIES)
    assert a["test_fraction"] == pytest.approx(0.1) and a["n_train"] == 27 and a["n_test"] == 3
    assert summary["elapsed_s"] > 0
    assert not (path.parent / (path.name + ".partial")).exists()


def test_prints_are_the_models_hard_threshold_prints(store, params_yaml):
    ds = open_dataset(store[0])
    masks, prints = ds.pairs([0, 17, 5])
    assert np.array_equal(prints, simulate(params_yaml, list(masks), device="cpu"))
    names = ds.attrs["family_names"]
    fam = ds.group["family"][:]
    for k, i in enumerate([0, 17, 5]):
        assert np.array_equal(masks[k], augmentation_mask(names[fam[i]], 4, i, 256))
    assert ds.params().values["sigma_px"] == pytest.approx(4.0)


def test_same_seed_same_arrays_whatever_the_workers(store, params_yaml, tmp_path):
    path, _ = store
    again = tmp_path / "again.zarr"
    augment(params_yaml, again, count=30, seed=4, size=256, workers=1, progress=False)
    a, b = zarr.open_group(str(path), mode="r"), zarr.open_group(str(again), mode="r")
    for k in ("masks", "prints", "family", "train", "test"):
        assert np.array_equal(a[k][:], b[k][:]), k
    other = tmp_path / "other.zarr"
    augment(params_yaml, other, count=30, seed=5, size=256, progress=False)
    assert not np.array_equal(a["masks"][:], zarr.open_group(str(other), mode="r")["masks"][:])


def test_families_option_restricts_the_set(params_yaml, tmp_path):
    s = augment(params_yaml, tmp_path / "v.zarr", count=6, seed=0, size=128, families={"vasculature": 1}, progress=False)
    assert s["families"] == {"vasculature": 6}
    ds = open_dataset(tmp_path / "v.zarr")
    assert set(ds.group["family"][:].tolist()) == {list(AUGMENT_FAMILIES).index("vasculature")}


def test_bad_inputs(params_yaml, tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        augment(tmp_path / "missing.yaml", tmp_path / "x.zarr", count=4, progress=False)
    with pytest.raises(InputError, match="does not exist"):
        open_dataset(tmp_path / "nothing.zarr")
    g = zarr.open_group(str(tmp_path / "half.zarr"), mode="w")
    g.attrs.update(format=FORMAT)
    with pytest.raises(InputError, match="incomplete"):
        open_dataset(tmp_path / "half.zarr")
    with pytest.raises(ValueError, match="count"):
        augment(params_yaml, tmp_path / "y.zarr", count=0, progress=False)
