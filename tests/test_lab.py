"""The virtual lab: deterministic, in the data contract, and richer than Eq. 1."""

import ast
from pathlib import Path

import numpy as np
import pytest
import tifffile

from unscatter.io import open_batch, read_tsv
from unscatter.lab import Printer, load_config, polymer_density
from unscatter.masks import TRIAL_FAMILIES, trial_masks

SRC = Path(__file__).resolve().parents[1] / "src" / "unscatter"


def test_trial_masks_are_seeded_8bit_and_cover_the_families():
    a, b = trial_masks(6, seed=4), trial_masks(6, seed=4)
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert not np.array_equal(trial_masks(6, seed=5)["trial_000"], a["trial_000"])
    assert all(m.dtype == np.uint8 and m.shape == (512, 512) and m.max() > 0 for m in a.values())
    assert len(TRIAL_FAMILIES) == 3
    # the checkerboards carry grey levels, which calibrate the dose response
    greys = np.unique(a["trial_000"])
    assert ((greys > 0) & (greys < 255)).any()


def test_batch_is_in_the_data_contract_and_truth_stays_outside(lab_batch):
    b = open_batch(lab_batch)
    img = tifffile.imread(b.images[b.ids[0]])
    assert img.dtype == np.uint16 and img.shape == (720, 720)
    truth = lab_batch.with_name(lab_batch.name + ".truth")
    assert not (lab_batch / "prints").exists() and (truth / "transforms.tsv").is_file()
    rows = read_tsv(truth / "transforms.tsv")
    for r in rows:
        assert abs(float(r["rotation_deg"])) <= 10 and 0.8 <= float(r["scale"]) <= 1.25
        assert 0 <= float(r["vignetting"]) <= 0.3


def test_lab_is_deterministic(trial_dir, tmp_path):
    from unscatter.lab import print_batch

    print_batch(trial_dir, tmp_path / "a", seed=1, progress=False)
    print_batch(trial_dir, tmp_path / "b", seed=1, progress=False)
    print_batch(trial_dir, tmp_path / "c", seed=2, progress=False)
    f = "images/trial_000.tif"
    assert np.array_equal(tifffile.imread(tmp_path / "a" / f), tifffile.imread(tmp_path / "b" / f))
    assert not np.array_equal(tifffile.imread(tmp_path / "a" / f), tifffile.imread(tmp_path / "c" / f))


def test_heavy_tail_is_an_effect_eq1_lacks():
    """Default lab: an exponential tail spreads light over tens of um; dense patterns fuse."""
    cfg = load_config()
    assert cfg["printer"]["kernel"]["heavy_tail"]["fraction"] > 0
    plain = load_config(overrides={"printer": {"kernel": {"heavy_tail": None}}})
    # three lines 6 px apart: the tail's extra dose fills the gaps between them
    m = np.zeros((512, 512), np.uint8)
    for c in (240, 252, 264):
        m[150:350, c : c + 6] = 255
    dose = {}
    for name, c in (("tail", cfg), ("plain", plain)):
        cc = dict(c["printer"], cells=dict(c["printer"]["cells"], dose_noise=0.0, print_to_print=0.0))
        p = Printer(cc, 512, 2.96)
        dose[name] = p.crop(p.dose(m, np.random.default_rng(0)))
    far = dose["tail"][250, 330], dose["plain"][250, 330]  # 60 px from the lines
    assert far[0] > 5 * far[1] + 1e-3


def test_density_is_half_saturated_at_the_threshold():
    d = np.array([0.0, 0.35, 0.5, 1.0])
    rho = polymer_density(d, threshold=0.5, gel_dose=0.35)
    assert rho[0] == 0 and rho[1] == 0 and abs(rho[2] - 0.5) < 1e-12 and rho[3] > 0.9


def test_nothing_outside_the_lab_imports_it():
    """docs/design.md: the virtual lab is not the model."""
    for py in SRC.rglob("*.py"):
        if "lab" in py.relative_to(SRC).parts[:1]:
            continue
        tree = ast.parse(py.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [("." * node.level) + (node.module or "")]
                names += [names[0] + "." + a.name for a in node.names]
            for n in names:
                if n.endswith(".lab") or ".lab." in n or n.startswith("unscatter.lab"):
                    # the CLI's 'lab print' command drives the lab: it is the lab's front end
                    assert py.name == "cli.py", f"{py} imports {n}"


def test_print_job_exposures(tmp_path):
    """A print job's job.tsv prints masks longer or shorter; bad jobs are named."""
    from unscatter.io import InputError, read_mask, read_tsv, write_png
    from unscatter.lab import print_batch, read_job

    m = np.zeros((128, 128), np.uint8)
    m[40:88, 40:88] = 255
    for k in ("a", "b"):
        write_png(tmp_path / "m" / f"{k}.png", m)
    (tmp_path / "job.tsv").write_text("id\texposure\na\t0.8\nb\t1.25\n")
    print_batch(tmp_path / "m", tmp_path / "batch", exposures=read_job(tmp_path / "job.tsv"), seed=1, progress=False)
    truth = tmp_path / "batch.truth"
    assert read_mask(truth / "prints" / "a.png").sum() < read_mask(truth / "prints" / "b.png").sum()
    assert {r["id"]: float(r["exposure"]) for r in read_tsv(tmp_path / "batch" / "job.tsv")} == {"a": 0.8, "b": 1.25}
    (tmp_path / "bad.tsv").write_text("id\texposure\na\tlong\n")
    with pytest.raises(InputError, match="bad.tsv.*not a number"):
        read_job(tmp_path / "bad.tsv")
    (tmp_path / "other.tsv").write_text("id\texposure\nzz\t1.1\n")
    with pytest.raises(InputError, match="not here: zz"):
        print_batch(tmp_path / "m", tmp_path / "batch2", exposures=read_job(tmp_path / "other.tsv"), progress=False)
