"""No command deletes or overwrites a user's files, none is silently wrong about its
input, and every such error is one line (`error: <file>: <problem>`, exit code 2).

Each case checks the exit code, that the one line names the file or option, and the
sha256 of every file of the user's folders before and after. Sizes are tiny: the
checks come before any work.
"""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from unscatter.cli import main
from unscatter.io import InputError, OUTPUT_MARKER, output_dir, read_batch_meta, write_png, write_yaml
from unscatter.model import default_params, load_params, save_params

REPO = Path(__file__).resolve().parents[1]


# ----------------------------------------------------------------------- helpers
def sums(*folders) -> dict:
    """sha256 of every file below the folders (and of the files given)."""
    out = {}
    for f in map(Path, folders):
        for p in sorted([f] if f.is_file() else f.rglob("*")):
            if p.is_file():
                out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def refused(res, *names) -> str:
    """The command failed with exit code 2 and one `error:` line naming ``names``."""
    assert res.exit_code == 2, res.output
    lines = [line for line in res.output.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "Traceback" not in res.output, res.output
    for n in names:
        assert str(n) in lines[0], lines[0]
    return lines[0]


def no_leftovers(parent: Path):
    assert not [p.name for p in parent.iterdir() if p.name.endswith((".partial", ".old"))]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """Two 128 px trial masks, their virtual-lab batch, a params file, two designs."""
    from unscatter.lab import print_batch
    from unscatter.masks import write_trial_masks

    root = tmp_path_factory.mktemp("tiny")
    write_trial_masks(root / "masks", count=2, size=128, seed=3)
    print_batch(root / "masks", root / "batch", seed=1, progress=False)
    save_params(root / "params.yaml", default_params("eq1", pixel_size_um=2.96))
    designs = root / "designs"
    for name, (a, b) in {"square": (32, 96), "bar": (56, 72)}.items():
        d = np.zeros((128, 128), np.uint8)
        d[a:b, 32:96] = 255
        write_png(designs / f"{name}.png", d)
    return root


@pytest.fixture
def user(tiny, tmp_path):
    """A user's folder that is no output of ours: a copy of a print batch plus notes."""
    u = tmp_path / "user"
    shutil.copytree(tiny / "batch", u, ignore=shutil.ignore_patterns(OUTPUT_MARKER))
    (u / "notes.txt").write_text("the only copy of my notes\n")
    return u


@pytest.fixture
def masks(tiny, tmp_path):
    m = tmp_path / "masks"
    shutil.copytree(tiny / "masks", m, ignore=shutil.ignore_patterns(OUTPUT_MARKER))
    return m


# ------------------------------------------------------------- A: nothing is lost
def test_augment_into_a_folder_that_is_not_a_store(tiny, user):
    before = sums(user)
    refused(run("augment", tiny / "params.yaml", user, "--count", 4, "--size", 128, "--no-progress"), user)
    assert sums(user) == before
    no_leftovers(user.parent)


def test_augment_replaces_its_own_store_only(tiny, tmp_path):
    store = tmp_path / "a.zarr"
    for count in (4, 3):  # the rerun replaces the store
        res = run("augment", tiny / "params.yaml", store, "--count", count, "--size", 128, "--no-progress", "--workers", 1)
        assert res.exit_code == 0, res.output
    from unscatter.augment import open_dataset

    assert len(open_dataset(store)) == 3 and not (store / OUTPUT_MARKER).exists()
    no_leftovers(tmp_path)


@pytest.mark.parametrize("where", ["same", "inside", "user", "truth", "link"])
def test_lab_print_never_writes_into_masks_or_a_users_folder(masks, user, tmp_path, where):
    before = sums(masks, user)
    out = {"same": masks, "inside": masks / "out", "user": user, "truth": tmp_path / "new", "link": tmp_path / "link"}[where]
    if where == "link":
        out.symlink_to(masks)
    extra = ["--truth-dir", user] if where == "truth" else []
    res = run("lab", "print", masks, out, *extra)
    refused(res, user if where == "truth" else out)
    assert sums(masks, user) == before
    assert not (tmp_path / "new").exists()


def test_lab_print_rerun_replaces_its_batch_without_stale_files(masks, tmp_path):
    out = tmp_path / "b"
    assert run("lab", "print", masks, out).exit_code == 0
    (masks / "trial_001.png").unlink()
    res = run("lab", "print", masks, out)
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (out / "masks").iterdir()) == ["trial_000.png"]
    assert sorted(p.name for p in (out / "images").iterdir()) == ["trial_000.tif"]
    assert sorted(p.name for p in (tmp_path / "b.truth" / "prints").iterdir()) == ["trial_000.png"]
    no_leftovers(tmp_path)


def test_an_output_with_files_the_user_added_is_not_replaced(tmp_path):
    out = tmp_path / "m"
    assert run("masks", "trial", out, "--count", 2, "--size", 64).exit_code == 0
    (out / "notes.txt").write_text("mine\n")
    before = sums(out)
    line = refused(run("masks", "trial", out, "--count", 2, "--size", 64), out)
    assert "notes.txt" in line and sums(out) == before


def test_a_rerun_leaves_nothing_stale_and_a_failed_run_leaves_the_old_output(tmp_path):
    out = tmp_path / "m"
    assert run("masks", "trial", out, "--count", 3, "--size", 64).exit_code == 0
    assert run("masks", "trial", out, "--count", 2, "--size", 64).exit_code == 0
    assert sorted(p.name for p in out.glob("*.png")) == ["trial_000.png", "trial_001.png"]
    before = sums(out)
    with pytest.raises(KeyboardInterrupt):
        with output_dir(out, command="masks trial") as tmp:
            write_png(tmp / "trial_000.png", np.zeros((8, 8), np.uint8))
            raise KeyboardInterrupt
    assert sums(out) == before
    no_leftovers(tmp_path)


def test_another_commands_output_is_not_replaced(tiny, tmp_path):
    out = tmp_path / "m"
    assert run("masks", "trial", out, "--count", 2, "--size", 64).exit_code == 0
    before = sums(out)
    line = refused(run("simulate", tiny / "params.yaml", tiny / "masks", out), out)
    assert "`unscatter masks trial`" in line and sums(out) == before


def test_simulate_into_its_masks(tiny, masks):
    before = sums(masks)
    refused(run("simulate", tiny / "params.yaml", masks, masks), masks)
    assert sums(masks) == before


def test_calibrate_and_diagnose_outputs(tiny, user, tmp_path):
    before = sums(user)
    refused(run("calibrate", tiny / "batch", "--out", user), user)
    refused(run("calibrate", user, "--out", user / "cal"), user / "cal")
    cal = tmp_path / "cal"
    cal.mkdir()
    shutil.copy(tiny / "params.yaml", cal / "params.yaml")
    refused(run("diagnose", tiny / "batch", "--base", cal, "--out", cal), cal)
    assert sums(user) == before and (cal / "params.yaml").is_file()


def test_train_outputs(tiny, user, tmp_path):
    from unscatter.augment import augment

    store = tmp_path / "s.zarr"
    augment(tiny / "params.yaml", store, count=4, size=128, workers=1, progress=False)
    before = sums(user, store)
    refused(run("train", store, user, "--preset", "ci", "--scale", 1, "--no-progress"), user)
    refused(run("train", store, store / "net", "--preset", "ci", "--scale", 1, "--no-progress"), store / "net")
    assert sums(user, store) == before


def test_compensate_designs_into_a_users_folder(tiny, user):
    from unscatter.compensation import compensate_designs

    before = sums(user)
    with pytest.raises(InputError, match="not an earlier output of `unscatter compensate`"):
        compensate_designs(tiny / "designs", user, "ilt", params_path=tiny / "params.yaml")
    assert sums(user) == before


@pytest.mark.parametrize("command", ["job", "simulate", "score"])
def test_benchmark_outputs(tiny, user, command):
    args = {"job": ["job", tiny / "designs", user], "simulate": ["simulate", tiny / "designs", user, "--params", tiny / "params.yaml"],
            "score": ["score", tiny / "batch", tiny / "designs", user]}[command]
    before = sums(user, tiny / "designs")
    refused(run("benchmark", *args), user)
    assert sums(user, tiny / "designs") == before
    refused(run("benchmark", "job", tiny / "designs", tiny / "designs" / "job"), tiny / "designs" / "job")


# registration writes through unscatter.imaging.register_batch, which calls io.output_dir
# with command="register" and inputs=[batch_dir]; until then these fail as marked.


@pytest.fixture
def batch(tiny, tmp_path):
    b = tmp_path / "batch"
    shutil.copytree(tiny / "batch", b, ignore=shutil.ignore_patterns(OUTPUT_MARKER))
    return b


@pytest.mark.parametrize("where", ["masks", "batch", "user"])
def test_register_never_writes_into_its_batch_or_a_users_folder(batch, user, where):
    out = {"masks": batch / "masks", "batch": batch, "user": user}[where]
    before = sums(batch, user)
    refused(run("register", batch, out, "--skip-failed"), out)
    assert sums(batch, user) == before


def test_register_rerun_leaves_no_stale_prints(batch, tmp_path):
    out = tmp_path / "prints"
    assert run("register", batch, out, "--skip-failed").exit_code == 0
    (batch / "masks" / "trial_001.png").unlink()
    (batch / "images" / "trial_001.tif").unlink()
    assert run("register", batch, out, "--skip-failed").exit_code == 0
    assert not (out / "trial_001.png").exists() and not (out / "overlays" / "trial_001.png").exists()
    no_leftovers(tmp_path)


# --------------------------------------------------------- B: silently wrong -> errors
@pytest.mark.parametrize("option, value", [("--level", 0), ("--level", 2), ("--min-score", -1), ("--min-score", 1.5)])
def test_register_options_are_bounded(batch, tmp_path, option, value):
    res = run("register", batch, tmp_path / "out", option, value)
    assert res.exit_code == 2 and option in res.output and not (tmp_path / "out").exists()


def _batch_yaml(batch: Path, text: str) -> Path:
    p = batch / "batch.yaml"
    p.write_text("pixel_size_um: 2.96\nexposure_s: 20\nmax_intensity_mw_cm2: 20.8\nmaterial: GelMA\n" + text)
    return p


@pytest.mark.parametrize("text, words", [
    ("camera_ofset_adu: 100\n", "unknown field 'camera_ofset_adu'; did you mean 'camera_offset_adu'?"),
    ("camera_offset_adu: dark\n", "'camera_offset_adu' must be a number, found 'dark'"),
    ("camera_offset_adu: -5\n", "'camera_offset_adu' must be a number >= 0"),
    ("camera_offset_adu: 100\ncamera_offset_adu: 0\n", "'camera_offset_adu' appears twice (lines 5 and 6)"),
    ("notes: 2024-05-02\n", "'notes' must be text"),
    ("image_rotation_deg: [-5]\n", "'image_rotation_deg' must be a number r (-r..r) or a pair"),
    ("image_rotation_deg: 200\n", "within -180..180"),
    ("layer_um: 0\n", "'layer_um' must be a positive number"),
])
def test_batch_yaml_is_checked_key_by_key(batch, tmp_path, text, words):
    p = _batch_yaml(batch, text)
    before = sums(batch)
    line = refused(run("register", batch, tmp_path / "out"), p)
    assert words in line and sums(batch) == before and not (tmp_path / "out").exists()


@pytest.mark.parametrize("value", ["true", "abc", "[2.96]"])
def test_pixel_size_must_be_a_number(batch, tmp_path, value):
    p = batch / "batch.yaml"
    p.write_text(p.read_text().replace("pixel_size_um: 2.96", f"pixel_size_um: {value}"))
    line = refused(run("register", batch, tmp_path / "out"), p)
    assert "'pixel_size_um' must be a number" in line


def test_batch_meta_defaults_and_optional_fields(batch):
    m = read_batch_meta(batch)
    assert m.camera_offset_adu == 100 and m.image_rotation_deg is None and m.source_batch is None
    _batch_yaml(batch, "image_rotation_deg: 10\nimage_pixel_size_um: 3.45\nz_step_um: 50\n")
    m = read_batch_meta(batch / "batch.yaml")
    assert m.camera_offset_adu == 0 and m.notes == "" and m.image_rotation_deg == (-10, 10) and m.z_step_um == 50
    _batch_yaml(batch, "image_rotation_deg: [-3, 12]\n")
    assert read_batch_meta(batch).image_rotation_deg == (-3, 12)
    _batch_yaml(batch, "dense_reference: ref_1\n")
    assert read_batch_meta(batch).dense_reference == ("ref_1",)
    _batch_yaml(batch, "dense_reference: [ref_1, ref_2]\n")
    assert read_batch_meta(batch).as_dict()["dense_reference"] == ["ref_1", "ref_2"]
    for bad in ("[ref_1, ref_1]", "3", "[]"):
        _batch_yaml(batch, f"dense_reference: {bad}\n")
        with pytest.raises(InputError, match="dense_reference"):
            read_batch_meta(batch)


def test_lab_config_with_a_bad_batch_field(masks, tmp_path):
    cfg = tmp_path / "lab.yaml"
    cfg.write_text("batch:\n  pixel_size_um: abc\n")
    line = refused(run("lab", "print", masks, tmp_path / "b", "--lab-config", cfg), cfg)
    assert "'pixel_size_um' must be a number" in line and not (tmp_path / "b").exists()


def _params(tmp_path, **values) -> Path:
    p = tmp_path / "p.yaml"
    save_params(p, default_params("eq1").with_values(**values))
    return p


@pytest.mark.parametrize("values, words", [
    (dict(sigma_px=1e6), "parameter 'sigma_px' = 1e+06 lies outside its bounds [0.25, 12]"),
    (dict(c0=0.5, T=1.4), "prints nothing: a fully exposed 512x512 square reaches a dose of 0.5, below the threshold T = 1.4"),
])
def test_params_that_cannot_be_a_printer(tiny, tmp_path, values, words):
    p = _params(tmp_path, **values)
    out = tmp_path / "mask.png"
    line = refused(run("compensate", tiny / "designs" / "square.png", "--method", "ilt", "--model", p, "-o", out), p)
    assert words in line and not out.exists()


def test_unknown_effect_names(tmp_path):
    p = _params(tmp_path)
    d = yaml.safe_load(p.read_text())
    d["effects"] = ["heavy_tial"]
    write_yaml(p, d)
    with pytest.raises(InputError, match=r"effects \['heavy_tial'\]: each must be one of .*'heavy_tail'"):
        load_params(p)
    d["effects"], d["model"] = [], "eq1+glow"
    write_yaml(p, d)
    with pytest.raises(InputError, match="unknown effect 'glow' .*known: .*'edge_offset'"):
        load_params(p)


def test_compensate_writes_png_masks_only(tiny, tmp_path):
    for opt in ("-o", "--frame"):
        out = tmp_path / "mask.jpg"
        args = ["-o", out] if opt == "-o" else ["-o", tmp_path / "m.png", "--frame", out]
        res = run("compensate", tiny / "designs" / "square.png", "--method", "ilt", "--model", tiny / "params.yaml", *args)
        assert res.exit_code == 2 and opt in res.output and "lossless PNG" in res.output
        assert not list(tmp_path.iterdir())


def test_a_store_that_lost_chunks(tiny, tmp_path):
    from unscatter.augment import augment, open_dataset

    store = tmp_path / "s.zarr"
    augment(tiny / "params.yaml", store, count=4, size=128, workers=1, progress=False)
    open_dataset(store)
    (store / "prints" / "c" / "2" / "0" / "0").unlink()
    with pytest.raises(InputError, match="1 of the 4 chunk files of 'prints' are missing"):
        open_dataset(store)
    refused(run("train", store, tmp_path / "net", "--preset", "ci", "--scale", 1, "--no-progress"), store)
    assert not (tmp_path / "net").exists()


# ------------------------------------------------------ C: one line, not a traceback
def test_a_read_only_output_folder(tmp_path, monkeypatch):
    def read_only(self, *a, **k):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self))

    monkeypatch.setattr(Path, "mkdir", read_only)
    refused(run("masks", "trial", tmp_path / "m", "--count", 1, "--size", 64), tmp_path / "m", "Read-only file system")


def test_a_file_system_error_is_one_line_and_a_traceback_with_v(tmp_path, monkeypatch):
    import unscatter.io

    def denied(path, arr):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))

    monkeypatch.setattr(unscatter.io, "write_png", denied)
    refused(run("masks", "trial", tmp_path / "m", "--count", 1, "--size", 64), "trial_000.png", "Permission denied")
    res = run("-v", "masks", "trial", tmp_path / "m", "--count", 1, "--size", 64)
    assert isinstance(res.exception, PermissionError)
    no_leftovers(tmp_path)


def test_a_truncated_checkpoint(tiny, tmp_path):
    from unscatter.augment import augment

    store = tmp_path / "s.zarr"
    augment(tiny / "params.yaml", store, count=4, size=128, workers=1, progress=False)
    net = tmp_path / "net"
    net.mkdir()
    (net / "checkpoint.pt").write_bytes(b"PK\x03\x04 the first bytes of a zip and no more")
    line = refused(run("train", store, net, "--preset", "ci", "--scale", 1, "--no-progress"), net / "checkpoint.pt")
    assert "truncated" in line


def test_a_tiff_given_as_params(tiny, tmp_path):
    tif = next((tiny / "batch" / "images").glob("*.tif"))
    line = refused(run("simulate", tif, tiny / "masks", tmp_path / "sim"), tif)
    assert "not a text (YAML) file" in line and not (tmp_path / "sim").exists()


def test_a_design_larger_than_the_dmd_fails_before_ilt(tiny, tmp_path):
    big = tmp_path / "big.png"
    d = np.zeros((4096, 4096), np.uint8)
    d[1000:3000, 1000:3000] = 255
    write_png(big, d)
    line = refused(run("compensate", big, "--method", "ilt", "--model", tiny / "params.yaml", "-o", tmp_path / "m.png"), big)
    assert "does not fit the 1600x2560 DMD frame" in line and not (tmp_path / "m.png").exists()


def test_a_benchmark_never_empties_a_users_folder(user, tmp_path, capsys):
    import importlib.util

    from unscatter.io import benchmark_output_dir

    before = sums(user)
    with pytest.raises(InputError, match="not an earlier output of `benchmarks/bench_print_budget.py`"):
        benchmark_output_dir(user, script="benchmarks/bench_print_budget.py")
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_print_budget.py"
    spec = importlib.util.spec_from_file_location("bench_print_budget", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    with pytest.raises(SystemExit):
        bench.main(["--labs", "0", "--out", str(user)])
    assert "is not empty and is not an earlier output" in capsys.readouterr().err
    assert sums(user) == before
    # its own earlier output is emptied for a rerun; another script's is not
    out = benchmark_output_dir(tmp_path / "b", script="benchmarks/bench_print_budget.py")
    (out / "stale.tsv").write_text("old\n")
    assert not (benchmark_output_dir(out, script="benchmarks/bench_print_budget.py") / "stale.tsv").exists()
    with pytest.raises(InputError, match="holds the output of `benchmarks/bench_print_budget.py`"):
        benchmark_output_dir(out, script="benchmarks/bench_registration.py")
    assert benchmark_output_dir(out, script="benchmarks/bench_print_budget.py", keep=True) == out.resolve()
