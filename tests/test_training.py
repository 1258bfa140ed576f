"""Training with Eq. 2: the loss terms, a short run, resumption, evaluation, inference."""

import math

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from unscatter.augment import augment
from unscatter.io import read_mask, read_tsv, write_png
from unscatter.model import default_params, design_coords, save_params
from unscatter.training import (
    EVAL_COLUMNS,
    LOG_COLUMNS,
    PRESETS,
    compensate_nn,
    coord_maps,
    eq2_total,
    load_net,
    loss_terms,
    prepare,
    settings_for,
    sparsity,
    train,
)

# one torch thread: the nets are tiny, and a busy machine makes spinning threads slow
FAST = dict(threads=1, progress=False)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("train_data")
    p = default_params(pixel_size_um=2.96).with_values(c1=-0.06, c3=0.03, sigma_px=4.0, T=0.5)
    save_params(root / "params.yaml", p)
    augment(root / "params.yaml", root / "eq1.zarr", count=40, seed=1, size=512, progress=False)
    return root / "eq1.zarr"


@pytest.fixture(scope="module")
def ci_run(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("ci_run")
    summary = train(dataset, out, preset="ci", settings=dict(epochs=3), **FAST)
    return out, summary


# --------------------------------------------------------------------------- Eq. 2


def test_eq2_terms_on_a_hand_checkable_example():
    master_y = torch.tensor([[-1.0, 1.0], [0.0, 0.5]]).reshape(1, 1, 2, 2)
    x = torch.tensor([[-1.0, 0.0], [1.0, 0.5]]).reshape(1, 1, 2, 2)
    p = torch.tensor([[0.0, 1.0], [1.0, 0.0]]).reshape(1, 1, 2, 2)  # solid where 1
    # logits (void, solid) per pixel
    slave_x = torch.zeros(1, 2, 2, 2)  # 50/50 everywhere: CE = ln 2
    slave_my = torch.zeros(1, 2, 2, 2)
    slave_my[0, 1] = torch.tensor([[-1.0, 1.0], [1.0, -1.0]])  # solid logit +-1, void logit 0
    t = loss_terms(master_y, slave_my, slave_x, x, p)
    assert t["ce_slave"].item() == pytest.approx(math.log(2))
    # every pixel is right with margin 1: -log(e / (1 + e)) = log(1 + e^-1)
    assert t["ce_master"].item() == pytest.approx(math.log(1 + math.exp(-1)))
    assert t["l1_master"].item() == pytest.approx((0 + 1 + 1 + 0) / 4)
    # dose (m + 1) / 2 outside the target: pixels (0,0) -> 0 and (1,1) -> 0.75; mean over 4 pixels
    assert t["sparsity"].item() == pytest.approx(0.75 / 4)
    assert sparsity(master_y, p).item() == pytest.approx(0.1875)
    total = eq2_total(t, lambda1=0.5, lambda2=1.0, lambda3=0.05)
    expect = math.log(1 + math.exp(-1)) + 0.5 * 0.5 + math.log(2) + 0.05 * 0.1875
    assert total.item() == pytest.approx(expect)


def test_soft_targets_at_reduced_resolution():
    masks = np.zeros((1, 4, 4), np.uint8)
    masks[0, :2, :2] = 255
    prints = np.zeros((1, 4, 4), bool)
    prints[0, 0, :2] = True  # half of the top-left 2 x 2 block
    x, p = prepare(masks, prints, scale=2)
    assert x.shape == (1, 1, 2, 2) and x[0, 0, 0, 0] == 1 and x[0, 0, 1, 1] == -1
    assert p[0, 0, 0, 0] == 0.5 and p[0, 0, 1, 1] == 0


def test_coordinate_channels_follow_the_models_convention():
    c = coord_maps(64, 64, 2, (128, 128))
    assert torch.allclose(c[0, 0], design_coords(64, 2.0))  # X along columns
    assert torch.allclose(c[1, :, 0], design_coords(64, 2.0))  # Y along rows
    assert c.min() >= -1 and c.max() <= 1


def test_presets():
    paper = settings_for("paper")
    assert (paper["width"], paper["epochs"], paper["batch"], paper["lr"], paper["scale"]) == (64, 200, 10, 1e-5, 1)
    assert (paper["lambda1"], paper["lambda2"], paper["lambda3"], paper["lambda1_decay"]) == (1.0, 1.0, 0.05, 0.98)
    assert paper["betas"] == (0.9, 0.999)
    assert set(PRESETS) >= {"paper", "default", "ci"}
    assert settings_for("ci", epochs=7)["epochs"] == 7
    with pytest.raises(ValueError, match="unknown training setting"):
        settings_for("ci", widht=3)
    with pytest.raises(ValueError, match="multiple of 2"):
        settings_for("ci", crop=100)


# --------------------------------------------------------------------------- a run


def test_ci_run_writes_its_outputs(ci_run):
    out, summary = ci_run
    for name in ("master.pt", "slave.pt", "log.tsv", "curves.png", "eval.tsv", "checkpoint.pt"):
        assert (out / name).is_file(), name
    rows = read_tsv(out / "log.tsv")
    assert list(rows[0]) == LOG_COLUMNS
    assert [(r["epoch"], r["split"]) for r in rows] == [(str(e), s) for e in (1, 2, 3) for s in ("train", "test")]
    ev = read_tsv(out / "eval.tsv")
    assert list(ev[0]) == EVAL_COLUMNS
    methods = {(r["method"], r["family"]) for r in ev}
    assert {("slave", "all"), ("master", "all"), ("identity", "all")} <= methods
    for r in ev:
        assert 0 <= float(r["iou"]) <= 1 and 0 <= float(r["pixel_accuracy"]) <= 1


def test_losses_fall(ci_run):
    out, summary = ci_run
    train_rows = [r for r in read_tsv(out / "log.tsv") if r["split"] == "train"]
    first, last = float(train_rows[0]["total"]), float(train_rows[-1]["total"])
    assert last < 0.9 * first
    assert float(train_rows[-1]["ce_slave"]) < float(train_rows[0]["ce_slave"])


def test_lambda1_decays_by_098_per_iteration(ci_run, dataset):
    out, summary = ci_run
    rows = read_tsv(out / "log.tsv")
    test_rows = [r for r in rows if r["split"] == "test"]
    # ci: 24 pairs in batches of 4 -> 6 iterations per epoch; test rows use l1 after the epoch
    assert summary["iterations"] == 18
    for e, r in enumerate(test_rows, 1):
        assert float(r["lambda1"]) == pytest.approx(0.98 ** (6 * e), rel=1e-5)
    train_rows = [r for r in rows if r["split"] == "train"]
    assert float(train_rows[0]["lambda1"]) == pytest.approx(np.mean(0.98 ** np.arange(6)), rel=1e-5)


def test_resumed_run_equals_an_uninterrupted_one(dataset, tmp_path):
    straight = tmp_path / "straight"
    train(dataset, straight, preset="ci", settings=dict(epochs=2), **FAST)
    broken = tmp_path / "broken"
    train(dataset, broken, preset="ci", settings=dict(epochs=1), **FAST)  # interrupted after epoch 1
    train(dataset, broken, preset="ci", settings=dict(epochs=2), **FAST)  # resumes from checkpoint.pt
    a = torch.load(straight / "master.pt", weights_only=True)["state_dict"]
    b = torch.load(broken / "master.pt", weights_only=True)["state_dict"]
    for k in a:
        assert torch.allclose(a[k].float(), b[k].float(), atol=1e-6), k
    la, lb = read_tsv(straight / "log.tsv"), read_tsv(broken / "log.tsv")
    for ra, rb in zip(la, lb):
        for k in ("ce_master", "l1_master", "ce_slave", "sparsity", "total"):
            assert float(ra[k]) == pytest.approx(float(rb[k]), rel=1e-5), (ra["epoch"], k)
    with pytest.raises(ValueError, match="other settings"):
        train(dataset, broken, preset="ci", settings=dict(epochs=3, lr=0.1), **FAST)
    # the workflow's mode: a checkpoint from other settings is not resumed, training starts over
    train(dataset, broken, preset="ci", settings=dict(epochs=1, lr=0.1), resume="matching", **FAST)
    fresh = tmp_path / "fresh"
    train(dataset, fresh, preset="ci", settings=dict(epochs=1, lr=0.1), **FAST)
    a = torch.load(fresh / "master.pt", weights_only=True)["state_dict"]
    b = torch.load(broken / "master.pt", weights_only=True)["state_dict"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert len(read_tsv(broken / "log.tsv")) == len(read_tsv(fresh / "log.tsv"))


def test_same_seed_same_weights(dataset, tmp_path):
    train(dataset, tmp_path / "a", preset="ci", settings=dict(epochs=1), **FAST)
    train(dataset, tmp_path / "b", preset="ci", settings=dict(epochs=1), **FAST)
    a = torch.load(tmp_path / "a" / "slave.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "b" / "slave.pt", weights_only=True)["state_dict"]
    assert all(torch.equal(a[k], b[k]) for k in a)


# ---------------------------------------------------------------------- inference


def test_compensate_nn_gives_a_uint8_mask(ci_run):
    out, _ = ci_run
    design = np.zeros((512, 512), np.uint8)
    design[200:320, 150:380] = 255
    mask = compensate_nn(design, out)
    assert mask.shape == (512, 512) and mask.dtype == np.uint8
    assert np.array_equal(mask, compensate_nn(design > 0, out))  # bool designs too
    odd = compensate_nn(np.ones((300, 200), bool), out)  # padded to the net's multiple inside
    assert odd.shape == (300, 200)
    master, meta = load_net(out / "master.pt")
    assert meta["kind"] == "master" and meta["scale"] == 4 and not master.training


def test_cli_train_and_compensate(dataset, tmp_path):
    from unscatter.cli import main

    r = CliRunner().invoke(main, ["train", str(dataset), str(tmp_path / "t"), "--preset", "ci", "--epochs", "1", "--threads", "1", "--no-progress"])
    assert r.exit_code == 0, r.output
    design = np.zeros((512, 512), np.uint8)
    design[100:400, 240:270] = 255
    write_png(tmp_path / "design.png", design)
    r = CliRunner().invoke(main, ["compensate", str(tmp_path / "design.png"), "--model", str(tmp_path / "t"), "--method", "nn", "-o", str(tmp_path / "mask.png")])
    assert r.exit_code == 0, r.output
    assert read_mask(tmp_path / "mask.png").shape == (512, 512)
    r = CliRunner().invoke(main, ["compensate", str(tmp_path / "design.png"), "--model", str(tmp_path / "nothing"), "-o", str(tmp_path / "m3.png")])
    assert r.exit_code == 2 and "does not exist" in r.output


def test_cli_augment(tmp_path, dataset):
    from unscatter.cli import main

    params = dataset.parent / "params.yaml"
    r = CliRunner().invoke(main, ["augment", str(params), str(tmp_path / "a.zarr"), "--count", "5", "--seed", "3", "--size", "128", "--no-progress"])
    assert r.exit_code == 0, r.output
    from unscatter.augment import open_dataset

    ds = open_dataset(tmp_path / "a.zarr")
    assert len(ds) == 5 and ds.size == 128 and ds.attrs["seed"] == 3
