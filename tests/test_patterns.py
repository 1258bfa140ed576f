"""Test patterns: the masks registration is benchmarked on (bench_registration.py --labs)."""

import numpy as np
import pytest
from scipy import ndimage

from unscatter import masks  # the module, so pytest does not collect masks.test_pattern_masks


def _pitch(m: np.ndarray) -> float:
    """Dominant period of a mask's pattern (px): the peak of the 2-D spectrum of its
    bounding box, Hann-windowed and zero-padded for sub-bin precision."""
    r, c = np.nonzero(m)
    crop = m[r.min() : r.max() + 1, c.min() : c.max() + 1].astype(float)
    crop -= crop.mean()
    crop *= np.hanning(crop.shape[0])[:, None] * np.hanning(crop.shape[1])[None, :]
    F = np.abs(np.fft.rfft2(crop, s=(1024, 1024)))
    F[0, 0] = 0
    ky, kx = np.unravel_index(np.argmax(F), F.shape)
    return 1 / np.hypot(np.fft.fftfreq(1024)[ky], kx / 1024)


def test_every_pattern_is_a_seeded_nonzero_8bit_mask():
    assert set(masks.FAMILIES) <= set(masks.TEST_PATTERNS)
    for name, gen in masks.TEST_PATTERNS.items():
        for s in range(4):
            a, b = gen(np.random.default_rng(s), 512), gen(np.random.default_rng(s), 512)
            assert a.dtype == np.uint8 and a.shape == (512, 512) and a.max() > 0, name
            assert np.array_equal(a, b), name
        assert not np.array_equal(gen(np.random.default_rng(0), 512), gen(np.random.default_rng(1), 512)), name


def test_test_pattern_masks_cover_every_pattern_and_extend():
    a = masks.test_pattern_masks(len(masks.TEST_PATTERNS), seed=3)
    assert sorted(masks.test_pattern_of(k) for k in a) == sorted(masks.TEST_PATTERNS)
    assert all(k.endswith(f"_{i:03d}") for i, k in enumerate(a))
    b = masks.test_pattern_masks(len(a) + 5, seed=3)
    assert all(np.array_equal(a[k], b[k]) for k in a)  # mask i depends on (seed, i) only
    c = masks.test_pattern_masks(len(a), seed=4)
    assert list(c) != list(a) or any(not np.array_equal(a[k], c[k]) for k in a)
    only = masks.test_pattern_masks(4, seed=1, size=256, patterns=["dots", "grating"])
    assert {masks.test_pattern_of(k) for k in only} == {"dots", "grating"}
    assert all(m.shape == (256, 256) for m in only.values())
    with pytest.raises(ValueError, match="unknown test patterns"):
        masks.test_pattern_masks(2, patterns=["zebra"])


@pytest.mark.parametrize("angle", [0, 90, 45, -45, 30])
def test_gratings_have_the_requested_pitch(angle):
    for pitch in (3, 5, 12, 30):
        m = masks.grating(np.random.default_rng(pitch), pitch=pitch, angle_deg=angle)
        assert abs(_pitch(m) - pitch) < 0.03 * pitch, (pitch, angle, _pitch(m))
    # drawn pitches span 3..30 px, duty cycle 0.3..0.7 (whole pixels)
    for s in range(20):
        m = masks.grating(np.random.default_rng(s), angle_deg=0)
        on = m.any(axis=1)
        rows = np.flatnonzero(on)
        p = np.diff(rows[np.r_[True, np.diff(rows) > 1]])  # line starts
        width = np.diff(np.flatnonzero(np.diff(np.r_[False, on, False])))[::2]  # on rows per line
        if len(p) > 2:  # the window may cut the first and the last line
            assert 3 <= p[1] <= 30 and np.all(p[1:] == p[1])
            assert max(1, 0.3 * p[1] - 0.5) <= width[1] <= min(p[1] - 1, 0.7 * p[1] + 0.5)


def test_cut_off_gratings_break_the_period_at_one_place():
    for s in range(6):
        m = masks.grating_cutoff(np.random.default_rng(s), variant="edge", pitch=10)
        r, c = np.nonzero(m)
        assert min(r.min(), c.min(), 511 - r.max(), 511 - c.max()) < 10  # runs off the field on one side
        t = masks.grating_cutoff(np.random.default_rng(s), variant="truncated", angle_deg=0, pitch=10, duty=0.5)
        rows = np.flatnonzero(t.any(axis=1))
        runs = np.diff(np.flatnonzero(np.diff(np.r_[False, t.any(axis=1), False])))[::2]  # line widths
        assert np.all(runs[:-1] == 5) and 1 <= runs[-1] < 5, runs
        assert np.all(np.diff(rows[np.r_[True, np.diff(rows) > 1]]) == 10)


def test_dots_and_lines_are_isolated_and_graded():
    for s in range(4):
        d = masks.dots(np.random.default_rng(s))
        lab, n = ndimage.label(d > 0)
        areas = np.bincount(lab.ravel())[1:]
        assert areas.min() == 1 and 280 <= areas.max() <= 330  # 1 px to 20 px across
        sizes, repeats = np.unique(areas, return_counts=True)
        assert len(sizes) >= 6 and np.all(repeats == repeats[0])  # no two dots merged: each size once per row
        li = masks.lines(np.random.default_rng(s), angle_deg=0)
        widths = np.diff(np.flatnonzero(np.diff(np.r_[False, li.any(axis=1), False])))[::2]
        assert widths.min() == 1 and widths.max() == 20 and np.all(np.diff(widths) != 0)


def test_partial_and_near_threshold_doses():
    for s in range(6):
        p = masks.partial(np.random.default_rng(s))
        on = p[p > 0]
        assert on.max() >= 190 and on.min() <= 100  # the dose falls across the pattern
        g = np.unique(masks.near_threshold(np.random.default_rng(s)))
        assert len(g) == 2 and 90 <= g[1] <= 150


def test_the_papers_trial_masks_carry_the_registration_marks_only_when_asked(tmp_path):
    """``unscatter masks trial --fiducials`` (``trial_masks.paper_fiducials``): the paper's
    random masks with the three marks and their cleared band, the rest of each mask as the
    paper has it; without the flag the masks are the paper's, unmarked."""
    from click.testing import CliRunner

    from unscatter.cli import main
    from unscatter.io import read_mask

    paper = masks.trial_masks(4, seed=3)
    for flags, marked in (([], False), (["--fiducials"], True), (["--no-fiducials"], False)):
        out = tmp_path / ("default" if not flags else flags[0])
        res = CliRunner().invoke(main, ["masks", "trial", str(out), "--count", "4", "--seed", "3", *flags])
        assert res.exit_code == 0, res.output
        assert sorted(p.stem for p in out.glob("*.png")) == sorted(paper)
        for mid, m in paper.items():
            got = read_mask(out / f"{mid}.png")
            assert masks.carries_marks(got) == marked, (flags, mid)
            assert np.array_equal(got, masks.with_fiducials(m) if marked else m), (flags, mid)
