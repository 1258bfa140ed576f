"""Registration of a print batch: the steps in order, the QC rules, the outputs."""

from __future__ import annotations

import contextlib
import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import tifffile
from scipy import ndimage

from ..settings import REGISTRATION
from ..masks import carries_marks, fiducial_marks
from ..io import InputError, open_batch, output_dir, read_mask, write_png, write_rgb, write_tsv, write_yaml
from .flatfield import correct_image, dense_level, reference_level, stain_field, stain_ratio
from .priors import rotation_range, scale_prior, scale_range
from .pose import (KERNEL_TAIL, KERNEL_WIDTH, STAIN_SLOPE, TAIL, Fit, coarse_candidates, dose_sensitivity, kernel_error, kernel_moves,
                   kernel_spread, feature_places, place_dose_spread, print_template, evidence, contradicted, h3, log_scale, pose_distance, pose_of, project_similarity, pose_moves, refine,
                   merged_features, print_level, similarity, refine_ecc, self_similar_moves, size_spread, to_design,
                   edge_misfit, EDGE_SD, NUISANCE)
from .parallel import forked_map
from .template import (PrintTemplate, blurred_mask, field_alternatives, fit_hot_spot, fit_template, half_cure_level, mean_ncc, ncc,
                       well_fitted)

log = logging.getLogger(__name__)

MARGIN = 32  # design px of context around the design region in templates


class RegistrationError(RuntimeError):
    """One or more prints failed registration QC."""


@dataclass
class Settings:
    mode: str = REGISTRATION.default.mode  # or "affine"
    level: float = REGISTRATION.default.level  # print = density >= level * dense polymer
    min_score: float = REGISTRATION.default.min_score
    rotation_deg: tuple = (-20.0, 20.0)  # searched range of the image's rotation
    scale_range: tuple = (0.6, 1.6)  # image px per mask px, searched when no camera pixel size is known
    scale_tolerance: float = 0.05  # with a known camera pixel size, the scale is searched within this
    min_coverage: float = 0.995
    poly_degree: int = 2
    min_background_snr: float = 5.0
    min_print_px: int = 30  # image px above threshold for a print to count as non-empty (and the area, in design
    # px, of the least cured speck that the faint test allows for: speck_peak)
    template_sigma: float = 2.0  # mask px
    dense_quantile: float = 0.9
    candidates: int = 3  # distinct coarse poses refined per print
    min_evidence: float = 4.0  # z a pose needs over every distinct alternative (pose.evidence)
    distinct_px: float = 1.5  # poses further apart than this (RMS, design px) are distinct
    field_set_share: float = 0.005  # a rival whose mask differs from the chosen pose's over less than this share of the
    # cured part (mask_apart) is set apart by the template's field alone: the print is ambiguous, whatever the evidence
    symmetric_corr: float = 0.9  # a mask that correlates this well with itself rotated (blurred 2 px) is symmetric ...
    symmetric_dip: float = 0.1  # ... when its correlation dips by this much at some smaller turn (stars 0.2 to 0.7,
    # blocks, dots and checkerboards turned a little less than 0.05)
    mismatch_factor: float = 3.0  # a print whose misfit is this many times the batch median ...
    mismatch_sigmas: float = 4.0  # ... and this many robust sigmas above it does not match its mask
    mismatch_factor_max: float = 10.0  # (the limit is at most this many times the median)
    implausible_factor: float = 5.0  # noise or background this far from the batch's: not a print image
    min_misfit_px: float = 3.0  # ... and at least this (px per edge px): a mean edge error no print of its mask has
    max_misfit_px: float = 8.0  # misfit (px per edge px) that fails without a batch to compare with
    max_pose_sd: float = 0.5  # design px: a pose known worse than this (1 sd, RMS over the field) fails
    batch_range_min: int = 8  # determined prints needed to bound the poses of ambiguous ones by the batch's
    batch_range_gaps: float = 6.0  # ... range, widened by this many mean gaps (batch_range)
    rotation_mads: float = 4.0  # a print turned this many robust spreads from the batch's median rotation fails ...
    min_rotation_spread: float = 0.5  # ... the spread (deg) at least this (batch_rotation) ...
    rotation_off_prints: int = 3  # ... unless this many determined prints lie beyond it: the batch then has no one rotation
    max_size_sd: float = 1.5  # design px: a pose whose spread from its features' sizes is larger fails (a bound on a
    # systematic error, not a noise level: at 1.5 px the print may be as far off as 'silently wrong' means)
    hold_size_sd: float = 0.75  # design px: a print whose spread from its features' sizes is larger, and whose
    # scale agrees with its stated camera pixel size, is held to that where it is known more closely than the batch's
    # one magnification (half max_size_sd: the size spread is a 1-sd estimate, 1.5 to 2.4 times off on some prints)
    size_sd: float = 0.5  # design px: how far feature sizes may be off the template's, without a batch to measure it
    min_size_sd: float = 0.1  # ... and at least this with one (size_error)
    size_min_prints: int = 4  # prints whose pose their features' places fix, needed to measure it
    min_edge_sd: float = 0.1  # design px: edge places known at best this well (edge_place_sd)
    fixed_scale_sd: float = 0.004  # a batch whose prints that fix their own scale agree on it within this (robust sd
    # of the log scale) was imaged at one magnification: it holds the scale of prints that cannot fix theirs
    scale_min_prints: int = 6  # ... with at least this many such prints
    stated_min_prints: int = 3  # placed prints that measure a stated camera pixel size, fewer than scale_min_prints:
    # their largest deviation from their median bounds the spread (stated_scales)
    one_scale_within: float = 0.008  # ... and none of them further than this (log) off their median
    min_scale_sd: float = 0.001  # ... the scale then known within at least this (log)
    scale_sigmas: float = 4.0  # ... and a print of such a batch this many of its sd off the batch's scale fails
    declared_margin: float = 1.25  # polymer this many times brighter than a declared dense_level: a warning
    reference_spread: float = 0.15  # dense references whose levels differ by more than this share, or one whose block
    # is this uneven (robust sd over median): a warning (a stain, the lamp's field, a block not fully cured)
    marks_agree_px: float = 1.0  # design px: a print with registration marks whose pose on the marks alone is
    # further than this from the whole print's takes the marks' pose
    edge_pull_sds: float = 6.0  # a print whose fitted edge offsets lie this many of the batch's spreads off the
    # batch's (size_error) is refitted with them held there ...
    edge_pull_px: float = 1.0  # ... and fails where that moves its pose further than this (design px, RMS over the field)
    field_alternatives: bool = True  # a print is refitted under each lamp field that the batch's placed prints fit
    # about as well as their best (template.field_alternatives), and fails where that moves its pose further
    # than edge_pull_px (docs/registration.md, "The lamp's field that the template prints do not fix")
    stain_recheck: bool = True  # a print whose image was divided by its stain at its first chosen pose (5a) is
    # refitted on its image divided by its stain measured again at its final pose, and fails where that moves its
    # pose further than edge_pull_px from a refit on the image it was fitted on (docs/registration.md, "A pose
    # that rests on its stain's division")
    faint_fraction: float = 1.0  # an image too faint to register whose brightest polymer reaches this share of the
    # threshold, times the peak its mask's features image at (imaged_peak), is failed, not empty
    faint_sigmas: float = 1.0  # ... that peak taken in an image this many sds of the batch's brightness dimmer (dimmest)
    empty_cure_share: float = 0.9  # ... unless the batch's template, at the highest dose of its determined prints,
    # cures its mask nowhere to this share of the print level (relative to a large block's density at that dose):
    # then it is empty (uncured). 0: never
    template_min_prints: int = 3  # prints whose poses no rival contests, that the template is fitted on again (step
    template_refit_gain: float = 0.002  # 5a), and the mean NCC it must gain there for the poses to be chosen again
    template_posed: bool = True  # the template's numbers fitted with each print's small pose moves (fit_template's
    # ``posed``), not at poses held from the template before: held, a common scale error of the poses goes into a lamp
    # field that keeps the next poses off (our lab's trial prints: median pose error 0.193 -> 0.073 px posed; docs/registration.md,
    # "The template's field and the poses' scale"). It costs 10 to 15 % of registration time; over 1024 random-lab
    # prints it took silently wrong prints 9 -> 2 (docs/registration.md, "Its cost, measured, and a cheaper form that failed")
    template_tail_restart: tuple | None = (0.3, 30.0)  # 5a's fit started again from its result with the scatter's
    # tail at this share and width (design px), the better of the two kept (None: one start). A fit that ends with
    # the haze in the tail's place is a poor optimum Powell does not leave; over three seeds' 24 labs the second start
    # took failed prints 287 -> 268 and silent errors 7 -> 6 (docs/registration.md, "A fifth fresh seed"). In every template fit
    # instead, one seed's silent errors went 2 -> 5
    stain_sigma_px: float = 16.0  # design px: the scale over which a print's uneven staining is measured (stain_field) ...
    stain_min_sd: float = 0.06  # ... and its spread across the print's interiors that divides it out (inf: never)
    stain_batch_sd: float = 0.02  # ... down to this in a batch where template_min_prints prints reach stain_min_sd
    stain_slope_sd: float = 0.1  # ... and in such a batch each print's brightness slopes across the field are fitted
    # with its pose, this their prior sd (``pose.BRIGHTNESS``; 0: none)
    stain_threshold: bool = True  # the prints of a batch that stains are thresholded on their images divided by the
    # stain (its field across the print, stain_divisor, and where the batch stains its mean over the print), and the
    # batch's dense level is taken from those images (False: on the images as they are)
    stain_cured: float = 0.9  # ... the mean only for prints whose template reaches this share of full cure over their
    # interiors (a thin line's gain trades with its dose: divided by it, lines came out 1.6 to 4.5 px too small)
    half_cure: bool = False  # each print is cut at the image level where the batch's template crosses its half cure
    # (template.half_cure_level), not at ``level`` of the dense polymer: the microscope's blur of the polymer's uneven
    # rise shifts the level set (off by default: measured on 28 random labs, not yet through the registration tests)
    hot_spot_gain: float = 2e-4  # mean NCC a lamp hot spot in the print template must gain on prints it was not
    # fitted to (fit_hot_spot; inf: no search)
    skip_failed: bool = REGISTRATION.default.skip_failed
    threads: int = 2  # registration's workers: threads, and for the pose searches as many forked processes (Linux;
    # ``parallel``); a batch registers alike at any number
    extra: dict = field(default_factory=dict)


@dataclass
class PoseChoice:
    """The chosen pose of one print and how it was chosen."""

    fit: Fit | None
    evidence: float = float("inf")  # z of the chosen pose over the nearest distinct rival
    rival: np.ndarray | None = None  # the rival's grid -> image pose, when one was close
    tried: int = 0
    symmetry: float | None = None  # deg: the mask maps onto itself rotated by this, and the rival is the chosen pose so turned
    # the rival least set apart by the image whose mask differs from the chosen pose's over less than
    # Settings.field_set_share of the cured part (mask_apart): (its evidence, that share, its grid -> image pose)
    field_set: tuple | None = None
    # z of the nearest rival set aside by a part of the print that only the chosen pose
    # explains (``contradicted``): for the print's own QC no rival, for the batch's fits
    # (``settled``) as if it were one, so that they rest on the prints the evidence places
    aside: float = float("inf")

    @property
    def settled(self) -> float:
        """The evidence over every rival, those set aside by a contradiction too."""
        return min(self.evidence, self.aside)

    @property
    def converged(self) -> bool:  # the chosen pose's refinement settled (a refit held to a scale: that refit's)
        return self.fit is not None and self.fit.converged

    @property
    def poses(self) -> list:
        """The chosen pose and its rival, if any: where choosing it again starts."""
        return [self.fit.M] + ([self.rival] if self.rival is not None else [])


# --------------------------------------------------------------------------- steps


def first_pose(mask: np.ndarray, img: np.ndarray, s: Settings, scale: tuple):
    """Distinct coarse poses against the blurred mask; the best one refined by ECC."""
    tpl = blurred_mask(mask, s.template_sigma, MARGIN)
    cands = coarse_candidates(tpl, img, s.rotation_deg, scale, s.candidates)
    starts = [M for _, M in cands]
    try:
        M, _ = refine_ecc(tpl, img, starts[0])
        c = ((tpl.shape[1] - 1) / 2, (tpl.shape[0] - 1) / 2)
        return [project_similarity(M, c) if s.mode == "similarity" else M] + starts, True
    except cv2.error:
        return starts, False


HELD_RESCALE = 0.002  # a print held to a scale (step 5c) this far (log) off it is refined from that scale
EDGE_HOLD_SD = 1e-3  # design px: the prior sd that holds a print's edge offsets at the batch's (step 5d'')
FAR_DEG, FAR_SCALE = 5.0, 1.1  # choose_pose: a coarse start this far beyond the searched rotations or scales stops
SYMMETRY_FACTOR = 2  # choose_pose: the mask's turns onto itself are sought at half resolution (at a quarter, a fine
# star's spokes merge: a 36-spoke star showed no symmetry and was `ok` two spokes, 77 px, off)


def mask_apart(m: np.ndarray, a: tuple, b: tuple, shape, blur: float = 2.0, widen: int = 6) -> tuple[float, float]:
    """Where two poses ``a`` and ``b`` ((Fit, template), as ``evidence``'s) put different
    parts of the mask on what either predicts cured, and how far they move that part.

    The share: the area where the two poses' masks in the image (``m``, the padded mask
    on the templates' grid, each blurred ``blur`` px) differ by half or more, within
    either's cured part (its template at a quarter of its top or more, widened by
    ``widen`` px), over the area of the mask there. The blur forgives the two poses'
    lines a misfit of a fraction of it; the caller keeps it under a quarter of the poses'
    distance, so that two poses a pixel or two apart, which move every edge, do not read
    as laying the same mask. The move: the median distance (design px) between where the
    two poses send the grid's points that either predicts cured.

    The share is near 0 where the two poses lay the same mask over the whole cured part:
    a grating that spans the field, a pitch along, so that only the template's field,
    placed with the pose, sets them apart; a pitch along a grating whose ends cured moves
    its end lines, and a dot array's rows, by a share of some per cent. Only with a move
    of a pattern's period is that share a sign of it: two poses that differ only away
    from the cured part (a small turn about it) lay the same mask there as well."""
    def warp(T, f):
        return cv2.warpAffine(T, f.M, (shape[1], shape[0]), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                              borderValue=0.0)

    def top(T):  # what a template predicts cured: a quarter of its top or more
        return T >= 0.25 * max(float(T.max()), 1e-9)

    cured = top(warp(a[1], a[0])) | top(warp(b[1], b[0]))
    cured = cv2.dilate(cured.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * widen + 1, 2 * widen + 1))) > 0
    Ma = cv2.GaussianBlur(warp(m, a[0]), (0, 0), blur)
    Mb = cv2.GaussianBlur(warp(m, b[0]), (0, 0), blur)
    area = float(((Ma >= 0.5) & cured).sum())
    share = float((np.abs(Ma - Mb) >= 0.5)[cured].sum()) / max(area, 1.0)
    y, x = np.nonzero((top(a[1]) | top(b[1]))[::4, ::4])
    if not len(x):
        return share, 0.0
    d = pose_moves(a[0].M, b[0].M, np.stack([4.0 * x, 4.0 * y]))
    return share, float(np.median(np.hypot(d[0], d[1])) / np.sqrt(abs(np.linalg.det(a[0].M[:, :2]))))


def choose_pose(mask: np.ndarray, img: np.ndarray, starts: list, x, s: Settings, design_px: int, scale: tuple,
                rotation: tuple | None = None) -> PoseChoice:
    """Refine every start, add the moves under which the print maps onto itself, and keep
    the pose the image prefers over every distinct rival (``pose`` module doc). Two poses
    that fit alike are rivals only if a barrier lies between them; where the pose halfway
    between fits clearly better than both (a grating's pitch either side of a pose that no
    start reached), that pose is refined and competes.

    ``scale`` and ``rotation`` (default ``s.rotation_deg``) bound the poses that count: a
    pose outside them is no rival."""
    rotation = tuple(s.rotation_deg if rotation is None else rotation)
    half = PrintTemplate(design_px, MARGIN, factor=2)
    full = PrintTemplate(design_px, MARGIN)
    m_full = full.padded(mask)
    B_half = half.exposure(half.padded(mask), x)
    B_full = full.exposure(m_full, x)
    n = full.shape[0]

    def coarse(M, known=()):  # half resolution: every start and every move; None where it joins a known pose
        f = refine(img, M, half, B_half, x, s.mode, iters=30, tol=0.02, spread=False, known=[g[0].M for g in known],
                   outside=far_outside)
        return None if f.joined else (f, predicted_print(half, B_half, x, f))

    def coarse_all(Ms, known=()):
        out = []
        for M in Ms:
            f = coarse(M, list(known) + out)
            if f is not None:
                out.append(f)
        return out

    def fine(f):  # full resolution: the poses still in the running
        f = refine(img, f[0], full, B_full, x, s.mode, iters=12, tol=0.01)
        return f, predicted_print(full, B_full, x, f)

    def in_range(M, deg=1.0, factor=1.01):  # within the searched ranges, widened by ``deg`` and ``factor``
        p = pose_of(M, n, img.shape)
        return (rotation[0] - deg <= p["rotation_deg"] <= rotation[1] + deg
                and scale[0] / factor <= p["scale"] <= scale[1] * factor)

    def plausible(f):  # a pose outside the searched ranges is no rival: the prior excludes it
        return in_range(f[0].M) and f[0].gain > 0

    def far_outside(M, gain) -> bool:  # a coarse start walking where no pose counts (refine's ``outside``): its gain
        # negative (a grating half a pitch off), or turned or scaled well beyond what ``in_range`` counts
        return gain <= 0 or not in_range(M, FAR_DEG, FAR_SCALE)

    def dedupe(fits):
        out = []
        for f in fits:
            if all(pose_distance(f[0].M, g[0].M, n, MARGIN) > 0.5 for g in out):
                out.append(f)
        return out

    def tournament(fits, factor):
        best = fits[0]
        for f in fits[1:]:
            if evidence(img, f, best, factor=factor) > 0:
                best = f
        return best

    found = coarse_all(starts)
    fits = dedupe(found)
    fits = [f for f in fits if plausible(f)] or fits[:1]
    best = tournament(fits, 2)
    moves = self_similar_moves(predicted_print(full, B_full, x, best[0]), rotation_span=max(10.0, s.rotation_deg[1] - s.rotation_deg[0]))
    fits = dedupe([best] + [f for f in fits if f is not best]
                  + [f for f in coarse_all([(h3(best[0].M) @ S)[:2] for S in moves], found) if plausible(f)])
    best = tournament(fits, 2)
    # rivals clearly worse at half resolution are settled; the rest are compared at full
    close = [f for f in fits if f is not best and pose_distance(f[0].M, best[0].M, n, MARGIN) > s.distinct_px
             and evidence(img, best, f, factor=2) < 3 * s.min_evidence]
    best = fine(best)
    z_min, rival, z_aside = float("inf"), None, float("inf")
    field_set = None

    def field_set_rival(best, f, z):
        """(evidence ``z``, share, ``f``, ``best``) where rival ``f`` lays the same mask as
        ``best`` over the cured part and only the field sets them apart; None where it does not."""
        d = pose_distance(f[0].M, best[0].M, n, MARGIN)
        share, moved = mask_apart(m_full, best, f, img.shape, blur=min(2.0, d / 4))
        log.debug("field-set check: rival %.1f px away, its cured part moved %.1f px, evidence %.1f, masks apart "
                  "over %.4f of the cured part", d, moved, z, share)
        if share < s.field_set_share and moved > s.distinct_px:  # a period along, not a pose that differs
            # only where nothing cured (whose uncertainty the pose spread holds)
            return z, share, f, best
        return None

    def halfway(a, b):
        """The pose halfway between two poses (the nuisance numbers too), and how much
        worse it fits than the better one (``evidence``). A barrier lies between them when
        it fits clearly worse: a grating's half pitch or a star's half spoke does; a scale
        traded against the print's dose along one valley does not. It fits clearly better
        when the two are a grating's pitch either side of a pose that no start reached."""
        mid = Fit(0.5 * (a[0].M + b[0].M), 0.5 * (a[0].gain + b[0].gain), 0.5 * (a[0].offset + b[0].offset),
                  0.5 * (a[0].q + b[0].q), a[0].sigma, a[0].pose_sd, True, 0)
        return mid, evidence(img, a, (mid, predicted_print(full, B_full, x, mid)))

    pending, between = [fine(f) for f in close], 0
    while pending:
        f = pending.pop(0)
        if pose_distance(f[0].M, best[0].M, n, MARGIN) <= s.distinct_px:
            continue  # it came back to the same pose at full resolution
        z = evidence(img, best, f)
        if z < 0:
            best, f, z = f, best, -z
        if z >= s.min_evidence and (field_set is None or z < field_set[0]):  # for the final QC only: the prints the
            # template is fitted at stay those the whole image places
            field_set = field_set_rival(best, f, z) or field_set
        if z < s.min_evidence:
            mid, z_mid = halfway(best, f)
            if z_mid <= -s.min_evidence and between < 2:  # the pose between them fits clearly better: refined, it competes
                between += 1
                pending.append(fine((mid, None)))
                continue
            if z_mid < s.min_evidence:
                continue  # one valley with the best pose, not a second pose: the pose spread covers it
            # a rival that leaves a cured part unexplained, or predicts one where the image shows
            # none, while the best pose explains the image there and nowhere misses what the
            # rival explains (a dot array a row along, of which three dots printed): no rival
            c_best, c_rival = contradicted(img, best, f, s.min_print_px)
            log.debug("rival %.1f px away at evidence %.1f: parts of %.0f px only the best pose explains, %.0f only the rival",
                      pose_distance(f[0].M, best[0].M, n, MARGIN), z, c_best, c_rival)
            if c_best > 0 and c_rival == 0:
                z_aside = min(z_aside, z)
                continue
        if z < z_min:
            z_min, rival = z, f[0].M
    # a mask that maps onto itself rotated (a Siemens star by a spoke pair) leaves the
    # choice between the poses so turned to details of the print (how anisotropic scatter
    # widens spokes of each direction) that its model may get wrong, however clearly the
    # image prefers one: within the ranges, they are rivals whatever the evidence
    # (its print then maps onto itself turned as well: only then is the mask looked at)
    symmetries = []
    if any(abs(S[0, 1]) > 1e-6 for S in moves):
        m = cv2.GaussianBlur(m_full.astype(np.float32), (0, 0), 2.0)
        symmetries = self_similar_moves(m, rotation_span=max(10.0, rotation[1] - rotation[0]), min_corr=s.symmetric_corr,
                                        shifts=False, dip=s.symmetric_dip, factor=SYMMETRY_FACTOR)
    for R in symmetries:
        alt = (h3(best[0].M) @ R)[:2]
        # the turn keeps the scale: only the rotation can put the turned pose out of range (a
        # star whose fitted scale, resting on its size, lay 1 % beyond the batch's range had
        # no rival by it, and was `ok` a spoke, 66 px, off)
        if in_range(alt, factor=float("inf")) and pose_distance(alt, best[0].M, n, MARGIN) > s.distinct_px:
            return PoseChoice(best[0], 0.0, alt, len(fits), float(np.degrees(np.arctan2(R[1, 0], R[0, 0]))))
    if field_set is not None and field_set[3] is not best:
        # found against a pose that a later rival beat: checked again against the chosen one (the
        # rival then may be the chosen pose itself, and the pose it was found against the rival)
        _, _, f, anchor = field_set
        other = anchor if pose_distance(f[0].M, best[0].M, n, MARGIN) <= s.distinct_px else f
        z = evidence(img, best, other)
        field_set = (field_set_rival(best, other, z) if z >= s.min_evidence
                     and pose_distance(other[0].M, best[0].M, n, MARGIN) > s.distinct_px else None)
    return PoseChoice(best[0], z_min, rival, len(fits), aside=z_aside,
                      field_set=None if field_set is None else (field_set[0], field_set[1], field_set[2][0].M))


def determined(ch: PoseChoice, s: Settings) -> bool:
    """A pose the print fixes on its own: converged, no rival close, a small spread."""
    return ch.fit is not None and ch.converged and ch.settled >= s.min_evidence and ch.fit.pose_sd <= s.max_pose_sd


def fails_anyway(ch: PoseChoice, s: Settings) -> bool:
    """A chosen pose that QC fails whatever the later steps find (``finish``'s reasons):
    none, not converged, the mask's symmetry or a rival close, a spread above the limits."""
    f = ch.fit
    return (f is None or not f.converged or ch.symmetry is not None or ch.evidence < s.min_evidence
            or not f.pose_sd <= s.max_pose_sd or not np.hypot(f.size_sd, f.model_sd) <= s.max_size_sd)


def batch_range(poses: list[dict], s: Settings):
    """The rotation (deg) and scale range of a batch's determined prints, widened by
    ``batch_range_gaps`` times the mean gap between neighbouring values (and at least
    1 deg, 1 %): ((lo, hi), (lo, hi)), or None with fewer than ``batch_range_min`` prints.

    One microscope images a batch; a print whose pose is ambiguous within the searched
    ranges (a Siemens star whose spokes repeat within +-20 deg) is then chosen among the
    poses in this range. With n prints drawn from a range, the range's true ends lie
    beyond the widened one with probability of the order exp(-gaps) each, and a new print
    falls there with probability of the order 2 exp(-gaps) / (n + 1). With 3 gaps, a
    lab that turned each sample by hand within +-13 deg had its 11 determined prints
    within -6.8..10.9 deg, the widened range began at -11.2, and a Siemens star turned
    -11.7 deg was chosen ok one spoke pair (13.8 deg) off, its true pose no rival
    outside the range: the range is widened by 6 gaps (15.6 deg there; the star is then
    ambiguous).
    """
    if len(poses) < s.batch_range_min:
        return None
    out = []
    for v, floor in ((np.array([p["rotation_deg"] for p in poses]), 1.0), (np.log([p["scale"] for p in poses]), 0.01)):
        m = max(floor, s.batch_range_gaps * (v.max() - v.min()) / (len(v) + 1))
        out.append((float(v.min() - m), float(v.max() + m)))
    (rlo, rhi), (slo, shi) = out
    return (rlo, rhi), (float(np.exp(slo)), float(np.exp(shi)))


def batch_rotation(rotations: list, s: Settings) -> tuple[float, float] | None:
    """(median, limit) of the rotations (deg) of a batch's determined prints: a print
    turned further than ``limit`` from the median is an outlier (a star one spoke off
    that the image preferred, a grating turned onto its own lines), not how this
    microscope images. The limit is ``rotation_mads`` times the rotations' robust spread
    (1.4826 MAD, at least ``min_rotation_spread`` deg): for rotations drawn uniformly
    within +-a (a sample placed by hand) about 3 a, for one fixed rotation 2 deg. None with fewer than ``batch_range_min`` prints.

    Also None where ``rotation_off_prints`` or more of the prints lie beyond the limit:
    one print turned far off is an outlier, several are how the microscope images. Prints
    placed by hand within +-11 deg (seed 1985358721's lab 5), most of whose determined
    prints by chance lay within 3..8 deg, gave a median of 4.8 deg and a limit of 9.2, 3 of
    the 13 beyond it: prints 0.06 to 0.16 px off failed as turned off the batch's, and the
    batch's range, drawn from the others, put a Siemens star's true pose (-10.7 deg) out of
    range, so that the pose one spoke pair off (+9.3 deg) had no rival and was `ok`, 73 px
    off."""
    if len(rotations) < s.batch_range_min:
        return None
    centre, sd = median_sd(rotations)
    limit = s.rotation_mads * max(s.min_rotation_spread, sd)
    off = int(np.count_nonzero(np.abs(np.asarray(rotations, float) - centre) > limit))
    if off >= s.rotation_off_prints:
        log.info("%d of %d determined prints turned more than %.1f deg off their median rotation %.1f deg: the microscope "
                 "turns by image, no one rotation", off, len(rotations), limit, centre)
        return None
    return centre, limit


def batch_scale(fits: list, s: Settings) -> tuple[float, float] | None:
    """The batch's scale when one magnification imaged it: (median log scale, its robust
    spread, at least ``min_scale_sd``) over ``fits`` (prints whose features' places fix
    their pose), or None when fewer than ``scale_min_prints`` of them or when their spread
    is above ``fixed_scale_sd`` (a zoom set per image: each print's scale is its own), or
    when any of them is more than ``one_scale_within`` off their median.

    The spread is that of single prints (the magnification's own variation and each
    print's measurement error), not of the median: it is what a further print's scale may
    be off by. It is robust, and a few prints of a zoom set per image may agree by chance:
    seven prints of our own lab at a zoom of 1.22 to 1.25 per image gave a spread of 0.23
    %, one of them 1.20 % off (and one 0.78 %), and held to their median, three prints
    were `ok` 1.7 to 3.2 px off. So one print as far off as no refocusing moves a scale is
    enough to say that the magnification was set per image: in the random labs of one
    objective the prints were at most 0.48 % off their median (0.09 to 0.48 % in five
    labs), in those of a zoom at least 3.7 % (docs/registration.md, "One magnification by chance"). A
    print whose template pulls its scale off by more than 0.8 % then costs the batch its
    one magnification: prints that needed it fail rather than pass at a wrong scale.
    """
    if len(fits) < s.scale_min_prints:
        return None
    scales = [log_scale(f.M) for f in fits]
    centre, spread = median_sd(scales)
    if spread > s.fixed_scale_sd:
        return None
    off = float(np.max(np.abs(np.asarray(scales) - centre)))
    if off > s.one_scale_within:
        log.info("no one magnification: %d prints whose features fix their scale agree within %.2f %% (robust spread), "
                 "but one is %.2f %% off their median (more than %.2f %%)", len(scales), 100 * spread, 100 * off,
                 100 * s.one_scale_within)
        return None
    return centre, max(spread, s.min_scale_sd)


def one_magnification_held(one_scale: tuple, prints: int, s: Settings) -> tuple[float, float]:
    """The scale every print of a batch of one magnification is held to (``batch_scale``:
    its median log scale and single prints' spread, from ``prints`` prints): the median,
    within its own uncertainty (the spread over the square root of the prints) and a
    zoom's repeatability between images (``min_scale_sd``), in quadrature. The single
    prints' spread is mostly each fit's own error (a template that misplaces edges pulls
    one print's scale, not the magnification), which holding removes."""
    return one_scale[0], float(np.hypot(s.min_scale_sd, one_scale[1] / np.sqrt(max(prints, 1))))


def size_error(fits: list, s: Settings) -> tuple[tuple, tuple]:
    """The size of a print's features against the batch template's, (centre, spread) of the
    edge offsets (e0, c2, s2; design px) fitted on prints whose pose their features' places
    fix: for them the fitted offsets measure the template's size error (erosion or swelling,
    anisotropic scattering: the batch's), for a print that is one feature they trade
    against its scale. Median and 1.4826 MAD (c2 and s2 pooled), the spread at least
    ``min_size_sd``; no offset and ``size_sd`` with fewer than ``size_min_prints`` prints."""
    if len(fits) < s.size_min_prints:
        return (0.0, 0.0, 0.0), (s.size_sd,) * 3
    e = np.array([[f.edge, f.edge_c2, f.edge_s2] for f in fits])
    centre = np.median(e, axis=0)
    mad = 1.4826 * np.median(np.abs(e - centre), axis=0)  # robust: a partial print among them does not set it
    aniso = float(max(s.min_size_sd, np.hypot(mad[1], mad[2]) / np.sqrt(2)))
    return tuple(float(v) for v in centre), (float(max(s.min_size_sd, mad[0])), aniso, aniso)


def edge_place_sd(misfits: list, s: Settings) -> tuple[float, float | None]:
    """How far one boundary pixel's place may be off (``size_spread``'s ``edge_sd``): the
    fixed EDGE_SD (0.4 px), or less where the batch's prints whose pose their features'
    places fix (at least ``size_min_prints``) show, by their median ``edge_misfit``, that
    its template places edges closer than that; never below ``min_edge_sd``. The misfit
    counts every residual as an edge's displacement (a stain too), so it only lowers the
    spread: a larger one is not taken as a measure of the edges. Returns (that spread,
    the median misfit of the finite ones, None without any)."""
    m = [v for v in misfits if np.isfinite(v)]
    median = float(np.median(m)) if m else None
    if len(m) < s.size_min_prints:
        return EDGE_SD, median
    return float(min(EDGE_SD, max(s.min_edge_sd, median))), median


def stated_scales(priors: dict, placed: dict, s: Settings) -> tuple[dict, str]:
    """The scale priors from stated camera pixel sizes that the batch can use (id -> (log
    scale, sd)), and a note for the prints that would need one when it cannot.
    ``priors``: id -> (log scale, sd) from ``scale_prior`` or None; ``placed``: id ->
    fitted log scale of the prints whose features fix their pose.

    What metadata states well is the ratio between images (the software knows each
    image's zoom); its absolute value is a calibration that may be off (a stale one,
    another camera adapter) and the registration's own scale may be biased by the
    template's sizes (anisotropic scatter) by a few tenths of a per cent. So, as
    ``batch_scale`` does for one magnification, the placed prints measure the stated
    sizes: with at least ``scale_min_prints`` of them, the stated log scales are shifted
    by the median of (fitted - stated), and a print's scale is known within the robust
    spread of those differences (at least ``min_scale_sd``), what a further print's scale
    may be off by. With fewer, but at least ``stated_min_prints``, they are shifted
    alike, each known within the largest deviation of those few from their median (a
    robust spread of three to five values may be small by chance; the largest deviation
    is the cautious estimate; of five, the second largest, as one print's template may
    pull its scale far off), where that is closer than the stated tolerance's sd. In
    lab 4 of seed 777123 (one objective, its size stated within 0.6 %, 0.15 % off the
    truth, heavy scatter) 5 prints fixed their scale, four of them within 0.03 % of each
    other and one 0.55 % off; held to the stated size at its tolerance, 11 prints failed
    as uncertain by 0.9 px. Otherwise the stated sizes are used as stated, within their
    tolerance (two sd), unless those few contradict them by more than the tolerance in
    the median: then none is used, and the prints that would need one fail as
    undetermined rather than be held to a scale the batch contradicts.

    Returns (id -> (log scale, sd) of the stated scales used, a note for the prints that
    would need one, the log shift that the check of every print's scale against its
    stated range allows: 0, or where the prints contradict the stated size, their median
    offset, so that a print as far off the stale calibration as the batch's own placed
    prints is not failed for it; the range is widened toward it, not moved)."""
    priors = {k: v for k, v in priors.items() if v is not None}
    d = np.array([placed[k] - priors[k][0] for k in placed if k in priors])
    if not priors:
        return {}, "", 0.0
    off = float(np.median(d)) if len(d) else 0.0

    def shifted(sd: float) -> dict:  # the stated scales moved by the prints' median offset, each known within sd
        return {k: (v[0] + off, sd) for k, v in priors.items()}

    if len(d) >= s.scale_min_prints:
        spread = 1.4826 * float(np.median(np.abs(d - off)))
        sd = max(s.min_scale_sd, spread)
        log.info("stated camera pixel size: %d prints whose features fix their scale are %+.2f %% off it (spread %.2f %%): "
                 "the stated scales shifted by that, each known within %.2f %%", len(d), 100 * off, 100 * spread, 100 * sd)
        return shifted(sd), "", 0.0
    tol = float(np.median([2 * v[1] for v in priors.values()]))
    if abs(off) <= tol and len(d) >= s.stated_min_prints:
        dev = np.sort(np.abs(d - off))
        spread = max(s.min_scale_sd, float(dev[-2] if len(d) >= 5 else dev[-1]))
        if spread < tol / 2:
            log.info("stated camera pixel size: %d prints whose features fix their scale are %+.2f %% off it: the "
                     "stated scales shifted by that, each known within %.2f %% (their largest deviation from it, of five "
                     "the second largest; the stated tolerance's sd is %.2f %%)", len(d), 100 * off, 100 * spread, 50 * tol)
            return shifted(spread), "", 0.0
    if abs(off) <= tol:
        log.info("stated camera pixel size: scale known within %.2f %% (its tolerance)%s", 100 * tol,
                 f", checked against {len(d)} prints whose features fix their scale" if len(d) else ", nothing to check it against")
        return priors, "", 0.0
    log.warning("the stated camera pixel size is contradicted by %d prints whose features fix their scale: they are %+.2f %% "
                "off it, more than its tolerance; it is not used", len(d), 100 * off)
    return {}, (f": the stated camera pixel size, which would fix it, is not used (the prints whose features fix their "
                f"scale are {100 * off:+.2f} % off it, more than its tolerance)"), off


def field_radius_px(design_px: int) -> float:
    """The design field's RMS distance from its centre: a log scale error e moves a pose by
    e times this, RMS over the field (``pose.pose_distance``)."""
    return design_px / np.sqrt(6.0)


def stated_scatter(stated: dict, placed: dict, pose_sds: dict, design_px: int, misfit: float | None,
                   s: Settings) -> dict | None:
    """How far the batch's prints scatter about their stated camera pixel sizes beyond what
    their own fits say (``stated``: id -> (log scale, sd) as ``stated_scales`` shifted them;
    ``placed``: id -> fitted log scale, ``pose_sds``: id -> pose spread, of the prints whose
    features' places fix their pose), or None with fewer than ``scale_min_prints`` of them.

    Metadata states the ratio between images well (the software knows each image's zoom),
    so the robust spread of (fitted - stated) is the prints' own scale error. Over the
    design field a log scale error e moves the pose by e times the field's RMS radius
    (design_px / sqrt(6)). Where that is larger than the pose spreads those prints claim
    (their median), either the stated ratios or the prints' scales are off by the excess.
    Which one, the batch's print template tells: where it misplaces the edges of those
    prints by more than EDGE_SD (``misfit``, their median ``edge_misfit``), the fits miss
    something that pulls their scale (a lamp hot spot it does not hold, an uneven stain),
    and the excess is theirs (``excess_px``); where it places them as closely as that, the
    fits are to be believed and the excess is the metadata's (``excess_px`` 0). In lab 5
    of seed 3354286069 (a hot spot of 0.33, an uneven stain of 18 %) the prints scattered
    by 0.54 % (1.1 px) while claiming 0.3 px, their edges 1.6 px off the template's, and
    three of them were ``ok`` 1.6 to 2.5 px off. There the stated ratios are the better
    scale: a print whose features fix its scale is refitted with it held to the weighted
    mean of its own and its stated one as the batch's prints measure it, the stated one
    known within ``held_within`` (the uncertainty of that median, the spread over the
    square root of the prints, and a zoom's repeatability, ``min_scale_sd``, in
    quadrature, as ``one_magnification_held`` for one magnification). Returns spread
    (log), spread_px, claimed_px (that median), misfit_px, excess_px, held_within (None
    where the excess is 0) and prints."""
    d = np.array([placed[k] - stated[k][0] for k in placed if k in stated])
    if len(d) < s.scale_min_prints:
        return None
    spread = 1.4826 * float(np.median(np.abs(d - np.median(d))))
    spread_px = spread * field_radius_px(design_px)
    claimed = float(np.median([pose_sds[k] for k in placed if k in stated]))
    pulled = misfit is not None and misfit > EDGE_SD
    excess = float(np.sqrt(max(spread_px**2 - claimed**2, 0.0))) if pulled else 0.0
    held = float(np.hypot(s.min_scale_sd, spread / np.sqrt(len(d)))) if excess > 0 else None
    return dict(spread=spread, spread_px=spread_px, claimed_px=claimed, misfit_px=misfit, excess_px=excess,
                held_within=held, prints=int(len(d)))


def reference_levels(refs: list, images: dict, offset: float, ff_mode: str, s: Settings, source: Path) -> dict:
    """The dense level measured on the batch's dense reference prints (batch.yaml
    ``dense_reference``; ``flatfield.reference_level``), corrected as the batch's images
    are: the median of their levels, each one's level and unevenness (registration.yaml
    ``dense_reference``). A reference image without a block to measure is an error that
    names it; references that disagree, or an uneven block, a warning that names the
    batch's ``source`` (its batch.yaml)."""
    got = {}
    for mid in refs:
        k = correct_image(mid, images[mid], offset, s, ff_mode)
        try:
            got[mid] = reference_level(k)
        except ValueError as exc:
            raise InputError(images[mid], f"dense reference {mid!r} (batch.yaml dense_reference): {exc}") from None
    levels = np.array([v[0] for v in got.values()])  # positive: the median of a block above half its bright end
    level = float(np.median(levels))
    if levels.max() / levels.min() - 1 > s.reference_spread:
        log.warning("%s: the dense references' levels differ by %.0f %% (%s): their median %.3g is the batch's dense level",
                    source, 100 * (levels.max() / levels.min() - 1), ", ".join(f"{m} {v[0]:.3g}" for m, v in got.items()), level)
    for mid, (v, uneven, _) in got.items():
        if uneven > s.reference_spread:
            log.warning("%s: dense reference %s: its block's polymer varies by %.0f %% (robust sd over median): an uneven "
                        "stain or lamp field, or a block not cured through", source, mid, 100 * uneven)
    return dict(prints=list(refs), level=level, levels={m: round(v[0], 4) for m, v in got.items()},
                unevenness={m: round(v[1], 4) for m, v in got.items()}, interior_px={m: v[2] for m, v in got.items()})


def declared_level(declared: float, observed: float, corr: dict, ff_mode: str, s: Settings, source: Path,
                   key: str = "dense_level") -> tuple[float, float]:
    """The dense level and threshold from batch.yaml's ``dense_level`` (fully cured polymer
    over the background, which the lab measured) in place of the batch's own estimate
    (``flatfield.dense_level``: its brightest polymer, too low when no print cures fully).

    The corrected images are in units of the background when divided by it; a batch that
    falls back to subtraction is in those units too as long as no image's noise exceeds its
    background (``correct_image``), and otherwise cannot use the declared level: an error,
    not a threshold in the wrong units. Polymer brighter than the declared level by more
    than ``declared_margin`` suggests a wrong value: a warning, with both numbers.

    ``key`` "dense_reference": the level measured on the batch's dense reference prints
    (``reference_levels``), corrected as the batch's images are and so in their units
    whatever the flat field's mode."""
    if key == "dense_level" and ff_mode != "divide" and any(k.noise >= 1.0 for k in corr.values()):  # then in units of their noise
        raise InputError(source, f"{key} {declared:g} is in units of the background, but the background of some images is "
                                 f"below their noise, so the registration cannot put it in their units; remove {key}")
    if np.isfinite(observed) and observed > s.declared_margin * declared:
        log.warning("%s: the batch's brightest polymer reaches %.3g, %.0f %% above the %s level %.3g: %s", source, observed,
                    100 * (observed / declared - 1), key, declared,
                    "was the reference cured through?" if key == "dense_reference" else "is it for this stain and microscope?")
    log.info("dense level %.3g from %s in %s (the batch's brightest polymer: %.3g)", declared, key, source, observed)
    return float(declared), s.level * float(declared)


def implausible(corr: dict, s: Settings) -> dict:
    """Images that cannot be fluorescence images of prints of this batch, with the reason.

    A print image is mostly background, flat after the flat field, with the noise of the
    batch's other images. Full-range noise, a different kind of image or a different
    camera setting shows as a noise level or background far from the batch's: more than
    ``implausible_factor`` times the batch median either way (with at least three images
    to compare).
    """
    if len(corr) < 3:
        return {}
    # pixel noise from the high-passed image (robust to how much of the field is print,
    # unlike the background fit's residual), relative to the background level. Noise
    # below one camera count is not resolved: an image of integers whose background
    # sits a few counts above zero reads anywhere from 0 (every pixel the same count)
    # to 0.74 counts (half one count, half the next), so noise is taken as at least one
    # count. Without that floor, the 8-bit images of a lab whose background lay 4 to 5
    # counts above zero read 0.03 to 0.39 counts, and two print images were called no print.
    noise = {k: max(1.4826 * float(np.median(np.abs(c.c - cv2.GaussianBlur(c.c, (0, 0), 2.0)))), c.count)
             for k, c in corr.items()}
    bg = {k: c.background for k, c in corr.items()}
    mn, mb = float(np.median(list(noise.values()))), float(np.median(list(bg.values())))
    f = s.implausible_factor
    out = {}
    for k in corr:
        if not 1 / f <= noise[k] / max(mn, 1e-12) <= f:
            out[k] = f"its noise is {noise[k] / max(mn, 1e-12):.1f} times the batch's (background-relative)"
        elif mb > 0 and not 1 / f <= bg[k] / mb <= f:
            out[k] = f"its background is {bg[k] / mb:.2f} times the batch's"
    return out


def misfit_px(printed: np.ndarray, predicted: np.ndarray, thr: float) -> float:
    """How far a print is from its predicted print (the predicted image, thresholded at
    ``thr``): the area where they differ per edge pixel (a mean edge displacement, in
    design px), counted only where the prediction is clearly solid or clearly void, so
    that a near-threshold print, whose cure boundary no template places exactly, is not
    taken for a wrong one."""
    from ..metrics import edge_length_px

    solid = predicted >= thr
    sure = (predicted > 1.5 * thr) | (predicted < 0.5 * thr)
    edge = edge_length_px(printed) + edge_length_px(solid)
    return float(np.count_nonzero((printed ^ solid) & sure) / max(edge / 2, 1.0))


def determinacy_only(reason: str) -> bool:
    """Whether a QC reason only says that the pose is ambiguous or not determined (the fit
    itself converged, in range, well correlated)."""
    return bool(reason) and all(r.startswith(("ambiguous", "pose not determined")) for r in reason.split("; "))


def mismatched(rows: list[dict], s: Settings) -> dict:
    """Prints that disagree with their mask's predicted print far more than the batch's
    other prints do (a swapped or mislabelled image): misfit above ``mismatch_factor``
    times the batch median, ``mismatch_sigmas`` robust sigmas (1.4826 MAD, on the log
    misfit) above it but at most ``mismatch_factor_max`` times it, and ``min_misfit_px`` at
    least. With fewer than five prints to compare, ``max_misfit_px`` alone. The batch's
    prints to compare with are the ``ok`` ones and those that failed only because their
    pose is ambiguous or not determined (``determinacy_only``): their fits are as good."""
    vals = {r["id"]: r["misfit"] for r in rows if isinstance(r.get("misfit"), float) and np.isfinite(r["misfit"])}
    ref = [r["misfit"] for r in rows if (r["status"] == "ok" or determinacy_only(r["reason"])) and r["id"] in vals]
    if len(ref) < 5:
        return {k: f"misfit {v:.1f} px per edge px above {s.max_misfit_px}" for k, v in vals.items() if v > s.max_misfit_px}
    med, mad = median_sd(np.log(np.maximum(np.array(ref), 1e-3)))
    # prints of different patterns misfit differently (a fine grating more than a block), so
    # the spread only widens the limit up to ``mismatch_factor_max`` times the median
    spread = min(max(np.log(s.mismatch_factor), s.mismatch_sigmas * mad), np.log(s.mismatch_factor_max))
    lim = max(med + spread, np.log(s.min_misfit_px))
    return {k: f"misfit {v:.1f} px per edge px, the batch's median {np.exp(med):.2f}" for k, v in vals.items()
            if np.log(max(v, 1e-3)) > lim}


def dimmest(gains: list, s: Settings) -> float:
    """How much dimmer than the batch's median print an image may show the same polymer:
    exp(-faint_sigmas sd) for the robust sd (1.4826 MAD) of the log gains of the batch's
    determined prints (the lamp and the stain vary by image), 1 with fewer than 3 of them."""
    g = [np.log(v) for v in gains if v > 0]
    return float(np.exp(-s.faint_sigmas * median_sd(g)[1])) if len(g) >= 3 else 1.0


def median_sd(values) -> tuple[float, float]:
    """The median of ``values`` and their robust standard deviation (1.4826 MAD)."""
    v = np.asarray(values, float)
    centre = float(np.median(v))
    return centre, 1.4826 * float(np.median(np.abs(v - centre)))


def imaged_peak(mask: np.ndarray, blur: float, erode: float = 0.0) -> float:
    """The brightest a print of ``mask`` images at, as a share of its density, were every
    exposed pixel to cure at the same density: the exposed area, its edges moved in by
    ``erode`` (design px; a batch that erodes its prints), blurred by ``blur`` (design px),
    at its maximum. 1 for a print with a feature wider than a few blurs (and twice the
    erosion); less for thin lines and small dots only, 0 where erosion leaves nothing."""
    on = mask > 0
    if not on.any():
        return 1.0
    if erode > 0:  # a boundary pixel's centre lies 1 px from the nearest unexposed one, its edge 0.5 px
        on = np.clip(cv2.distanceTransform(on.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE) - erode, 0.0, 1.0)
    return float(cv2.GaussianBlur(on.astype(np.float32), (0, 0), max(blur, 0.3)).max())


def template_cure_share(tmpl: PrintTemplate, mask: np.ndarray, x, dose: float, block_peak: float | None = None) -> float:
    """The highest density the batch's template cures a mask to at ``dose`` (its scattered
    dose's peak through the template's cure curve, before the microscope's blur), as a
    share of the density of a large block (5/8 of the field, full grey) at that dose: what
    the print level, a share of the batch's dense polymer, is measured against.
    ``block_peak``: that block's scattered dose peak (``block_dose_peak``), where the
    caller has it."""
    if block_peak is None:
        block_peak = block_dose_peak(tmpl, mask.shape[0], x)

    def density(peak):
        return 1.0 - float(PrintTemplate.cured(np.float32(peak), x, dose)[1])

    full = density(block_peak)
    return density(float(tmpl.exposure(tmpl.padded(mask), x).max())) / full if full > 0 else 1.0


def block_dose_peak(tmpl: PrintTemplate, n: int, x) -> float:
    """The peak scattered dose of a block of 5/8 of an n x n field at full grey."""
    a = (3 * n) // 16
    block = np.zeros((n, n), np.uint8)
    block[a:n - a, a:n - a] = 255
    return float(tmpl.exposure(tmpl.padded(block), x).max())


def speck_peak(area_px: float, blur: float) -> float:
    """The brightest a cured speck of ``area_px`` design px (a disc) images at, as a share
    of its density, under a blur of ``blur`` design px (``imaged_peak``): near the
    threshold the cells' scatter cures specks of a feature, not the whole of it."""
    r = float(np.sqrt(area_px / np.pi))
    n = 2 * int(np.ceil(r + 4 * max(blur, 0.3))) + 1
    yy, xx = np.mgrid[:n, :n] - (n - 1) / 2
    return imaged_peak(np.where(xx * xx + yy * yy <= r * r, 255, 0).astype(np.uint8), blur)


def predicted_print(tmpl: PrintTemplate, B: np.ndarray, x, fit: Fit) -> np.ndarray:
    """The print template of one print: the batch's numbers with the print's own."""
    return print_template(tmpl, B, x, fit.q, derivatives=False)[0]


DOSE_STEP = 0.02  # the relative dose step of ``dose_response``'s difference


def dose_response(tmpl: PrintTemplate, B: np.ndarray, x, fit: Fit, T: np.ndarray | None = None) -> np.ndarray:
    """dT / d ln(dose) of one print's template ``T`` (computed if not given): how its
    edges move with the print's dose (``size_spread``), by a forward difference through
    the same template (``print_template``'s analytic dose derivative leaves out the edge
    offsets and costs an image more), in T's dtype: the batch keeps one per print."""
    T = predicted_print(tmpl, B, x, fit) if T is None else T
    q = np.array(fit.q, dtype=float)
    q[0] *= 1 + DOSE_STEP
    return (print_template(tmpl, B, x, q, derivatives=False)[0] - T) / float(np.log1p(DOSE_STEP))


def smoothing_px(scale: float) -> float:
    """The smoothing against noise before the threshold (design px): about one image pixel."""
    return max(0.5, 0.6 / scale)


def threshold_print(c: np.ndarray, M: np.ndarray, thr: float, design_px: int, divisor: np.ndarray | None = None):
    """The corrected image in design coordinates and the print: divided by the print's
    stain where it has one (``divisor``, on the design grid: ``stain_divisor``), smoothed
    against noise over about one image pixel, then the batch threshold. Returns
    (registered, print)."""
    reg = warp_to_design(c, M, design_px)
    if divisor is not None:
        reg = reg / divisor
    scale = np.sqrt(abs(np.linalg.det(M[:, :2])))
    reg_s = cv2.GaussianBlur(np.nan_to_num(reg, nan=0.0), (0, 0), smoothing_px(scale))
    return reg, reg_s >= thr


def slopeless_print(tmpl: PrintTemplate, B: np.ndarray, x, fit: Fit) -> np.ndarray:
    """``predicted_print`` without the fit's brightness slopes (a stain's, which a divided image no longer has)."""
    q = np.array(fit.q, float)
    q[len(NUISANCE):] = 0.0
    return print_template(tmpl, B, x, q, derivatives=False)[0]


def stain_divisor(tmpl: PrintTemplate, B: np.ndarray, x, fit: Fit, img_smooth: np.ndarray, sigma_px: float):
    """A print's stain on the design grid (``tmpl``'s full grid less its margin), at its
    fit's pose: the smooth field of its image over its fit's prediction across its cured
    interiors (``stain_ratio``, ``stain_field``), the prediction without the fit's
    brightness slopes (a stain too), relative to the print's median there; and the
    template's median over those interiors (1: cured through). None for a print with no
    interiors to measure it on (a fine grating, a star's spokes). ``img_smooth``: the
    corrected image, smoothed by 1 px, not divided."""
    T = slopeless_print(tmpl, B, x, fit)
    ratio, inner = stain_ratio(warp_to_design(img_smooth, fit.M, tmpl.shape[0]), fit.gain * T + fit.offset, fit.offset,
                               print_level(fit, T))
    if not inner.any():
        return None
    m = tmpl.margin
    return stain_field(ratio, inner, sigma_px)[0][m:-m, m:-m], float(np.median(T[inner > 0]))


def measurement_record(template: dict, rows: list[dict], level: float, meta=None) -> dict:
    """What a calibration needs to simulate this measurement (``unscatter.measurement``),
    for registration.yaml: the microscope's blur as the print template measured it (the
    median focus blur of the ok prints, design px; a calibration fits it, starting here),
    the smoothing before the threshold (median, design px), the gel dose as a share of
    the dose at which the template's cure reaches half of saturation, and the level.
    Where batch.yaml states the microscope's blur (``microscope_blur_um``, ``meta``), it
    is recorded in design px as ``declared_blur_px``: a calibration through the
    measurement holds it instead of fitting one. ``dense_level_from`` says where the level's
    reference, the fully cured polymer, came from: ``reference`` (measured on the batch's
    dense reference prints), ``declared`` (batch.yaml ``dense_level``) or ``estimated``
    (the batch's brightest polymer, low where no print cures through)."""
    ok = [r for r in rows if r["status"] == "ok" and r.get("blur") not in ("", None)]
    blur = float(np.median([float(r["blur"]) for r in ok])) if ok else float(template["blur"])
    smooth = float(np.median([smoothing_px(float(r["scale"])) for r in ok])) if ok else 0.5
    gel, k = max(float(template["gel"]), 0.0), max(float(template["k"]), 1e-3)
    out = dict(blur_px=round(blur, 4), smoothing_px=round(smooth, 4),
               gel_share=round(float(np.clip(gel / (gel - k * np.log1p(-level)), 0.1, 0.9)), 4), level=float(level))
    if meta is not None and meta.microscope_blur_um is not None:
        out["declared_blur_px"] = round(float(meta.microscope_blur_um) / float(meta.pixel_size_um), 4)
    if meta is not None:
        out["dense_level_from"] = ("reference" if meta.dense_reference else "declared" if meta.dense_level is not None
                                   else "estimated")
    return out


def stain_divided(img: np.ndarray, fld: np.ndarray, M: np.ndarray, offset: float) -> np.ndarray:
    """The image ``img`` with its polymer (above ``offset``) divided by a stain's field
    ``fld``, which ``M`` maps onto the image (1 outside it)."""
    H, W = img.shape
    d = cv2.warpAffine(fld, M.astype(np.float64), (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                       borderValue=1.0)
    return (offset + (img - offset) / d).astype(img.dtype)


def warp_to_design(c: np.ndarray, M: np.ndarray, design_px: int) -> np.ndarray:
    return cv2.warpAffine(c, M.astype(np.float64), (design_px, design_px), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)


def coverage(M: np.ndarray, mask: np.ndarray, image_shape, margin_px=8) -> float:
    """Share of the mask's exposed area (plus a margin) that lands inside the image."""
    exposed = ndimage.binary_dilation(mask > 0, iterations=margin_px)
    ys, xs = np.nonzero(exposed[::2, ::2])
    if len(xs) == 0:
        return 1.0
    pts = M[:, :2] @ np.vstack([2 * xs, 2 * ys]).astype(float) + M[:, 2:3]
    H, W = image_shape
    inside = (pts[0] >= 0) & (pts[0] <= W - 1) & (pts[1] >= 0) & (pts[1] <= H - 1)
    return float(inside.mean())


def _overlay(reg: np.ndarray, mask: np.ndarray, printed: np.ndarray, dense: float) -> np.ndarray:
    from ..metrics import edges

    g = np.nan_to_num(reg, nan=0.0) / (1.2 * dense if dense > 0 else 1.0)
    g = (np.clip(g, 0, 1) * 255).astype(np.uint8)
    rgb = np.stack([g, g, g], axis=-1)
    e_mask = ndimage.binary_dilation(edges(mask > 127))
    rgb[e_mask] = (255, 40, 40)  # the mask's contour, red
    rgb[edges(printed)] = (40, 220, 40)  # the thresholded print's contour, green
    return rgb


# --------------------------------------------------------------------------- batch


_REG = REGISTRATION.default


@contextlib.contextmanager
def one_library_thread():
    """A context in which OpenBLAS (``threadpoolctl``) and OpenCV run on one thread
    each, whatever ``Settings.threads``: registration's own threads work on the prints.

    The matrix products of each step are small, and OpenBLAS's own threads, two per
    product on two cores, spin while they wait: on seed 172094's lab 4 (32 prints of
    970 x 939) they took a third of the CPU time, 66 to 91 s per batch against 49 to 51 s
    with one BLAS thread. And a batch registers alike at any thread count and on every
    run: with BLAS at two threads for one registration thread, its sums added in another
    order, the template fit of seed 1985358721's lab 6 came to another optimum (sigma
    2.38 against 2.51 px) and a cut-off grating was `ok` a pitch (30 px) off that two
    threads registered right; with OpenCV's own threads as well, 2 of 10 runs of one
    small batch at two registration threads wrote another registration.yaml in the last
    digits (0 of 10 with OpenCV at one thread; 0 of 6 at one registration thread)."""
    from threadpoolctl import threadpool_limits

    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1, user_api="blas"):
            yield
    finally:
        cv2.setNumThreads(before)


def register_batch(batch_dir, out_dir, mode=_REG.mode, level=_REG.level, min_score=_REG.min_score,
                   skip_failed=_REG.skip_failed, progress=True, **kw) -> list[dict]:
    """Register and threshold every image of a batch; write prints, qc.tsv, overlays.

    The output folder is written beside and swapped in whole (``io.output_dir``): it
    never replaces a folder that is not an earlier registration, never lies in the
    batch, and a rerun leaves nothing stale. QC failures raise after the output is
    written, so qc.tsv and the overlays show why.
    """
    checked = REGISTRATION.make(mode=mode, level=level, min_score=min_score, skip_failed=skip_failed)
    s = Settings(mode=checked.mode, level=checked.level, min_score=checked.min_score, skip_failed=checked.skip_failed, **kw)
    batch = open_batch(batch_dir)
    with output_dir(out_dir, command="register", inputs=[batch_dir]) as tmp, one_library_thread():
        rows = _register(batch, Path(batch_dir), tmp, Path(out_dir), s, progress)
    failed = [r for r in rows if r["status"] == "failed"]
    for r in failed:
        log.warning("%s: registration failed: %s", r["id"], r["reason"])
    if failed and not s.skip_failed:
        raise RegistrationError(
            f"{len(failed)} of {len(rows)} prints in {batch_dir} failed registration QC "
            f"({'; '.join(r['id'] + ': ' + r['reason'] for r in failed)}). See {Path(out_dir) / 'qc.tsv'} and the overlays; "
            "re-image them, remove them from the batch, or set registration.skip_failed to go on without them."
        )
    return rows


def _register(batch, batch_dir: Path, out_dir: Path, final_dir: Path, s: Settings, progress: bool) -> list[dict]:
    """The steps of ``register_batch``, writing into ``out_dir`` (``final_dir`` once swapped in)."""
    from tqdm import tqdm

    meta = batch.meta.as_dict()
    offset = float(batch.meta.camera_offset_adu)
    (out_dir / "overlays").mkdir(parents=True, exist_ok=True)
    refs = list(batch.meta.dense_reference or ())  # calibration images of the dense level, not prints to register
    unknown = [mid for mid in refs if mid not in batch.masks]
    if unknown:
        raise InputError(batch_dir / "batch.yaml", f"dense_reference names {', '.join(map(repr, unknown))}, which the batch "
                                                   "does not hold (masks/<id>.png and images/<id>.tif)")
    ids = [mid for mid in batch.ids if mid not in refs]
    if not ids:
        raise InputError(batch_dir / "batch.yaml", "every image of the batch is a dense_reference: no prints to register")
    masks = {mid: read_mask(batch.masks[mid]) for mid in ids}
    shapes = {m.shape for m in masks.values()}
    sh = next(iter(shapes))
    if len(shapes) != 1 or sh[0] != sh[1]:
        raise InputError(batch_dir / "masks", f"masks must all be square and of one size, found {sorted(shapes)}")
    design_px = sh[0]
    s.rotation_deg = rotation_range(meta, s.rotation_deg, batch_dir / "batch.yaml")
    scales = {mid: scale_range(meta, batch.images[mid], s.scale_range, s.scale_tolerance, batch_dir / "batch.yaml")
              for mid in ids}
    pool = ThreadPoolExecutor(s.threads)
    bar = tqdm(total=5 * len(ids), desc=f"registering {batch_dir.name}", unit="step", disable=not progress)

    def pmap(fn, items, fork: bool = False):
        """``fn`` over ``items`` on the batch's threads, or (``fork``) in as many forked
        processes (``parallel``: for the pose searches, whose small NumPy calls keep
        threads waiting on Python's lock; ``fn`` then must change nothing here)."""
        return forked_map(fn, items, s.threads if fork else 1, pool.map, bar.update)  # one process: the threads

    def fmap(fn, items):  # ``pmap(fn, items, fork=True)`` off the progress bar's count
        return forked_map(fn, items, s.threads, pool.map)

    # 1. flat field: one mode for the whole batch, so units agree between prints
    corr = pmap(lambda mid: correct_image(mid, batch.images[mid], offset, s, "divide"), ids)
    ff_mode = "divide" if all(k.noise < 1.0 / s.min_background_snr for k in corr) else "subtract"
    if ff_mode == "subtract":
        corr = list(pool.map(lambda mid: correct_image(mid, batch.images[mid], offset, s, "subtract"), ids))
    corr = {k.id: k for k in corr}

    # 2. one threshold for the batch, from the images that can be prints; empty prints are
    # recognised before registration
    odd = implausible(corr, s)
    dense, thr = dense_level([k for mid, k in corr.items() if mid not in odd], s)
    if batch.meta.dense_level is not None:
        dense, thr = declared_level(batch.meta.dense_level, dense, corr, ff_mode, s, batch_dir / "batch.yaml")
    reference = reference_levels(refs, batch.images, offset, ff_mode, s, batch_dir / "batch.yaml") if refs else None
    if reference:
        dense, thr = declared_level(reference["level"], dense, corr, ff_mode, s, batch_dir / "batch.yaml", "dense_reference")
    log.info("flat field: %s; dense polymer level %.3g, threshold %.3g (level %.2f)", ff_mode, dense, thr, s.level)
    smooth = {mid: cv2.GaussianBlur(k.c, (0, 0), 1.0) for mid, k in corr.items()}
    low = {}  # too little above the threshold to register: empty or faint (decided after the poses, step 5f)
    for mid, k in corr.items():
        if mid in odd:
            continue
        n_above = int(np.count_nonzero(smooth[mid] > max(thr, 6 * k.noise))) if np.isfinite(thr) else 0
        if n_above < s.min_print_px:
            low[mid] = n_above
    todo = [mid for mid in ids if mid not in low and mid not in odd and masks[mid].max() > 0]
    bar.total = 2 * len(ids) + 2 * len(todo)
    bar.refresh()

    # 3. distinct first poses against the blurred mask
    starts = dict(zip(todo, pmap(lambda mid: first_pose(masks[mid], smooth[mid], s, scales[mid][0]), todo, fork=True)))

    # 4. the batch's print template, fitted over a spread of prints at their first poses
    quarter = PrintTemplate(design_px, MARGIN, factor=4)
    tshape = (design_px + 2 * MARGIN,) * 2
    fit_ids = [mid for mid in todo if starts[mid][1]][:: max(1, len(todo) // 12)][:12]

    def pair(mid, M):
        reg = cv2.warpAffine(smooth[mid], M, tshape[::-1], flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        return quarter.padded(masks[mid]), cv2.resize(reg, quarter.shape[::-1], interpolation=cv2.INTER_AREA), 1.0

    def fit_batch_template(poses: dict, x, max_evals: int = 600, hot_spot: bool = True, tail_restart=None):
        """The template fitted on the prints of ``poses`` (id -> pose) from ``x``: its numbers,
        its mean NCC, the (mask, image, dose) it was fitted on, and the prints it was fitted
        on and left out (registration.yaml). ``tail_restart``: (tail share, width) that
        each fit starts again from, with its other numbers where the first start ended."""
        def fit_from(pairs, x):
            x, fit = fit_template(quarter, pairs, x, max_evals, pool=pool.map, posed=s.template_posed,
                                  processes=s.threads)
            if tail_restart is None:
                return x, fit
            start = x.copy()
            start[TAIL:TAIL + 2] = tail_restart  # the tail's share and width
            x2, fit2 = fit_template(quarter, pairs, start, max_evals, pool=pool.map, posed=s.template_posed,
                                    processes=s.threads)
            log.info("print template: started again with its tail at %s: mean NCC %.4f against %.4f", tail_restart,
                     fit2, fit)
            return (x2, fit2) if fit2 > fit else (x, fit)

        ids_ = list(poses)
        pairs = list(pool.map(lambda mid: pair(mid, poses[mid]), ids_))
        x, fit = fit_from(pairs, x)
        kept = well_fitted(quarter, pairs, x)
        if len(kept) < len(pairs):  # fitted again without the prints it cannot explain (a pose off)
            pairs = kept
            x, fit = fit_from(pairs, x)
        used = dict(fitted=[m for m, p in zip(ids_, pairs) if any(p is k for k in kept)],
                    left_out=[m for m, p in zip(ids_, pairs) if not any(p is k for k in kept)])
        if hot_spot:  # a lamp hot spot, where the prints show one
            x, fit = fit_hot_spot(quarter, pairs, x, fit, s.hot_spot_gain, pool=pool.map, max_evals=max_evals, search_map=fmap,
                                  posed=s.template_posed, processes=s.threads)
        log.info("print template: %s, mean NCC %.4f", dict(zip(PrintTemplate.NAMES, np.round(x, 4))), fit)
        return x, fit, pairs, used

    x = np.array(PrintTemplate.START)
    template_prints = dict(fitted=list(fit_ids), left_out=[])  # registration.yaml: the prints the template was fitted on
    # (and where it was fitted again at the chosen poses, ``first``: those of the first template)
    if fit_ids:
        x, _, _, template_prints = fit_batch_template({mid: starts[mid][0][0] for mid in fit_ids}, x)
    # 5. every print's pose: refined hypotheses and the moves under which it maps onto itself
    def counted(mid) -> tuple:
        """The scales within which a pose counts (``choose_pose``): the searched range;
        around a stated pixel size about 10 % either side, for a print whose scale its
        features' size sets may be that far off until step 5c holds it."""
        lo, hi = scales[mid][0]
        return (lo, hi) if scale_prior(*scales[mid]) is None else (min(lo, hi / 1.1), max(hi, lo * 1.1))

    def chosen(ids_, x, start=None):  # ``start``: id -> the poses to start from (default: the first poses)
        start = start or {}
        return dict(zip(ids_, pmap(lambda mid: choose_pose(masks[mid], smooth[mid], start.get(mid, starts[mid][0]), x, s,
                                                           design_px, counted(mid)), ids_, fork=True)))

    # 5a. the template again. A first pose against the blurred mask is off by the print's
    # difference from its mask (features that shrank, or grew more along one direction; a
    # line grating by a pitch or more, a partial print), and a template fitted at poses
    # that far off comes out blurred (seen: sigma 22 px where it is 8 at the true poses),
    # which biases every pose chosen with it (1.5 to 2 px). So once every print's pose is
    # chosen, the template is fitted again at up to 12 poses that no rival contests, and
    # where it fits those prints clearly better than the first did, it is the batch's:
    # every print whose pose no rival contests is refined with it, and the others are
    # chosen again with it, from their first choice and its rival (the moves under which
    # a print maps onto itself are tried again from there; the first poses that lost to
    # them are not). Choosing every print again gave the same verdicts on 16 labs and took
    # 8 % longer; choosing again only where the refined ones moved 0.3 px or more saved
    # no time on 8 labs (they all moved) and left one more print silently wrong.
    def placed(ch) -> bool:  # a pose the template may be fitted at: no rival close, converged (its spread, which a
        return ch.fit is not None and ch.converged and ch.settled >= s.min_evidence  # poor template inflates, aside)

    def uncontested() -> list:  # the prints the template is fitted on again: up to 12 placed ones, spread over the batch
        ids_ = [mid for mid in todo if placed(choices[mid])]
        return ids_[:: max(1, len(ids_) // 12)][:12]

    def hot_spot_again(x):  # the template's numbers with its lamp hot spot back at its start, to be searched for again
        return np.r_[x[:13], PrintTemplate.START[13:17], x[17:]]

    full = PrintTemplate(design_px, MARGIN)  # the full-resolution template, steps 5a to 6
    choices = chosen(todo, x)
    # 5a, first: uneven staining. A print whose polymer is brighter in one part than another
    # (``stain_field``) is fitted with one gain, and its dim part's edges are pulled inside
    # its bright part's. Where a print's interiors show such a field at its first chosen
    # pose, the image its pose and the template are fitted to is divided by it (the
    # polymer, not the background), and the print is chosen again (below). The print is
    # thresholded on its image divided by its stain as well, measured again at its final
    # pose (step 5e).
    stains, batch_stained = {}, False
    if np.isfinite(s.stain_min_sd):
        n_grid = design_px + 2 * MARGIN

        def ratio_of(mid):  # on the template's grid
            f = choices[mid].fit
            if f is None or not f.gain > 0:
                return None
            T = predicted_print(full, full.exposure(full.padded(masks[mid]), x), x, f)
            return stain_ratio(warp_to_design(smooth[mid], f.M, n_grid), f.gain * T + f.offset, f.offset, print_level(f, T))

        ratios = {mid: r for mid, r in zip(todo, pool.map(ratio_of, todo)) if r is not None and r[1].any()}

        def stain_of(mid):
            return (mid, *stain_field(*ratios[mid], s.stain_sigma_px))

        fields = list(pool.map(stain_of, list(ratios)))
        # a stain is the lab's (its staining, its bleaching): where enough of the batch's
        # prints show one, every print's field is divided out down to stain_batch_sd
        batch_stained = sum(sd >= s.stain_min_sd for _, _, sd in fields) >= s.template_min_prints
        least = s.stain_batch_sd if batch_stained else s.stain_min_sd
        for mid, fld, sd in fields:
            if sd >= least:
                stains[mid] = sd
                f = choices[mid].fit
                smooth[mid] = stain_divided(smooth[mid], fld, f.M, f.offset)
        del ratios  # two grids a print, not needed past here
        if stains:
            log.info("uneven staining in %d prints (polymer brightness %.1f to %.1f %% across them): their images divided "
                     "by it", len(stains), 100 * min(stains.values()), 100 * max(stains.values()))
    rechosen = stain_refit = False
    spot_kept = None  # the mean NCC by which the prints fit the spot found before the stain's division (where lost after it)
    if len(stains) >= s.template_min_prints:  # the template, fitted on the stained images, fitted again (a stain
        # takes the place of the lamp's hot spot and of the core's anisotropy) from where it is, the hot spot searched for
        # again, and every print chosen again with it. From the template's start instead: a lab's rectangles print
        # (tests/test_bench_registration.py, seed 147307914's lab 4) went 1.16 -> 1.60 px off, ok
        refit = uncontested()
        x = np.r_[x[:STAIN_SLOPE], s.stain_slope_sd, x[STAIN_SLOPE + 1:]]
        if len(refit) >= s.template_min_prints:
            refit_poses = {mid: choices[mid].fit.M for mid in refit}
            x_spot = x
            x, _, pairs_r, template_prints = fit_batch_template(refit_poses, hot_spot_again(x))
            if x_spot[13] > 0 and not x[13] > 0:  # the spot found before the division, lost in the search after it: kept
                # where the prints fit it better (an uneven stain the spot's dose makes brighter in part is divided
                # out with the stain, and an elliptical core takes its place; seed 124444929's lab 4)
                x_k, _, _, used_k = fit_batch_template(refit_poses, x_spot, hot_spot=False)
                spot_kept = mean_ncc(quarter, pairs_r, x_k) - mean_ncc(quarter, pairs_r, x)
                log.info("lamp hot spot found before the stain's division: mean NCC %+.5f against the search after it: %s",
                         spot_kept, "kept" if spot_kept >= s.hot_spot_gain else "not kept")
                if spot_kept >= s.hot_spot_gain:
                    x, template_prints = x_k, used_k
            bar.total += len(todo)
            choices = chosen(todo, x, {mid: ch.poses + list(starts[mid][0]) for mid, ch in choices.items() if ch.fit is not None})
            rechosen = stain_refit = True
    sure = uncontested()
    if len(sure) >= s.template_min_prints:
        x2, fit2, pairs2, used2 = fit_batch_template({mid: choices[mid].fit.M for mid in sure}, hot_spot_again(x), 300,
                                                     hot_spot=False, tail_restart=s.template_tail_restart)
        before = mean_ncc(quarter, pairs2, x)
        log.info("print template at the poses of %d prints: mean NCC %.4f, the first template's %.4f", len(sure), fit2, before)
        if fit2 - before > s.template_refit_gain:
            def refined(mid, x):  # from the pose alone: the print's dose and edge offsets under the first template are
                # not its numbers under this one (a half-dose print's dose 0.65 cured nothing under it, and its pose walked
                # 23 px off); from the prior's, every print converged
                B = full.exposure(full.padded(masks[mid]), x)
                return replace(choices[mid], fit=refine(smooth[mid], choices[mid].fit.M, full, B, x, s.mode, iters=12, tol=0.01))

            bar.total += len(choices)
            x, fit2 = fit_hot_spot(quarter, pairs2, x2, fit2, s.hot_spot_gain, pool=pool.map, max_evals=300, search_map=fmap,
                                   posed=s.template_posed, processes=s.threads)
            log.info("print template: %s, mean NCC %.4f", dict(zip(PrintTemplate.NAMES, np.round(x, 4))), fit2)
            template_prints = dict(used2, first=template_prints)
            settled = [mid for mid in todo if placed(choices[mid])]  # no rival close: refined, not chosen again
            again = [mid for mid in choices if mid not in settled]
            choices.update(zip(settled, pmap(lambda mid: refined(mid, x), settled, fork=True)))
            choices.update(chosen(again, x, {mid: ch.poses for mid, ch in choices.items() if mid in again}))
            rechosen = True
    if stains and not rechosen:  # the prints whose images the stain changed, chosen again from their pose and rival
        bar.total += len(stains)
        choices.update(chosen(list(stains), x, {mid: choices[mid].poses for mid in stains}))
    # 5b. a print with a rival pose (a star one spoke off) is chosen again among the poses
    # that the batch's determined prints make plausible
    grid = design_px + 2 * MARGIN
    exposed = {}  # id -> the mask's scattered dose on the full grid, made once for steps 5b to 6

    def exposure_of(mid) -> np.ndarray:
        if mid not in exposed:
            exposed[mid] = full.exposure(full.padded(masks[mid]), x)
        return exposed[mid]

    known = {mid: pose_of(ch.fit.M, grid, smooth[mid].shape) for mid, ch in choices.items() if determined(ch, s)}
    one_rotation = batch_rotation([p["rotation_deg"] for p in known.values()], s)

    def off_rotation(M) -> bool:
        return one_rotation is not None and abs(pose_of(M, grid, (1, 1))["rotation_deg"] - one_rotation[0]) > one_rotation[1]

    limits = batch_range([p for mid, p in known.items() if not off_rotation(choices[mid].fit.M)], s)
    if limits is not None:
        (rlo, rhi), (slo, shi) = limits
        # and a print turned far from the batch's others (a star one spoke off that the
        # image happened to prefer)
        redo = [mid for mid, ch in choices.items() if ch.settled < s.min_evidence or off_rotation(ch.fit.M)]

        def again(mid):
            ch = choices[mid]
            rot = (max(rlo, s.rotation_deg[0]), min(rhi, s.rotation_deg[1]))
            sc = (max(slo, counted(mid)[0]), min(shi, counted(mid)[1]))
            if rot[0] > rot[1] or sc[0] > sc[1]:
                return ch
            tried = [M for M in (ch.fit.M, ch.rival) if M is not None]
            if one_rotation is not None:  # the pose turned about the mask's centre of mass to the batch's rotation
                turn = one_rotation[0] - pose_of(ch.fit.M, grid, (1, 1))["rotation_deg"]
                cy, cx = (v + MARGIN for v in ndimage.center_of_mass(masks[mid].astype(np.float64)))
                for t in (turn, -turn):
                    tried.append((h3(ch.fit.M) @ h3(similarity(t, 1.0, (cx, cy), (cx, cy))))[:2])
            new = choose_pose(masks[mid], smooth[mid], tried + list(starts[mid][0]), x, s, design_px, sc, rot)
            if ch.settled >= s.min_evidence:  # chosen again only for its rotation: kept where the image clearly
                # prefers it to the pose within the batch's range (it then fails), never forced into the range
                B = exposure_of(mid)
                z = evidence(smooth[mid], (ch.fit, predicted_print(full, B, x, ch.fit)), (new.fit, predicted_print(full, B, x, new.fit)))
                if z >= s.min_evidence:
                    log.info("%s: turned %.1f deg off the batch's rotation, and the image prefers that pose (z = %.1f) to the "
                             "one within the batch's range", mid, pose_of(ch.fit.M, grid, (1, 1))["rotation_deg"] - one_rotation[0], z)
                    return ch
            return new

        for mid, ch in zip(redo, fmap(again, redo)):  # ``again`` changes nothing here (the
            # exposures it makes in a child are made again where needed)
            log.info("%s: chosen again within the batch's poses (rotation %.1f..%.1f deg, scale %.3f..%.3f): evidence %.1f -> %.1f",
                     mid, rlo, rhi, slo, shi, choices[mid].evidence, ch.evidence)
            choices[mid] = ch
    p = dict(zip(PrintTemplate.NAMES, (float(v) for v in x)))  # every number: fit_template keeps them all

    # 5c. how far a print's pose rests on the size of its features, and how well this
    # batch's template predicts sizes: the edge offsets fitted on the prints whose features'
    # places fix their pose (``size_error``)
    def imaged(mid, f, img=None):
        """The image on the template's grid at the pose of ``f``, in the template's units
        (``size_spread``'s ``image``)."""
        img = warp_to_design(smooth[mid], f.M, grid) if img is None else img
        return (img - f.offset) / f.gain if f.gain > 0 else None

    def free_spread(mid):
        f = choices[mid].fit
        B = exposure_of(mid)
        T = predicted_print(full, B, x, f)
        R = dose_response(full, B, x, f, T)
        img = warp_to_design(smooth[mid], f.M, grid)
        seen = imaged(mid, f, img)
        return (T, size_spread(T, s.mode, image=seen), edge_misfit(img, T, f), R, dose_sensitivity(T, R),
                feature_places(seen, T, R) if seen is not None else np.zeros((0, 3)))

    spreads = dict(zip(todo, pool.map(free_spread, todo)))
    placed_ids = [mid for mid in todo if determined(choices[mid], s) and spreads[mid][1] <= s.max_pose_sd]
    placed = [choices[mid].fit for mid in placed_ids]
    centre, edge_sd = size_error(placed, s)
    log.info("feature sizes: edge offset %.2f +- %.2f px, across directions %.2f +- %.2f px (from %d prints whose pose "
             "their features' places fix)", centre[0], edge_sd[0], np.hypot(centre[1], centre[2]), edge_sd[1], len(placed))
    place_sd, misfit = edge_place_sd([spreads[mid][2] for mid in placed_ids], s)
    # how far the dose moves the edges of the prints whose edges place_sd measures (9 in 10
    # of each one's, the median print): an edge that it moves further is off by as much
    # further (size_spread)
    moved = [spreads[mid][4] for mid in placed_ids if np.isfinite(spreads[mid][4])]
    dose_ref = float(np.median(moved)) if moved else None
    # how far the features of those prints sit off their places, per unit of how far the
    # dose moves their edges: each feature of every print may be off by as much (size_spread)
    place_dose, place_features = place_dose_spread([spreads[mid][5] for mid in placed_ids], place_sd)
    edge_places = dict(sd=place_sd, median_misfit=misfit, prints=len(placed_ids), dose_px=dose_ref,
                       feature_place_dose=place_dose, feature_place_features=place_features)
    feature_sizes = dict(edge_offset=centre[0], edge_sd=edge_sd[0], prints=len(placed))
    log.info("edge places: off by %.2f px (median misfit %s of %d prints whose pose their features' places fix); "
             "their %d features off their places by %.3f of how far the dose moves their edges", place_sd,
             "none" if misfit is None else f"{misfit:.2f} px", len(placed_ids), place_features, place_dose)
    edge_prior = dict(zip(("edge", "edge_c2", "edge_s2"), zip(centre, edge_sd)))

    # how far the batch's scatter kernel is off in shape, as the prints whose features place
    # their pose show it (``kernel_moves``' shares, ``kernel_error``): each print's pose
    # spread from the kernel's shape (5d') is its move at that much change
    def kernel_share(mid):
        f = choices[mid].fit
        return kernel_moves(full, full.padded(masks[mid]), exposure_of(mid), x, f, s.mode,
                            image=warp_to_design(smooth[mid], f.M, grid))[1]

    kernel_off, kernel_prints = kernel_error(list(pool.map(kernel_share, placed_ids)), s.size_min_prints)
    log.info("scatter kernel's shape: off by %.2f of a tail share of %.2f (and %.2f of a width change of %.0f %%, not "
             "counted) from %d prints whose features place their pose%s", kernel_off["tail"], KERNEL_TAIL,
             kernel_off["wider"], 100 * (KERNEL_WIDTH - 1), kernel_prints,
             "" if kernel_prints >= s.size_min_prints else ": too few to measure it, assumed")
    one_scale = batch_scale(placed, s)
    held_scale = None if one_scale is None else one_magnification_held(one_scale, len(placed), s)
    if one_scale is not None:
        log.info("one magnification: scale %.4f +- %.2f %% (from %d prints whose pose their features' places fix), "
                 "every print held to it within %.2f %%", np.exp(one_scale[0]), 100 * one_scale[1], len(placed),
                 100 * held_scale[1])

    placed_scales = {mid: log_scale(choices[mid].fit.M) for mid in placed_ids}
    stated, stated_note, stale = stated_scales({mid: scale_prior(*scales[mid]) for mid in todo}, placed_scales, s)
    if len(placed) < s.size_min_prints:
        # a small batch: its template's size error is assumed, not measured (docs/registration.md, "Small registration batches"):
        # the size spread of every print (size_spread) and the erosion of the faint test (5f) rest on size_sd,
        # which the batch cannot check
        log.warning("prints whose pose their features' places fix: %d of %d, fewer than the %d needed to measure how "
                    "far the template's feature sizes are off; they are assumed right within %.1f px, and a print whose "
                    "scale rests on them may be less sure than its spread says. Register the prints of one printer and "
                    "microscope together%s", len(placed), len(todo), s.size_min_prints, s.size_sd,
                    "" if stated else ", or state the camera pixel size")
    scatter = stated_scatter(stated, placed_scales, {mid: choices[mid].fit.pose_sd for mid in placed_ids}, design_px,
                             misfit, s)
    held_stated = scatter["held_within"] if scatter else None
    if scatter:
        log.info("stated camera pixel sizes: %d prints whose features fix their scale scatter about them by %.2f %% (%.2f px "
                 "over the field), their own pose spreads %.2f px (median)%s", scatter["prints"], 100 * scatter["spread"],
                 scatter["spread_px"], scatter["claimed_px"],
                 f": {scatter['excess_px']:.2f} px more, which their template's edges, {misfit:.2f} px off theirs, "
                 f"leave to the prints' scales: each print whose features fix its scale is weighed against its stated "
                 f"size, known within {100 * held_stated:.2f} %" if held_stated else "")
    weighed = set()  # prints whose scale is weighed against their stated size (stated_scatter)
    stated_held = set()  # prints refitted held to their stated size (where the batch has one magnification: in its place)

    def spreads_of(*args, **kw) -> tuple[float, float]:
        """``size_spread`` with the features' own places (``Fit.size_sd``) and without them
        (``Fit.sizes_sd``): one computation where the batch measured no place spread."""
        with_places = size_spread(*args, place_dose_sd=place_dose, **kw)
        return with_places, (with_places if place_dose <= 0 else size_spread(*args, **kw))

    def no_size_note(mid) -> str:
        """What would hold the scale of a print whose features' sizes set it, where the
        batch knows nothing of it (no stated camera pixel size, and not one magnification
        that its prints show): a stated one (``priors``)."""
        if stated.get(mid) is not None or held_scale is not None:
            return ""
        # joined with ": ", not "; ", which separates a print's reasons (``determinacy_only``)
        return (": no camera pixel size is stated, which would hold its scale (batch.yaml image_pixel_size_um for one "
                "objective, or each image's TIFF resolution tags or OME-XML PhysicalSizeX)")

    def off_scale(M) -> bool:
        return one_scale is not None and abs(log_scale(M) - one_scale[0]) > s.scale_sigmas * one_scale[1]

    def held(mid):
        """A print whose pose its features' sizes set: refitted with its edge offsets held
        to the batch's (erosion and anisotropic scattering are the batch's), their spread
        the batch's; not for a feature that joins parts of its mask (a grating printed as
        one block), whose size the scatter between the parts sets, px off the template's
        in our labs: its size counts as unknown. In a batch of one magnification
        (``batch_scale``) the scale of every print is held to the batch's, within the
        uncertainty of the batch's median (``one_magnification_held``): a print whose
        scale its features' sizes set, one whose pose is uncertain, one whose scale is off
        the batch's (a grating whose lines cure wider than the template predicts pulls its
        scale off), and one that seems to fix its own scale, which a template that
        misplaces its edges (a hot spot, a broad scatter) pulls off by more than its own
        spread says (0.7 % for two rectangles prints of seed 3297061028, 1.9 and 2.4 px).

        A stated camera pixel size (``stated_scales``) holds the scale in the same way,
        but only for a print whose scale trades against its features' size (its spread
        from their sizes alone, ``Fit.sizes_sd``, without their own places, over
        ``hold_size_sd``, and where it is below the limit, its own scale
        within ``scale_sigmas`` spreads of the stated one) while its data nearly fix the
        rest of its pose (its pose spread, which the free scale's trade against the
        features' size inflates, within the size spread's limit ``max_size_sd``; a pose
        looser than that, a grating loose along its lines or a pose far off, stays
        failed), and only where it is known more closely than the batch's one
        magnification, and only where the held fit's spreads are the smaller. The limit
        was 1.5 times ``max_pose_sd`` (0.75 px): paper trial prints of checkerboards and
        rectangles whose free scale had slid 1 to 3 % along their blocks' size (pose
        spreads 0.83 to 1.35 px, 2.0 to 7.4 px off) stayed failed; held, they are 0.6 to
        0.9 px off (docs/registration.md, "Held to a stated size though their free pose is loose"). It
        counts in the pose's spread, so it lets a print pass only when it is tight enough
        (about 0.15 % for a print of 512 px)."""
        ch, T = choices[mid], spreads[mid][0]
        padded = full.padded(masks[mid])
        merged = merged_features(T, padded)
        if not merged:  # the template may resolve what the print joins (a grating whose gaps scatter filled): the
            # print itself, smoothed against noise and cut at the template's half level
            seen = imaged(mid, ch.fit)
            merged = seen is not None and merged_features(ndimage.gaussian_filter(seen, 1.0), padded,
                                                          level=0.5 * float(T.max()))
        if merged:
            joined.add(mid)
        sd = None if merged else edge_sd
        sized = spreads[mid][1] > s.max_pose_sd
        edges = not merged and sized and len(placed) >= s.size_min_prints
        scaled = one_scale is not None
        B = exposure_of(mid)

        def fit(held_at):  # (log scale, sd) or None
            start = ch.fit
            if held_at is not None and abs(held_at[0] - log_scale(ch.fit.M)) > HELD_RESCALE:
                # from the held scale, about the mask's centre of mass: refinement moves a
                # pose by at most 2 px a step, and a print 17 % off a scale of one
                # magnification (a disc whose size set it) walked all 12 steps toward it
                cy, cx = (v + MARGIN for v in ndimage.center_of_mass(masks[mid].astype(np.float64)))
                r = float(np.exp(held_at[0] - log_scale(ch.fit.M)))
                start = replace(ch.fit, M=(h3(ch.fit.M) @ h3(similarity(0.0, r, (cx, cy), (cx, cy))))[:2])
            f = refine(smooth[mid], start, full, B, x, s.mode, iters=12, prior=edge_prior if edges else None,
                       scale_prior=held_at)
            # QC asks whether the chosen pose converged; held to a scale, the refit answers for
            # itself: the free fit may not have only because it slid along the scale that its
            # features' sizes trade against, which the scale now holds
            f.converged = f.converged if held_at is not None else ch.fit.converged
            Tf = predicted_print(full, B, x, f)
            f.size_sd, f.sizes_sd = spreads_of(Tf, s.mode, sd, held_at[1] if held_at else None, place_sd, imaged(mid, f),
                                               dose_response(full, B, x, f, Tf), dose_ref)
            return f

        if edges or scaled:
            f = fit(held_scale if scaled else None)
        else:
            f = ch.fit
            f.size_sd, f.sizes_sd = spreads_of(T, s.mode, sd, edge_sd=place_sd, image=imaged(mid, f),
                                               dose_response=spreads[mid][3], dose_reference=dose_ref)
        p = stated.get(mid)
        if (p is not None and held_stated is not None and not scaled and f.sizes_sd <= s.hold_size_sd
                and np.isfinite(f.pose_sd)):
            # the batch's prints scatter about their stated sizes more than they should, and
            # its template misplaces their edges (stated_scatter): the stated size holds the
            # scale of every print whose features fix it and whose own scale agrees with it
            # (one that does not fails as off its stated scale: evidence of a wrong pose),
            # weighed against its own scale, whose spread is its pose spread and the batch's
            # excess scatter in quadrature, over the field's RMS radius (inverse variances:
            # a print whose features fix its scale well leans on it less; held outright,
            # prints of seed 3297061028's lab 3 that fixed theirs within 0.05 % were moved to
            # stated sizes 0.17 % off, where the metadata scatters by 0.09 % an image).
            # Holding fixes the scale, not the rest of the pose: the print keeps its own pose
            # spread as the least. A print whose scale rests on its features' size is held
            # as before, at the single-print spread (below): held at the median's (0.14 %),
            # a cut-off grating of lab 2 of seed 2745280767 that failed at 0.81 px passed at
            # 0.43 px, 1.69 px off along its lines
            if abs(log_scale(f.M) - p[0]) > s.scale_sigmas * p[1]:
                return f
            own = float(np.hypot(f.pose_sd, scatter["excess_px"])) / field_radius_px(design_px)
            w = own**2 / (own**2 + held_stated**2)  # the stated size's weight
            at = (w * p[0] + (1 - w) * log_scale(f.M), float(1.0 / np.sqrt(1.0 / own**2 + 1.0 / held_stated**2)))
            g = fit(at)
            g.pose_sd = max(g.pose_sd, f.pose_sd)
            weighed.add(mid)
            log.info("%s: held to its stated camera pixel size (weight %.2f) within %.2f %%: pose spread %.2f -> %.2f px", mid,
                     w, 100 * at[1], f.pose_sd, g.pose_sd)
            return g
        # between hold_size_sd and max_size_sd the print's own scale means something: held
        # only where it agrees with the stated one (a print whose scale is off it is
        # evidence of a wrong pose, which holding would hide: a grey ramp of seed
        # 1767693049 passed 2.6 px off, its free scale 0.4 % off, 4.1 times the spread)
        if (p is not None and (held_scale is None or p[1] < held_scale[1]) and f.pose_sd <= s.max_size_sd
                and (f.sizes_sd > s.max_size_sd
                     or (f.sizes_sd > s.hold_size_sd and abs(log_scale(f.M) - p[0]) <= s.scale_sigmas * p[1]))):
            g = fit(p)
            if max(g.pose_sd / s.max_pose_sd, g.sizes_sd / s.max_size_sd) < max(f.pose_sd / s.max_pose_sd, f.sizes_sd / s.max_size_sd):
                log.info("%s: held to its stated camera pixel size: pose spread %.2f -> %.2f px, size spread %.2f -> %.2f px",
                         mid, f.pose_sd, g.pose_sd, f.size_sd, g.size_sd)
                f = g
                stated_held.add(mid)
        return f

    joined = set()  # prints that join parts of their mask into one feature (held: their size is unknown)
    for mid, f in zip(todo, pool.map(held, todo)):
        choices[mid].fit = f
    del spreads

    # 5d. a mask that carries the registration marks (designed trial masks): the pose is
    # checked against one that rests on the marks alone (refitted from the chosen pose on
    # their cleared bands, the print's nuisance numbers held: three solid squares cannot fix
    # them), whatever the rest of the print does. A block of fine grating that cures in
    # patches pulled a fit of the whole print 1 % off in scale, 2.8 px from its marks. The
    # marks' pose is noisier (0.1 to 0.5 px off, its spread up to 1 px in our labs), so it
    # replaces the whole print's only where the two disagree by more than marks_agree_px.
    marks, clear = fiducial_marks(design_px)
    region, marks_only = np.pad(clear, MARGIN), np.where(marks, 255, 0).astype(np.uint8)
    B_marks = None

    def on_marks(mid):
        f = choices[mid].fit
        g = refine(smooth[mid], f, full, exposure_of(mid), x, s.mode, iters=12, region=region, hold_nuisance=True)
        d = pose_distance(f.M, g.M, grid, MARGIN)
        if d <= s.marks_agree_px:
            return f
        # the pose and its spread are the marks'; gain, offset and nuisance numbers stay the
        # whole print's (the marks' gain is that of three squares under an uneven stain)
        g = replace(f, M=g.M, pose_sd=g.pose_sd, converged=g.converged, iterations=g.iterations)
        Tg = predicted_print(full, B_marks, x, g)
        g.size_sd = size_spread(Tg, s.mode, edge_sd, edge_sd=place_sd, image=imaged(mid, g),
                                dose_response=dose_response(full, B_marks, x, g, Tg), dose_reference=dose_ref,
                                place_dose_sd=place_dose)
        log.info("%s: posed on its registration marks, %.2f px from the pose of the whole print (pose spread %.2f -> "
                 "%.2f px)", mid, d, f.pose_sd, g.pose_sd)
        posed_on_marks.add(mid)
        return g

    posed_on_marks = set()
    marked = [mid for mid in todo if choices[mid].fit is not None and carries_marks(masks[mid])]
    if marked:
        B_marks = full.exposure(full.padded(marks_only), x)
        for mid, g in zip(marked, pool.map(on_marks, marked)):
            choices[mid].fit = g

    # 5d'. how far each pose rests on the shape of the batch's scatter kernel, which its
    # template knows only roughly (``kernel_spread``): a grey ramp's pose along the ramp
    # rests on the edge at its bright end, whose place the kernel's shape sets
    def kernel_moved(mid):
        f = choices[mid].fit
        if mid in posed_on_marks:
            return kernel_spread(kernel_moves(full, full.padded(marks_only), B_marks, x, f, s.mode)[0], kernel_off)
        return kernel_spread(kernel_moves(full, full.padded(masks[mid]), exposure_of(mid), x, f, s.mode)[0], kernel_off)

    fitted = [mid for mid in todo if choices[mid].fit is not None]
    for mid, moved in zip(fitted, pool.map(kernel_moved, fitted)):
        choices[mid].fit.model_sd = moved

    # 5d''. a print whose fit puts its edges far off the batch's. Erosion and anisotropic
    # scattering are the batch's, so a print's fitted edge offsets (all round, and by
    # direction) differ from the batch's by little (size_error's spread); where they differ
    # by edge_pull_sds spreads or more, the template does not describe the print (a grey
    # ramp whose cut the dose places and whose one sharp edge eroded more than the template
    # predicts at its grey), and the pose may trade against them: the offsets and the
    # shift along the ramp moved together, and a ramp of seed 1577074319's lab 6 was `ok`
    # 3.2 px off with an offset of +3.1 px on its vertical edges against the batch's +0.02
    # +- 0.1. Such a print is refitted with its offsets held at the batch's, and fails
    # where that moves its pose by more than edge_pull_px: one of the two poses is then off
    # by half that at least, and the print's spreads, which count its offsets within the
    # batch's spread, do not say which. Not for a print that joins parts of its mask (a
    # grating printed as one block): its size is unknown (held), its offsets are free. A
    # print whose scale step 5c held is refitted held to the same scale.
    held_edges = {n: (c, EDGE_HOLD_SD) for n, (c, _) in edge_prior.items()}

    def edge_pull(mid):
        f = choices[mid].fit
        z = max(abs(getattr(f, n) - c) / sd for n, (c, sd) in edge_prior.items())
        if not z > s.edge_pull_sds:
            return None
        g = refine(smooth[mid], f, full, exposure_of(mid), x, s.mode, iters=12, prior=held_edges,
                   scale_prior=f.scale_prior)
        return z, pose_distance(f.M, g.M, grid, MARGIN)

    pulled = {}  # id -> (how many spreads its offsets lie off the batch's, how far holding them moves its pose)
    cands = [mid for mid in todo if choices[mid].fit is not None and mid not in posed_on_marks and mid not in joined]
    for mid, r in zip(cands, pool.map(edge_pull, cands)):
        if r is not None:
            pulled[mid] = r
            log.info("%s: edge offsets %.1f of the batch's spreads off its; held there, the pose moves %.2f px", mid, *r)
    edge_moved = {mid for mid, r in pulled.items() if r[1] > s.edge_pull_px}  # QC fails these (``finish``)

    # 5d, last. The lamp's field that the placed prints leave open (``field_alternatives``): each print refitted under
    # each such field; its largest move (px), that field's spot width and its mean NCC against the prints' best field
    field_moved, alternatives = {}, []
    if s.field_alternatives and len(placed_ids) >= s.template_min_prints:
        alternatives = field_alternatives(quarter, list(pool.map(lambda mid: pair(mid, choices[mid].fit.M), placed_ids)), x,
                                          tol=s.hot_spot_gain)
        # the prints that pass so far: one that fails anyway needs no refit (4 of 30 and 10 of 22 posed prints in two labs)
        field_cands = [mid for mid in todo if not fails_anyway(choices[mid], s) and mid not in edge_moved]
        for xa, ncc_gain, spot_width in alternatives:
            def moved_by(mid, xa=xa):
                f = choices[mid].fit
                g = refine(smooth[mid], f, full, full.exposure(full.padded(masks[mid]), xa), xa, s.mode, iters=12,
                           scale_prior=f.scale_prior)
                return pose_distance(f.M, g.M, grid, MARGIN)

            for mid, moved in zip(field_cands, fmap(moved_by, field_cands)):  # in processes: it changes nothing here
                if moved > field_moved.get(mid, (0.0,))[0]:
                    field_moved[mid] = (moved, spot_width, ncc_gain)
    field_moved_far = sorted(mid for mid, r in field_moved.items() if r[0] > s.edge_pull_px)  # QC fails these (``finish``)
    if alternatives:
        log.info("lamp fields that the placed prints fit as well: %d; prints they move more than %.1f px: %s",
                 len(alternatives), s.edge_pull_px, field_moved_far)

    def smooth_raw(mid):  # the image as ``smooth`` held it before 5a divided it
        return cv2.GaussianBlur(corr[mid].c, (0, 0), 1.0)

    # 5d, after the lamp's fields: the stain. A print's image was divided by its stain as measured at its first
    # chosen pose (5a), and the print then fitted again to the divided image. A pose off by a few px leaves bands of
    # misfit along the print's edges that the stain's smooth field partly takes up, and the division then holds the
    # pose where it was (seed 469681202's lab 6: a checkerboard 3.3 px off, ok at a pose spread of 0.47 px). Each
    # such print is refitted on its image divided by its stain measured again at its final pose, against a refit on
    # the image it was fitted on; a pose that its own stain moves by more than edge_pull_px rests on the division
    restained, stain_moved = {}, {}  # id -> stain_divisor at the final pose; id -> how far it moves the pose (px)
    if s.stain_recheck and stains:
        def stain_move(mid):
            f, raw = choices[mid].fit, smooth_raw(mid)
            r = stain_divisor(full, exposure_of(mid), x, f, raw, s.stain_sigma_px)
            if r is None:
                return None, None
            a = refine(smooth[mid], f, full, exposure_of(mid), x, s.mode, iters=12, scale_prior=f.scale_prior)
            b = refine(stain_divided(raw, r[0], to_design(f.M, MARGIN), f.offset), f, full, exposure_of(mid), x, s.mode,
                       iters=12, scale_prior=f.scale_prior)
            return r, pose_distance(a.M, b.M, grid, MARGIN)

        recheck = [mid for mid in todo if mid in stains and not fails_anyway(choices[mid], s) and mid not in posed_on_marks]
        for mid, (r, moved) in zip(recheck, pool.map(stain_move, recheck)):
            if r is not None:
                restained[mid], stain_moved[mid] = r, moved
    stain_moved_far = sorted(mid for mid, m in stain_moved.items() if m > s.edge_pull_px)  # QC fails these (``finish``)
    if stain_moved:
        log.info("stain measured again at the final poses of %d prints; prints it moves more than %.1f px: %s",
                 len(stain_moved), s.edge_pull_px, stain_moved_far)

    # 5e. the images the prints are thresholded on. A stain is the image's, not the print's:
    # thresholded as it is, a print's dim part comes out too small and its bright part too
    # large, and the batch's dense level (its brightest polymer) is where the stain is
    # brightest. So each print whose image was divided for its pose (or, where the batch
    # stains, every print with cured interiors) is thresholded on its image divided by its
    # stain at its final pose (``stain_divisor``), and the dense level comes from those
    # images (unless declared or measured on a reference)
    divisors, div_gain, dense_as_imaged, cured, g_med = {}, {}, None, [], None
    if s.stain_threshold and stains:
        def field_of(mid):  # measured above for the prints the stain was rechecked on (the same fit, the same field)
            if mid in restained:
                return mid, restained[mid]
            return mid, stain_divisor(full, exposure_of(mid), x, choices[mid].fit, smooth_raw(mid), s.stain_sigma_px)

        # prints whose pose is their own (a field measured at a pose a spoke off is no stain)
        cands = [mid for mid in todo if determined(choices[mid], s) and (batch_stained or mid in stains)]
        fields = {mid: fld for mid, fld in pool.map(field_of, cands) if fld is not None}
        # where the batch stains, a print's mean brightness is the stain's too: each print whose
        # interiors the template cures through (its gain then the brightness of cured polymer,
        # not a trade with its dose) is divided by its gain over their median as well
        cured = [mid for mid, (_, t) in fields.items() if t >= s.stain_cured]
        g_med = (float(np.median([choices[mid].fit.gain for mid in cured]))
                 if batch_stained and len(cured) >= s.template_min_prints else None)
        for mid, (fld, t) in fields.items():
            by = g_med if g_med and t >= s.stain_cured else choices[mid].fit.gain  # the gain the divided image has
            divisors[mid], div_gain[mid] = fld * np.float32(choices[mid].fit.gain / by), by
        if divisors and batch.meta.dense_level is None and not reference:  # the empty and faint test (5f) at this level
            def divided(mid, k):
                if mid not in divisors:
                    return k
                H, W = k.c.shape
                d = cv2.warpAffine(divisors[mid], to_design(choices[mid].fit.M, MARGIN).astype(np.float64), (W, H),
                                   flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=1.0)
                return replace(k, c=(k.c / d).astype(np.float32))

            dense_as_imaged = dense
            dense, thr = dense_level([divided(mid, k) for mid, k in corr.items() if mid not in odd], s)
            log.info("stain: %d prints thresholded on their images divided by it%s; dense polymer level %.3g (%.3g on "
                     "the images as they are), threshold %.3g", len(divisors),
                     f" and by their brightness over the batch's median ({min(choices[m].fit.gain for m in cured) / g_med:.2f}"
                     f" to {max(choices[m].fit.gain for m in cured) / g_med:.2f})" if g_med else "", dense, dense_as_imaged, thr)

    n_divided, n_bright = len(divisors), len(cured) if divisors and g_med else 0
    # a print the fit puts below the threshold is near it (step 6), as thresholded or as imaged:
    # a cut-off grating that cured nothing, whose fit as imaged put its polymer at 95 % of the
    # threshold of the images as they are, passed the divided check as ok, 6.5 px off
    near = thr if dense_as_imaged is None else s.level * dense_as_imaged

    # 5f. an image too faint to register is empty only where nothing that its mask may have
    # printed could image that bright: its features cured at the print level, their edges
    # moved in by the batch's erosion at its pessimistic bound (offset less one spread),
    # and blurred by the microscope (thin lines of an eroding batch image far below the
    # level they cured at), or a speck of min_print_px design px, whichever images
    # dimmer (near the threshold the cells' scatter cures specks of a feature, not all of
    # it; the test allows for them whatever the print's dose, since a dim image is itself
    # near the threshold), in an image as much dimmer than the batch's median as its
    # prints' brightness varies (lamp, stain: ``dimmest``)
    erode = max(0.0, -(centre[0] - edge_sd[0]))
    dim = dimmest([choices[mid].fit.gain for mid in placed_ids], s)
    empty, faint = {}, {}  # id -> reason
    doses = [choices[mid].fit.dose for mid in placed_ids if np.isfinite(choices[mid].fit.dose)]
    top_dose = max(doses) if len(doses) >= s.size_min_prints else None  # the empty cure test wants a batch's doses
    # ... and the numbers of the template that the prints set: where the fit left a number that a feature's cure
    # relative to a block's rests on at a bound, the prints did not set it, and the share must stay under the bound
    # whether the number is there or back where the fit began (and halfway): seen, a soft cure curve (k at 3) with
    # its tail 100 px wide took a Siemens star's cure to 20 % of a block's (72 % with k and the tail's width at their
    # starts; the lab cured it to 60 %), and the star, printed, was called empty
    unset = PrintTemplate.on_bounds(x)
    cure_xs = [x] + [PrintTemplate.toward_start(x, unset, f) for f in ((0.5, 1.0) if unset else ())]
    cure_test = dict(used=top_dose is not None and s.empty_cure_share > 0, numbers_on_bounds=unset, prints=len(doses))
    block_peaks = None  # a large block's scattered dose peak for each of cure_xs, made once where a print needs it
    for mid, n_above in low.items():
        if dense_as_imaged is not None:  # the threshold the stain's division set (5e), not the one 'low' was judged at
            n_above = int(np.count_nonzero(smooth[mid] > max(thr, 6 * corr[mid].noise)))
            if n_above >= s.min_print_px:
                faint[mid] = (f"not registered: {n_above} px above the batch threshold, which the stain's division "
                              f"lowered to {thr:.3g}, but fewer than {s.min_print_px} above the threshold of the images as "
                              f"they are ({s.level * dense_as_imaged:.3g}), at which the batch's poses were sought")
                continue
        peak = float(smooth[mid].max())
        sc = float(np.sqrt(scales[mid][0][0] * scales[mid][0][1]))
        blur = float(np.hypot(x[10], 1.0 / sc))
        cure = None
        if cure_test["used"] and not n_above:  # nothing above the threshold: may the batch's template cure it?
            block_peaks = block_peaks or [block_dose_peak(full, design_px, a) for a in cure_xs]
            cures = [template_cure_share(full, masks[mid], a, top_dose, b) for a, b in zip(cure_xs, block_peaks)]
            cure = max(cures)
        if cure is not None and cure < s.empty_cure_share * s.level:
            # nothing images above the threshold, and the batch's own model cures nothing of the
            # mask to the print level at the batch's highest dose: empty, not merely unseen (a
            # few px above the threshold may be specks that the cells' scatter cured, which the
            # template does not predict: seen, 73 px of a cut-off grating at a share of 42 %)
            empty[mid] = (f"no polymer above the batch threshold, and the batch's template cures its mask "
                          f"to at most {100 * cure:.1f} % of a large block's density at the highest dose of its "
                          f"determined prints ({top_dose:.2f}), under {100 * s.empty_cure_share * s.level:.1f} %"
                          + (f", with {', '.join(unset)} (on a bound of its fit) where the fit left them or began"
                             if unset else ""))
            continue
        whole = imaged_peak(masks[mid], blur, erode)
        speck = speck_peak(s.min_print_px, blur)
        reach = min(whole, speck)
        if np.isfinite(thr) and peak >= max(s.faint_fraction * dim * reach * thr, 6 * corr[mid].noise):
            # polymer this bright may have cured at the print level in features that the
            # microscope's blur spreads below the threshold (thin lines, small dots): not
            # evidence that nothing printed
            what = ("its mask's features, cured at the print level"
                    + (f" and eroded by {erode:.1f} px as this batch's prints may be" if erode > 0 else "")
                    if whole <= speck else f"a speck of {s.min_print_px} px cured at the print level (what near the "
                    f"threshold the cells' scatter cures of a feature)")
            faint[mid] = (f"faint: its brightest polymer reaches {100 * peak / thr:.0f} % of the batch threshold, in {n_above} "
                          f"px (fewer than {s.min_print_px}), and {what}, would image at {100 * reach:.0f} % of it"
                          + (f" ({100 * dim * reach:.0f} % in an image as dim as this batch's prints may be)" if dim < 1 else "")
                          + ": whether it printed cannot be told, and it is not empty"
                          + (f" (the batch's template cures it to {100 * cures[0]:.0f} % of a block, but to "
                             f"{100 * max(cures):.0f} % with {', '.join(unset)}, which its fit left on a bound, where the "
                             "fit began)" if cure is not None and cures[0] < s.empty_cure_share * s.level else ""))
        else:
            empty[mid] = "no polymer above the batch threshold"


    # 6. warp, threshold, QC, write
    def finish(mid):
        k, mask = corr[mid], masks[mid]
        row = dict(id=mid, status="ok", reason="", rotation_deg="", scale="", shift_x="", shift_y="", score="",
                   evidence="", pose_sd="", size_sd="", model_sd="", misfit="", dose="", blur="", stain="", threshold=thr, dense_level=dense, flatfield=ff_mode, coverage="", solid_fraction="",
                   mask=os.path.relpath(batch.masks[mid].resolve(), final_dir.resolve()), image=str(batch.images[mid]))
        if mid in odd:
            row.update(status="failed", reason=f"not a print image: {odd[mid]}")
            return row, None
        if mid in faint:
            row.update(status="failed", reason=faint[mid])
            return row, None
        if mid in empty:
            printed = np.zeros((design_px, design_px), bool)
            row.update(status="empty", reason=empty[mid], solid_fraction=0.0)
            write_rgb(out_dir / "overlays" / f"{mid}.png", _overlay(np.zeros(printed.shape), mask, printed, 1.0))
            return row, printed
        if mask.max() == 0:
            row.update(status="failed", reason="polymer in the image but the mask is all zero")
            return row, None
        ch = choices[mid]
        M = to_design(ch.fit.M, MARGIN)
        pose = pose_of(M, design_px, k.c.shape)
        reg, printed = threshold_print(k.c, M, thr_print, design_px, divisors.get(mid))
        row["threshold"] = thr_print
        gain = ch.fit.gain
        tpl = as_imaged = predicted_print(full, exposure_of(mid), x, ch.fit)[MARGIN:-MARGIN, MARGIN:-MARGIN]
        if mid in divisors:  # what the print's image was divided by before its threshold; the divided image is
            # the fit's print without its brightness slopes, at the gain it was divided to (stain_divisor)
            (out_dir / "stain").mkdir(exist_ok=True)
            tifffile.imwrite(out_dir / "stain" / f"{mid}.tif", divisors.pop(mid))
            tpl = slopeless_print(full, exposure_of(mid), x, ch.fit)[MARGIN:-MARGIN, MARGIN:-MARGIN]
            gain = div_gain[mid]
        exposed.pop(mid, None)  # its last use
        score = ncc(reg, tpl)
        cov = coverage(M, mask, k.c.shape)
        row.update(**{kk: round(v, 4) for kk, v in pose.items()}, score=round(score, 4), coverage=round(cov, 4),
                   evidence=round(ch.evidence, 2) if np.isfinite(ch.evidence) else "inf", dose=round(ch.fit.dose, 4),
                   pose_sd=round(min(ch.fit.pose_sd, 1e6), 3), size_sd=round(min(ch.fit.size_sd, 1e6), 3),
                   model_sd=round(min(ch.fit.model_sd, 1e6), 3), blur=round(ch.fit.blur, 3),
                   stain=round(stains[mid], 3) if mid in stains else "")
        for a in range(2):
            for b in range(3):
                row[f"m{a}{b}"] = float(M[a, b])
        reasons = []
        if not ch.converged:
            reasons.append("pose refinement did not converge")
        if not s.rotation_deg[0] - 1 <= pose["rotation_deg"] <= s.rotation_deg[1] + 1:
            reasons.append(f"rotation {pose['rotation_deg']:.1f} deg outside {tuple(s.rotation_deg)}")
        lo, hi = scales[mid][0]
        if mid in stated:  # a stated scale, as the batch measured it (stated_scales)
            c, sd = stated[mid]
            if abs(log_scale(ch.fit.M) - c) > s.scale_sigmas * sd:
                reasons.append(f"scale {pose['scale']:.4f} off its stated {np.exp(c):.4f} ({scales[mid][1]}; as the batch's "
                               f"prints measure it) by more than {s.scale_sigmas:g} times its spread ({100 * sd:.2f} %)")
        else:  # widened toward the offset of a stated size that the batch's prints contradict (stated_scales)
            lo, hi = lo * min(1.0, np.exp(stale)), hi * max(1.0, np.exp(stale))
            if not lo <= pose["scale"] <= hi:
                reasons.append(f"scale {pose['scale']:.4f} outside {lo:.4f}..{hi:.4f} ({scales[mid][1]}"
                               + (f", widened by the {100 * stale:+.2f} % that the batch's prints measure it off" if stale else "")
                               + ")")
        if score < s.min_score:
            reasons.append(f"registration score {score:.2f} below {s.min_score}")
        if off_rotation(ch.fit.M):
            reasons.append(f"rotation {pose['rotation_deg']:.1f} deg off the batch's {one_rotation[0]:.1f} by more than "
                           f"{one_rotation[1]:.1f} deg ({s.rotation_mads:g} times the spread of its prints whose pose "
                           f"their features fix): one microscope imaged the batch")
        if ch.symmetry is not None:
            reasons.append(f"ambiguous: the mask maps onto itself rotated by {ch.symmetry:.1f} deg, and the pose so turned "
                           f"({pose_distance(ch.rival, ch.fit.M, design_px + 2 * MARGIN, MARGIN):.1f} px away) lies within "
                           f"the batch's rotations: only details of the print that its model may not hold tell them apart")
        elif ch.evidence < s.min_evidence:
            rv = pose_of(to_design(ch.rival, MARGIN), design_px, k.c.shape)
            reasons.append(f"ambiguous: a pose {pose_distance(ch.rival, ch.fit.M, design_px + 2 * MARGIN, MARGIN):.1f} px away "
                           f"(rotation {rv['rotation_deg']:.2f} deg, scale {rv['scale']:.4f}, shift {rv['shift_x']:.1f}, "
                           f"{rv['shift_y']:.1f}) fits almost as well (evidence {ch.evidence:.1f} < {s.min_evidence})")
        elif ch.field_set is not None:
            z_f, share_f, M_f = ch.field_set
            rv = pose_of(to_design(M_f, MARGIN), design_px, k.c.shape)
            reasons.append(f"ambiguous: a pose {pose_distance(M_f, ch.fit.M, design_px + 2 * MARGIN, MARGIN):.1f} px "
                           f"away (rotation {rv['rotation_deg']:.2f} deg, scale {rv['scale']:.4f}, shift {rv['shift_x']:.1f}, "
                           f"{rv['shift_y']:.1f}) lays the same mask over every part of the print that cured (it differs "
                           f"over {100 * share_f:.2f} % of it): only where the batch's template puts the lamp's "
                           f"field sets the two apart (evidence {z_f:.1f}), as along a grating that spans the "
                           f"field and cured in part of it")
        if not ch.fit.pose_sd <= s.max_pose_sd:
            how = (f"uncertain by {ch.fit.pose_sd:.2f} px (more than {s.max_pose_sd})" if ch.fit.pose_sd < 1e3 else
                   "free along some direction (a shift along a grating's lines, a turn of a disc)")
            if mid in weighed:
                how += (f", its scale weighed against its stated camera pixel size: the batch's prints scatter about "
                        f"their stated sizes by {100 * scatter['spread']:.2f} %, more than their own spreads say, and its "
                        f"template misplaces their edges by {misfit:.2f} px")
            reasons.append(f"pose not determined by the print: {how}")
        if not ch.fit.size_sd <= s.max_size_sd:
            by = f"uncertain by {min(ch.fit.size_sd, 1e6):.2f} px (more than {s.max_size_sd})"
            if mid in stated_held or held_scale is not None:  # its scale held, not left to its features' size: the
                # spread is what its turn and shift rest on (and a stated size's tolerance over the field)
                sp = ch.fit.scale_prior if mid in stated_held else None
                to = ("the batch's one magnification" if mid not in stated_held else "its stated camera pixel size"
                      + (f" (known within {100 * sp[1]:.2f} %, {field_radius_px(design_px) * sp[1]:.2f} px over the "
                         f"field)" if sp is not None else ""))
                reasons.append(f"pose not determined by the print: its scale held to {to}, its turn or shift still rests "
                               f"on the sizes of its features more than on where they lie (few, small or close together; "
                               f"a ring turns freely); {by}")
            else:
                reasons.append(f"pose not determined by the print: its scale rests on the size of a feature (one block, a "
                               f"grating printed as one) more than on where its features lie; "
                               f"{by}{stated_note or no_size_note(mid)}")
        elif not np.hypot(ch.fit.size_sd, ch.fit.model_sd) <= s.max_size_sd:
            reasons.append(f"pose not determined by the print: it rests on the shape of the scatter kernel, which the batch's "
                           f"template knows only roughly (an edge on a grey ramp or at a dose near the cure threshold, with "
                           f"no edge opposite it that moves alike): the fit moves it by {min(ch.fit.model_sd, 1e6):.2f} px "
                           f"with the kernel's tail share off by {KERNEL_TAIL * kernel_off['tail']:.2f}, as far as the "
                           f"batch's prints show it off, and with its spread from the sizes of its features ({ch.fit.size_sd:.2f} px), "
                           f"{min(float(np.hypot(ch.fit.size_sd, ch.fit.model_sd)), 1e6):.2f} px, more than {s.max_size_sd}")
        if mid in field_moved_far:
            fm = field_moved[mid]  # (move, width, NCC against the best): not named in this scope, whose gain is the print's
            reasons.append(f"pose rests on the lamp's field, which the batch's prints do not fix: a hot spot {fm[1]:.2f} wide "
                           f"fits the prints whose features place their pose as well (mean NCC {fm[2]:+.5f} against the "
                           f"best field) and moves this print's pose {fm[0]:.2f} px (more than {s.edge_pull_px})")
        if mid in stain_moved_far:
            reasons.append(f"pose rests on the stain its image was divided by: that stain was measured at the print's "
                           f"first pose, and measured again at its final pose it moves the pose {stain_moved[mid]:.2f} px "
                           f"(more than {s.edge_pull_px}): the print's edges and the stain's field trade against each other")
        if mid in edge_moved:
            f = ch.fit
            reasons.append(f"pose rests on edges off the batch's: its fitted edge offsets (all round {f.edge:+.2f} px, by "
                           f"direction {f.edge_c2:+.2f}, {f.edge_s2:+.2f}) lie {pulled[mid][0]:.0f} times the batch's "
                           f"spread off the batch's ({centre[0]:+.2f}, {centre[1]:+.2f}, {centre[2]:+.2f} +- "
                           f"{edge_sd[0]:.2f}, {edge_sd[1]:.2f} px), and with them held there its pose moves "
                           f"{pulled[mid][1]:.2f} px (more than {s.edge_pull_px}): the batch's template does not describe "
                           f"the print (a grey ramp's one sharp edge at its grey, a cure it does not predict)")
        if off_scale(ch.fit.M):
            reasons.append(f"scale {pose['scale']:.4f} off the batch's {np.exp(one_scale[0]):.4f} by more than "
                           f"{s.scale_sigmas:g} times its spread ({100 * one_scale[1]:.2f} %): one magnification imaged "
                           f"the batch")
        if cov < s.min_coverage:
            reasons.append(f"print extends beyond the image (only {100 * cov:.1f} % in view)")
        predicted = gain * tpl + ch.fit.offset
        # below the threshold as thresholded, or as imaged (the fit's print with its slopes, against the
        # threshold of the images as they are): either makes a print near the threshold
        share = min(float(predicted.max()) / thr_print, float((ch.fit.gain * as_imaged + ch.fit.offset).max())
                    / (near * thr_print / thr))
        if printed.any() and share < 1.0:
            # a near-threshold print whose polymer the fit puts below the threshold everywhere:
            # what crosses it is noise (or a cure the template does not predict), and its pose
            # rests on the grey of uncured gel, not on a print's edges
            reasons.append(f"near the threshold: at this pose and dose the batch's template puts its polymer at "
                           f"{100 * share:.0f} % of the threshold at most"
                           + (" (as imaged or divided by its stain)" if mid in div_gain else "")
                           + f", so the {int(printed.sum())} px above it are noise or a cure the template does not "
                           f"predict")
        if half_cure and not printed.any():
            reasons.append(f"nothing above the half cure's threshold ({thr_print:.3g}; the batch threshold {thr:.3g})")
        row["solid_fraction"] = round(float(printed.mean()), 5)
        row["misfit"] = misfit_px(printed, predicted, thr_print)
        write_rgb(out_dir / "overlays" / f"{mid}.png", _overlay(reg, mask, printed, dense))
        if reasons:
            row.update(status="failed", reason="; ".join(reasons))
        return row, printed

    thr_print, half_cure = thr, None
    if s.half_cure and np.isfinite(thr):
        print_scales = [float(np.exp(log_scale(ch.fit.M))) for ch in choices.values() if ch.fit is not None]
        smoothing = smoothing_px(float(np.median(print_scales))) if print_scales else 0.5
        # the level over a large area's image where the dense level is estimated from the batch's brightest
        # polymer (that area's image), over full cure where it is declared or measured on a dense reference
        lvl = half_cure_level(x, smoothing, full=batch.meta.dense_level is not None or bool(reference))
        if lvl is not None:
            thr_print = thr * lvl / s.level
            half_cure = dict(level=round(lvl, 4), threshold=float(thr_print), smoothing_px=round(smoothing, 4))
            log.info("half cure: the template's image of an edge crosses its half cure at %.3f of the plateau; prints "
                     "cut at %.3g (not %.3g)", lvl, thr_print, thr)
        else:
            log.warning("half cure: the template does not cure a large area to half; prints cut at level %.2f", s.level)
    done = pmap(finish, ids)
    rows = [r for r, _ in done]
    bad = mismatched(rows, s)
    for r in rows:
        if r["id"] in bad:  # the likeliest cause first: a pose is hard to find for the wrong mask
            why = f"does not match its mask: {bad[r['id']]}"
            r.update(status="failed", reason=why + (f"; {r['reason']}" if r["reason"] else ""))
    for r, printed in done:
        if isinstance(r["misfit"], float):
            r["misfit"] = round(r["misfit"], 3)
        if r["status"] in ("ok", "empty"):
            write_png(out_dir / f"{r['id']}.png", printed)
    bar.close()
    pool.shutdown()
    cols = ["id", "status", "reason", "rotation_deg", "scale", "shift_x", "shift_y", "score", "evidence", "pose_sd", "size_sd", "model_sd", "misfit", "dose", "blur", "stain", "coverage",
            "threshold", "dense_level", "flatfield", "solid_fraction", "mask", "image"] + [f"m{a}{b}" for a in range(2) for b in range(3)]
    write_tsv(out_dir / "qc.tsv", rows, cols)
    write_yaml(out_dir / "batch.yaml", dict(meta, source_batch=str(batch_dir)))
    write_yaml(out_dir / "registration.yaml", dict(settings=dict(mode=s.mode, level=s.level, min_score=s.min_score),
                                                   flatfield=ff_mode, dense_level=dense, threshold=thr, dense_reference=reference,
                                                   print_template=p,
                                                   template_prints=template_prints,
                                                   measurement=None if half_cure else measurement_record(p, rows, s.level, batch.meta),
                                                   half_cure=half_cure,
                                                   one_magnification=None if one_scale is None else dict(
                                                       scale=float(np.exp(one_scale[0])), spread=one_scale[1], prints=len(placed),
                                                       held_within=held_scale[1]),
                                                   edge_places=edge_places, feature_sizes=feature_sizes,
                                                   edge_pull=dict(sds=s.edge_pull_sds, px=s.edge_pull_px, refitted=len(pulled),
                                                                  moved=sorted(edge_moved)),
                                                   field_alternatives=dict(
                                                       tried=s.field_alternatives,
                                                       widths=[round(w, 4) for _, _, w in alternatives],
                                                       ncc_gains=[float(g) for _, g, _ in alternatives],
                                                       moved=field_moved_far),
                                                   empty_cure_test=cure_test,
                                                   kernel_shape=dict(tail=kernel_off["tail"], width=kernel_off["wider"],
                                                                     tail_share=KERNEL_TAIL, width_change=round(KERNEL_WIDTH - 1, 3),
                                                                     width_counted=False, prints=kernel_prints),
                                                   stain=dict(prints=len(stains), sigma_px=s.stain_sigma_px, min_sd=s.stain_min_sd,
                                                              template_refitted=stain_refit,
                                                              spot_kept_gain=None if spot_kept is None else float(spot_kept),
                                                              thresholded_divided=n_divided,
                                                              by_brightness=n_bright,
                                                              dense_level_as_imaged=dense_as_imaged,
                                                              rechecked=len(stain_moved), moved=stain_moved_far),
                                                   stated_scatter=scatter))
    contact_sheet(out_dir / "overlays", rows, out_dir / "overlays.png")
    return rows


def contact_sheet(overlay_dir: Path, rows: list[dict], out_path: Path, thumb: int = 160, cols: int = 8) -> None:
    """All overlays of a batch on one page, each labelled with its id and QC status."""
    from PIL import Image, ImageDraw

    n = len(rows)
    ncols = min(cols, max(n, 1))
    nrows = (n + ncols - 1) // ncols
    sheet = Image.new("RGB", (ncols * thumb, nrows * (thumb + 14)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    colour = {"ok": (0, 120, 0), "empty": (90, 90, 90), "failed": (200, 0, 0)}
    for i, r in enumerate(rows):
        x, y = (i % ncols) * thumb, (i // ncols) * (thumb + 14)
        p = overlay_dir / f"{r['id']}.png"
        if p.is_file():
            with Image.open(p) as im:
                sheet.paste(im.convert("RGB").resize((thumb, thumb)), (x, y + 14))
        draw.text((x + 2, y + 1), f"{r['id']} {r['status']}", fill=colour.get(r["status"], (0, 0, 0)))
    out_path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out_path)
