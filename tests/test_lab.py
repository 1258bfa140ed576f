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


def test_the_lab_prints_a_dense_reference_when_asked(tmp_path):
    """Lab config dense_reference: x adds one print of a large block at x times the exposure,
    named in batch.yaml; its polymer cures through (density at saturation in its interior).
    A bad factor, and a mask that already has the reference's id, are errors."""
    from unscatter.io import InputError, read_batch_meta, read_mask, read_tsv, write_png
    from unscatter.lab import print_batch
    from unscatter.masks import dense_reference_mask

    write_png(tmp_path / "m" / "a.png", dense_reference_mask(128) // 2)
    print_batch(tmp_path / "m", tmp_path / "batch", overrides={"dense_reference": 4}, seed=1, progress=False)
    assert read_batch_meta(tmp_path / "batch").dense_reference == ("dense_reference",)
    assert np.array_equal(read_mask(tmp_path / "batch" / "masks" / "dense_reference.png"), dense_reference_mask(128))
    assert {r["id"]: float(r["exposure"]) for r in read_tsv(tmp_path / "batch" / "job.tsv")} == {"a": 1.0, "dense_reference": 4.0}
    rho = np.load(tmp_path / "batch.truth" / "density" / "dense_reference.npy")
    assert np.median(rho[48:80, 48:80]) > 0.99
    for bad in (True, 0.8, "long"):
        with pytest.raises(InputError, match="dense_reference must be an exposure factor"):
            print_batch(tmp_path / "m", tmp_path / "b2", overrides={"dense_reference": bad}, progress=False)
    write_png(tmp_path / "m" / "dense_reference.png", dense_reference_mask(128))
    with pytest.raises(InputError, match="a mask is named 'dense_reference'"):
        print_batch(tmp_path / "m", tmp_path / "b3", overrides={"dense_reference": 4}, progress=False)


# ------------------------------------------------------------------ randomised labs


def _known_keys(over: dict, base: dict, path=""):
    """Every key an override sets exists in the lab's default config (no silent typos)."""
    for k, v in over.items():
        assert k in base, f"unknown lab key {path}{k}"
        if isinstance(v, dict) and isinstance(base[k], dict):
            _known_keys(v, base[k], f"{path}{k}.")


def test_random_labs_stay_in_their_ranges():
    from unscatter.lab.random import MARGIN_PX, RANGES, field_extent_px, random_lab

    default = load_config()
    seen_formats, seen_effects, seen_metadata = set(), set(), set()
    for s in range(200):
        over = random_lab(np.random.default_rng(s))
        _known_keys(over, default)
        cfg = load_config(overrides=over)
        m, p = cfg["microscope"], cfg["printer"]
        within = lambda key, v: RANGES[key][0] - 1e-9 <= v <= RANGES[key][1] + 1e-9  # noqa: E731
        assert within("rotation_deg", m["rotation_deg"])
        assert RANGES["scale"][0] <= m["scale"][0] <= m["scale"][1] <= RANGES["scale"][1]
        assert all(within("image_px", v) for v in m["image_size"])
        # the whole design field fits the image at the largest scale and rotation
        assert min(m["image_size"]) >= field_extent_px(m["scale"][1], m["rotation_deg"]) + 2 * MARGIN_PX - 0.5
        assert within("blur_px", m["blur_px"][0]) and within("blur_px", m["blur_px"][1]) and m["blur_px"][0] <= m["blur_px"][1]
        assert 0 <= m["vignetting"][0] <= m["vignetting"][1] <= RANGES["vignetting"][1]
        for key in ("background", "photons", "read_noise_e", "offset_adu", "lamp_jitter", "background_tilt"):
            assert within(key, m[key]), key
        assert m["format"] in ("tif16", "png8") and isinstance(m["declare_offset"], bool)
        # the brightest expected pixel stays below the camera's maximum
        assert m["offset_adu"] + m["adu_per_e"] * m["photons"] * (1 + m["background"]) * (1 + 3 * m["lamp_jitter"]) < 65535
        if m["haze"]:
            assert within("haze_fraction", m["haze"]["fraction"]) and within("haze_sigma_px", m["haze"]["sigma_px"])
            seen_effects.add("haze")
        if m["staining"]:
            assert within("staining", m["staining"]["variation"]) and within("staining_length_px", m["staining"]["length_px"])
            seen_effects.add("staining")
        if m["background_tilt"]:
            seen_effects.add("tilt")
        k = p["kernel"]
        assert within("sigma_um", k["sigma_um"]) and within("anisotropy", k["anisotropy"]["ratio"])
        assert within("tail_fraction", k["heavy_tail"]["fraction"]) and within("tail_length_um", k["heavy_tail"]["length_um"])
        assert within("threshold", p["cure"]["threshold"]) and 0 < p["cure"]["gel_dose"] < p["cure"]["threshold"]
        assert within("edge_offset_um", p["edge_offset_um"]) and within("dose_noise", p["cells"]["dose_noise"])
        hs = p["illumination"]["hotspot"]
        if hs:
            assert within("hotspot_amplitude", hs["amplitude"]) and within("hotspot_width", hs["width"])
        seen_formats.add(m["format"])
        md = m["pixel_size_metadata"]
        if md:  # what the lab states of its camera pixel: only what its images and objective can carry
            one = m["scale"][1] / m["scale"][0] < 1.005
            assert md["where"] in (["ome", "imagej"] if m["format"] == "tif16" else []) + (["batch"] if one else [])
            tol = md["tolerance"]
            if tol is None:
                assert within("pixel_size_error", md["error"])
            else:
                assert within("pixel_size_tolerance", tol)
                assert abs(md["error"]) <= tol / 2 + 1e-9 or RANGES["stale_factor"][0] * tol - 1e-9 <= abs(md["error"]) <= RANGES["stale_factor"][1] * tol + 1e-9
            seen_metadata.add(md["where"] + (" stale" if tol and abs(md["error"]) > tol else ""))
    assert seen_formats == {"tif16", "png8"} and seen_effects == {"haze", "staining", "tilt"}
    assert seen_metadata >= {"ome", "imagej", "batch", "ome stale"} or seen_metadata >= {"ome", "imagej", "batch", "imagej stale"}


def test_describe_lab_names_the_effects_a_lab_has_and_lacks():
    """A lab with its tail switched off and physics outside the model library (the
    diagnosis benchmark's one-effect labs) is described, not a crash."""
    from unscatter.lab.random import describe_lab, random_lab

    over = random_lab(np.random.default_rng(3))
    assert "tail " in describe_lab(over) and "no tail" not in describe_lab(over)
    k = over["printer"]["kernel"]
    over["printer"]["kernel"] = dict(k, heavy_tail=None)
    over["printer"].update(oxygen_inhibition=dict(strength=0.2, length_um=15.0), kernel_dose_growth=0.5)
    line = describe_lab(over)
    assert "no tail" in line and "O2 0.20/15 um" in line and "kernel x1.50 at full grey" in line


def test_print_batch_takes_a_random_lab(tmp_path):
    from unscatter import masks
    from unscatter.io import read_image_raw, write_png
    from unscatter.lab import print_batch, random_lab

    for mid, m in masks.test_pattern_masks(2, seed=0, patterns=["grating", "siemens_star"]).items():
        write_png(tmp_path / "m" / f"{mid}.png", m)
    over = random_lab(np.random.default_rng(7))
    over["microscope"].update(format="png8", haze={"fraction": 0.2, "sigma_px": 30.0}, background_tilt=0.4,
                              staining={"variation": 0.2, "length_px": 100.0})
    rows = print_batch(tmp_path / "m", tmp_path / "b", overrides=over, seed=3, progress=False)
    b = open_batch(tmp_path / "b")
    H, W = over["microscope"]["image_size"]
    for r in rows:
        img = read_image_raw(b.images[r["id"]])
        assert img.dtype == np.uint8 and img.shape == (H, W) and img.max() < 255
        M = np.array([[r["m00"], r["m01"], r["m02"]], [r["m10"], r["m11"], r["m12"]]])
        corners = M[:, :2] @ np.array([[0, 511, 0, 511], [0, 0, 511, 511]], float) + M[:, 2:]
        assert corners.min() >= 0 and corners[0].max() <= W - 1 and corners[1].max() <= H - 1  # the field in view


def _image(cfg, density=None, seed=0):
    from unscatter.lab.microscope import image_print

    rho = np.zeros((96, 96)) if density is None else density
    pose = dict(rotation_deg=0.0, scale=1.0, shift_x=0.0, shift_y=0.0)
    return image_print(rho, 16, 64, cfg, np.random.default_rng(seed), pose=pose)[0].astype(float)


def test_new_microscope_effects_are_off_by_default():
    """haze, background_tilt and staining: the default lab's images are those of the lab
    before these keys existed (same random stream, same pixels)."""
    mic = load_config()["microscope"]
    assert mic["haze"] is None and mic["background_tilt"] == 0 and mic["staining"] is None
    mic = dict(mic, image_size=[96, 96])
    old = {k: v for k, v in mic.items() if k not in ("haze", "background_tilt", "staining")}
    zeros = dict(mic, haze={"fraction": 0.0, "sigma_px": 20.0}, staining={"variation": 0.0, "length_px": 50.0})
    rho = np.zeros((96, 96))
    rho[30:60, 40:50] = 0.9
    ref = _image(old, rho)
    assert np.array_equal(_image(mic, rho), ref) and np.array_equal(_image(zeros, rho), ref)


def test_new_microscope_effects_do_what_they_say():
    bright = dict(load_config()["microscope"], image_size=[96, 96], photons=1e6, read_noise_e=0.0, lamp_jitter=0.0,
                  vignetting=[0.0, 0.0], background=0.2, blur_px=[0.5, 0.5], offset_adu=0, adu_per_e=0.05)
    blocks = lambda img: img.reshape(8, 12, 8, 12).mean(axis=(1, 3))  # noqa: E731
    # a tilted background: corner to corner by the tilt's share, no polymer needed
    b = blocks(_image(dict(bright, background_tilt=0.4)))
    assert 0.25 < (b.max() - b.min()) / b.mean() < 0.42
    assert (lambda f: (f.max() - f.min()) / f.mean())(blocks(_image(bright))) < 0.01
    # haze: a small print glows into the background around it
    rho = np.zeros((96, 96))
    rho[40:56, 40:56] = 1.0
    dim = dict(bright, background=0.05)
    plain, hazy = _image(dim, rho), _image(dict(dim, haze={"fraction": 0.2, "sigma_px": 15.0}), rho)
    assert hazy[16:30, 16:30].mean() > 1.03 * plain[16:30, 16:30].mean()
    assert hazy[40:56, 40:56].mean() < 0.95 * plain[40:56, 40:56].mean()
    # staining: uneven polymer signal, the background alone untouched on average
    rho = np.ones((96, 96))
    st = dict(bright, staining={"variation": 0.2, "length_px": 40.0})
    spread = lambda img: blocks(img).std() / blocks(img).mean()  # noqa: E731
    assert spread(_image(bright, rho)) < 0.01 and spread(_image(st, rho)) > 0.05
    assert abs(_image(st).mean() / _image(bright).mean() - 1) < 0.01


def test_an_8bit_labs_declared_offset_is_what_its_dark_frame_reads():
    """An 8-bit export keeps the top byte of the camera's 16-bit value, which drops the
    rest: its dark frame reads about half a level below offset / 256. The lab declares
    what a lab measuring a dark frame of its stored images would (``run.dark_level``), not
    offset / 256, which left the background of a dim 8-bit image half a level low."""
    from unscatter.lab.run import dark_level

    for offset, read_noise in ((647.9, 7.5), (300.0, 3.0), (90.0, 1.2)):
        mic = dict(load_config()["microscope"], image_size=[256, 256], photons=0.0, offset_adu=offset,
                   read_noise_e=read_noise, adu_per_e=51.8, format="png8")
        dark = (_image(mic).astype(np.uint16) >> 8).mean()  # the stored 8-bit dark frame
        assert abs(dark_level(mic) - dark) < 0.02, (offset, dark_level(mic), dark)
        assert dark_level(dict(mic, format="tif16")) == offset
    lab7 = dict(mic, offset_adu=647.9, read_noise_e=7.5)  # lab 7 of the registration benchmark's seed 434016831
    assert abs(dark_level(lab7) - 647.9 / 256) > 0.4  # not what was declared before (offset / 256)


def test_a_lab_states_its_microscope_blur_only_when_told_to():
    """``declare_blur``: batch.yaml's microscope_blur_um is the Gaussian sigma at the sample
    that the lab's microscope applies (a point's image, measured by its second moment, at
    one magnification); the default lab states none (its runs stay as they were)."""
    from unscatter.lab.run import batch_yaml

    cfg = load_config()
    assert "microscope_blur_um" not in batch_yaml(cfg, {}, "lab.yaml")
    px = cfg["batch"]["pixel_size_um"]
    mic = dict(cfg["microscope"], image_size=[96, 96], blur_px=[1.5, 1.5], scale=[1.0, 1.0], photons=1e5, background=0.0,
               read_noise_e=0.0, vignetting=[0.0, 0.0], lamp_jitter=0.0, offset_adu=0.0)
    rho = np.zeros((96, 96))
    rho[48, 48] = 1.0
    img = _image(mic, rho)
    yy, xx = np.mgrid[0:96, 0:96]
    w = img / img.sum()
    cy, cx = (w * yy).sum(), (w * xx).sum()
    sd_px = np.sqrt(0.5 * (w * ((yy - cy) ** 2 + (xx - cx) ** 2)).sum())
    stated = batch_yaml(dict(cfg, microscope=mic | {"declare_blur": True}), {}, "lab.yaml")["microscope_blur_um"]
    assert stated / px == pytest.approx(sd_px, rel=0.03), (stated / px, sd_px)
