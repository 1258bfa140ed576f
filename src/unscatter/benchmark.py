"""Benchmark: compensated masks against identical masks (Guan et al. 2022, 'Results',
Fig. 6).

For every design, the masks printed are

- each compensation method's mask (nn, ilt, nn+ilt, ...), and
- the identical mask (the design itself) at 100, 75, 70 and 50 % grey, as an operator
  would tune the dose of a plain mask (Guan et al. 2022, 'Results');

each at the nominal exposure and, for the PV band, at 90 % and 110 % of it (docs/design.md,
'Metrics'). The 110 % print cannot be a mask value (255 is the most a mirror gives), so
the PV prints change the exposure (time or lamp power), as dose drift does.

Each print is scored against its design with ``unscatter.metrics`` (IoU, pixel error,
EPE, PV band); ``metrics.tsv`` has one row per design x mask, and the figures are one
like Fig. 6 (prints over designs), one like Fig. 5 (the compensated masks with the
design's contour) and bars of the mean metrics.

Print ids (one flat folder of masks, one batch): ``<design>__<variant>`` at the nominal
exposure and ``<design>__<variant>__x090`` / ``__x110`` at 90 / 110 % of it, where the
variant is a method name or ``identical_<grey %>``.

Where the prints come from:

- a **printer callable** ``printer(masks, exposures) -> prints`` (``run_benchmark``):
  the calibrated simulator (``simulator_printer``) or, for in-process benchmarks, the
  virtual lab (``unscatter.lab.jobs.virtual_lab_printer``, which lives in the lab: this
  module never imports the lab);
- a **printer through files** (a real one, or the virtual lab in the workflow):
  ``write_print_job`` writes the masks as a print job (masks/, batch.yaml, job.tsv with
  each mask's exposure); once printed, imaged and registered like any batch,
  ``score_measured`` scores it. No score ever reads the lab's truth.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path
from typing import Callable

import numpy as np

from . import metrics
from .io import InputError, list_pngs, output_dir, read_batch_meta, read_mask, read_print, read_tsv, write_png, write_tsv, write_yaml
from .masks import carries_marks, fiducial_marks, with_fiducials
from .settings import BENCHMARK, PAPER_PIXEL_SIZE_UM

log = logging.getLogger(__name__)

IDENTICAL = "identical"
# Guan et al. 2022, 'Results': identical masks at 100, 75, 70 and 50 % grey (Fig. 6 shows 100/75/70).
IDENTICAL_DOSES = tuple(BENCHMARK.default.doses)
# docs/design.md, 'Metrics': the PV band is between prints at 90 % and 110 % of the nominal dose.
PV_EXPOSURES = (0.9, 1.1)
# The most grey (of 255) that a benchmark mask may have in the registration marks' cleared band, which the marks
# replace: 5 % of full grey, far below any cure, and what a network's mask has there (3 to 5 in the default run's nn
# and nn+ilt masks); an ILT mask's assist grey near a design at the corners (rings: up to 24) is more, and keeps it
# without marks
MARK_ROOM_GREY = 13

COLUMNS = ["design", "method", "mask_dose", "variant", "status", "iou", "pixel_error", "epe_um", "pv_band_um",
           "solid_fraction"]
METRICS = ("iou", "pixel_error", "epe_um", "pv_band_um")
SUMMARY_COLUMNS = ["method", "mask_dose", "variant", "designs", *METRICS, "no_print", "common_designs",
                   *(f"common_{k}" for k in METRICS)]

Printer = Callable[[dict, dict], dict]  # (id -> uint8 mask, id -> exposure) -> id -> bool print (or None: no print)


# ------------------------------------------------------------------------------ ids

_METHOD = re.compile(r"^[A-Za-z0-9+]+(?:_[A-Za-z0-9+]+)*$")
_EXPOSURE = re.compile(r"^x(\d{3})$")
_IDENTICAL = re.compile(rf"^{IDENTICAL}_(\d{{1,3}})$")


def variant(method: str, mask_dose: float = 1.0) -> str:
    """The variant token of a print id: the method, or ``identical_<grey %>``."""
    if method == IDENTICAL:
        return f"{IDENTICAL}_{int(round(100 * mask_dose))}"
    if not _METHOD.match(method) or method.startswith(IDENTICAL) or "__" in method:
        raise ValueError(f"method name {method!r}: use letters, digits, '+' and single '_' (not 'identical...')")
    return method


def print_id(design: str, method: str, mask_dose: float = 1.0, exposure: float = 1.0) -> str:
    """``<design>__<variant>``, plus ``__x<exposure %>`` off the nominal exposure."""
    if not design or "__" in design or design.startswith("_") or design.endswith("_"):
        raise ValueError(f"design name {design!r} must not contain '__' or start/end with '_'")
    pid = f"{design}__{variant(method, mask_dose)}"
    if abs(exposure - 1.0) > 1e-9:
        pid += f"__x{int(round(100 * exposure)):03d}"
    return pid


def parse_print_id(pid: str) -> dict:
    """Back from a print id: design, method, mask_dose, exposure, variant."""
    parts = pid.split("__")
    exposure = 1.0
    if len(parts) == 3 and _EXPOSURE.match(parts[2]):
        exposure = int(_EXPOSURE.match(parts[2]).group(1)) / 100
        parts = parts[:2]
    if len(parts) != 2 or not parts[0] or not parts[1]:
        raise ValueError(f"{pid!r} is not a benchmark print id (<design>__<method or identical_NN>[__xNNN])")
    design, var = parts
    m = _IDENTICAL.match(var)
    if m:
        return dict(design=design, method=IDENTICAL, mask_dose=int(m.group(1)) / 100, exposure=exposure, variant=var)
    if not _METHOD.match(var):
        raise ValueError(f"{pid!r}: {var!r} is not a method name")
    return dict(design=design, method=var, mask_dose=1.0, exposure=exposure, variant=var)


def label(method: str, mask_dose: float) -> str:
    return f"identical {int(round(100 * mask_dose))} %" if method == IDENTICAL else method


# -------------------------------------------------------------------------- the masks


def identical_mask(design: np.ndarray, dose: float = 1.0) -> np.ndarray:
    """The design as a mask at ``dose`` (grey = round(255 * dose) where solid)."""
    if not 0 < dose <= 1:
        raise ValueError(f"an identical mask's dose is a grey level in (0, 1], got {dose}")
    return np.where(np.asarray(design) != 0, np.uint8(round(255 * dose)), np.uint8(0))


def _designs(designs) -> dict:
    """name -> bool design, from a folder of PNGs or a dict of arrays."""
    if isinstance(designs, dict):
        return {k: np.asarray(v) != 0 for k, v in designs.items()}
    files = list_pngs(designs)
    if not files:
        raise InputError(designs, "no design .png files")
    return {k: read_mask(p) != 0 for k, p in files.items()}


def _method_masks(masks_by_method: dict, designs: dict) -> dict:
    """method -> name -> uint8 mask, from folders of <design>.png or dicts of arrays."""
    out = {}
    for method, src in masks_by_method.items():
        if method == IDENTICAL:
            raise ValueError(f"{IDENTICAL!r} is the benchmark's own reference, not a method name")
        variant(method)  # checks the name
        got = {}
        for name, d in designs.items():
            if isinstance(src, dict):
                if name not in src:
                    raise ValueError(f"method {method!r} has no mask for design {name!r}")
                m = np.asarray(src[name])
                where = f"{method}/{name}"
            else:
                path = Path(src) / f"{name}.png"
                m = read_mask(path)
                where = path
            if m.dtype != np.uint8 or m.shape != d.shape:
                raise InputError(where, f"mask must be uint8 of the design's size {d.shape}, got {m.dtype} {m.shape}")
            got[name] = m
        out[method] = got
    return out


def benchmark_masks(designs, masks_by_method: dict, doses=IDENTICAL_DOSES, pv_band: bool = True,
                    fiducials: bool = False) -> tuple[dict, dict]:
    """Every mask of the benchmark and its exposure: (id -> uint8 mask, id -> exposure).

    ``fiducials``: the registration marks (``masks.with_fiducials``) on every mask of each
    design whose masks (every method's and the identical ones) leave the marks' cleared
    band dark (``MARK_ROOM_GREY`` at most); a design that reaches into it is printed
    without them (logged)."""
    designs = _designs(designs)
    by_method = _method_masks(masks_by_method, designs)
    exposures = (1.0,) + (tuple(PV_EXPOSURES) if pv_band else ())
    masks, expo = {}, {}
    for name, d in designs.items():
        entries = [(m, 1.0, by_method[m][name]) for m in by_method]
        entries += [(IDENTICAL, dose, identical_mask(d, dose)) for dose in doses]
        if fiducials and d.shape[0] != d.shape[1]:
            log.warning("%s: printed without registration marks: they are laid out for a square field", name)
        elif fiducials:
            clear = fiducial_marks(d.shape[0])[1]
            if all(mask[clear].max(initial=0) <= MARK_ROOM_GREY for _, _, mask in entries):
                entries = [(method, dose, with_fiducials(mask)) for method, dose, mask in entries]
            else:
                log.warning("%s: printed without registration marks: its masks reach into the marks' corners (grey above "
                            "%d there)", name, MARK_ROOM_GREY)
        for method, dose, mask in entries:
            for e in exposures:
                pid = print_id(name, method, dose, e)
                masks[pid], expo[pid] = mask, e
    return masks, expo


# ------------------------------------------------------------------------ printers


def simulator_printer(params) -> Printer:
    """The calibrated simulator as a printer: Eq. 1 with the hard threshold.

    An exposure k scales the absorbed dose by k, which for a threshold T is the same
    print as the nominal dose against the threshold T / k.
    """
    from .model import load_params, simulate

    p = params if not isinstance(params, (str, Path)) else load_params(params)

    def printer(masks: dict, exposures: dict) -> dict:
        out = {}
        for e in sorted(set(exposures.values())):
            ids = [i for i in masks if exposures[i] == e]
            prints = simulate(p.with_values(T=p.values["T"] / e), [masks[i] for i in ids])
            out.update(zip(ids, prints))
        return out

    return printer


def exposure_token(exposure: float) -> str:
    return f"x{int(round(100 * exposure)):03d}"


def registered_masks(prints_dir, rows: list[dict] | None = None) -> dict:
    """id -> the mask of each print of a registration output whose qc.tsv names one that
    is there (``rows``: qc.tsv's rows, read where not given)."""
    prints_dir = Path(prints_dir)
    rows = read_tsv(prints_dir / "qc.tsv") if rows is None else rows
    paths = {r["id"]: (prints_dir / r["mask"]).resolve() for r in rows if r.get("mask")}
    return {k: read_mask(p) for k, p in paths.items() if p.is_file()}


def read_registered(prints_dir, masks: dict | None = None) -> dict:
    """id -> bool print of a registration output (None where registration failed).

    A print whose mask (qc.tsv's ``mask``; ``masks``: ``registered_masks``, read where not
    given) carries the registration marks is returned without them: the marks' cleared
    band, empty in its design, is set to no print."""
    prints_dir = Path(prints_dir)
    qc = prints_dir / "qc.tsv"
    if qc.is_file():
        rows = read_tsv(qc)
        masks = registered_masks(prints_dir, rows) if masks is None else masks
        out = {}
        for r in rows:
            p = read_print(prints_dir / f"{r['id']}.png") if r["status"] in ("ok", "empty") else None
            if p is not None and r["id"] in masks and carries_marks(masks[r["id"]]):
                p = p.copy()
                p[fiducial_marks(p.shape[0])[1]] = False
            out[r["id"]] = p
        return out
    files = list_pngs(prints_dir)
    if not files:
        raise InputError(prints_dir, "no registered prints (qc.tsv or <id>.png)")
    return {k: read_print(p) for k, p in files.items()}


# ------------------------------------------------------------------------- scoring


def score_prints(prints: dict, designs, pixel_size_um: float) -> list[dict]:
    """metrics.tsv rows (one per design x mask) from prints keyed by print id.

    A missing or failed nominal print gives a row with status 'no print' and no
    metrics; a missing 90 or 110 % print leaves the PV band empty.
    """
    designs = _designs(designs)
    parsed = {}
    for pid in prints:
        try:
            parsed[pid] = parse_print_id(pid)
        except ValueError:
            log.warning("%s is not a benchmark print id; ignored", pid)
    keys = sorted({(q["design"], q["method"], q["mask_dose"]) for q in parsed.values()},
                  key=lambda k: (k[0], k[1] == IDENTICAL, k[1], -k[2]))
    rows = []
    for name, method, dose in keys:
        if name not in designs:
            raise ValueError(f"prints of design {name!r}, which is not among the designs {sorted(designs)}")
        d = designs[name]
        get = lambda e: prints.get(print_id(name, method, dose, e))  # noqa: E731
        p = get(1.0)
        row = dict(design=name, method=method, mask_dose=dose, variant=label(method, dose))
        if p is None:
            row.update(status="no print", iou=math.nan, pixel_error=math.nan, epe_um=math.nan, pv_band_um=math.nan,
                       solid_fraction=math.nan)
        else:
            p = np.asarray(p, bool)
            if p.shape != d.shape:
                raise ValueError(f"print {print_id(name, method, dose)} is {p.shape}, its design {d.shape}")
            row.update(status="ok", **metrics.score(p, d, pixel_size_um), solid_fraction=float(p.mean()))
            lo, hi = (get(e) for e in PV_EXPOSURES)
            row["pv_band_um"] = metrics.pv_band_um(lo, hi, d, pixel_size_um) if lo is not None and hi is not None else math.nan
        rows.append(row)
    return rows


FULL_GREY = 1.0  # the mask dose of the masks compared head to head: each method's, and the identical mask at 100 %


def common_designs(rows: list[dict]) -> list[str]:
    """The designs that every mask at full grey (``FULL_GREY``) printed: the set on which
    the masks are compared head to head (none where no row is at full grey)."""
    printed: dict = {}
    for r in rows:
        if r["mask_dose"] == FULL_GREY:
            got = printed.setdefault(r["variant"], set())
            if r["status"] == "ok":
                got.add(r["design"])
    return sorted(set.intersection(*printed.values())) if printed else []


def summarise(rows: list[dict]) -> list[dict]:
    """Mean metrics per method (and identical dose) over the designs with a print; the
    count of ``common_designs`` (``common_designs``) and the means over them
    (``common_*``, NaN for a mask without a print of every one of them); and the designs
    a mask has no print of (``no_print``).

    A print that failed registration QC (or was never imaged) has no metrics, so each
    mask's mean over its own designs may be over other designs than the next mask's: in
    a run of the default workflow the registration failed the star's nominal prints of
    three methods (it could not place them, their true error 0.67 to 2.25 px), and those
    methods' means left out a design that the others' held. The ``common_*`` columns
    compare the masks on the same designs."""
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["method"], r["mask_dose"]), []).append(r)
    common = set(common_designs(rows))
    out = []

    def means(rs):
        return {k: float(np.nanmean([r[k] for r in rs])) if rs and not all(np.isnan(r[k]) for r in rs) else math.nan
                for k in METRICS}

    for (method, dose), rs in sorted(groups.items(), key=lambda kv: (kv[0][0] == IDENTICAL, kv[0][0], -kv[0][1])):
        ok = [r for r in rs if r["status"] == "ok"]
        shared = [r for r in ok if r["design"] in common]
        on_common = means(shared) if common and len(shared) == len(common) else dict.fromkeys(METRICS, math.nan)
        out.append(dict(method=method, mask_dose=dose, variant=label(method, dose), designs=len(ok), **means(ok),
                        no_print=",".join(sorted(r["design"] for r in rs if r["status"] != "ok")),
                        common_designs=len(common), **{f"common_{k}": v for k, v in on_common.items()}))
    return out


def compared_on_common(summary: list[dict]) -> bool:
    """Whether the masks of ``summary`` are to be compared on their common designs: there
    are some, and a mask's own designs are not just those."""
    return any(s["common_designs"] for s in summary) and any(s["designs"] != s["common_designs"] for s in summary)


def summary_line(s: dict) -> str:
    """One summary row as the CLI and the workflow log print it."""
    n = s["designs"]
    line = (f"{s['variant']:<16} IoU {s['iou']:.3f}  pixel error {s['pixel_error']:.3f}  EPE {s['epe_um']:.1f} um  "
            f"PV band {s['pv_band_um']:.1f} um  ({n} design{'' if n == 1 else 's'})")
    if s["no_print"]:
        line += f"; no print of {s['no_print']}"
    if s["common_designs"] and s["common_designs"] != n and not np.isnan(s["common_iou"]):
        line += (f"; on the {s['common_designs']} designs that every full-grey mask printed: IoU {s['common_iou']:.3f}, "
                 f"EPE {s['common_epe_um']:.1f} um")
    return line


def write_results(rows: list[dict], out_dir, designs, prints: dict, masks: dict | None = None, figures: bool = True) -> None:
    """metrics.tsv, summary.tsv and the figures."""
    out_dir = Path(out_dir)
    write_tsv(out_dir / "metrics.tsv", rows, COLUMNS)
    summary = summarise(rows)
    write_tsv(out_dir / "summary.tsv", summary, SUMMARY_COLUMNS)
    if figures:
        designs = _designs(designs)
        fig_prints(out_dir / "fig6_prints.png", rows, designs, prints)
        if masks:
            fig_masks(out_dir / "fig5_masks.png", designs, masks)
        fig_bars(out_dir / "metrics_bars.png", summary)


def printer_pixel_size(params, source) -> float:
    """The DMD pixel size (um) of a calibrated printer model, which the benchmark's
    micrometre metrics need; InputError naming ``source`` when the model has none."""
    px = params.pixel_size_um
    if not px:
        raise InputError(source, "the printer model has no pixel_size_um (the DMD pixel at the sample, in um); "
                                 "the benchmark's micrometre metrics need it")
    return float(px)


def run_benchmark(designs_dir, masks_by_method: dict, out_dir, pixel_size_um: float, printer: Printer,
                  doses=IDENTICAL_DOSES, pv_band: bool = True, figures: bool = True, fiducials: bool = False) -> list[dict]:
    """Print every benchmark mask with ``printer``, score, write metrics.tsv and figures.

    ``masks_by_method``: method -> folder of <design>.png (or dict design -> uint8 mask).
    ``printer(masks, exposures) -> prints``: e.g. ``simulator_printer(params)`` or
    ``virtual_lab_printer(work_dir)``. ``out_dir``: a new folder or an earlier output of this function.
    ``fiducials``: the registration marks on the masks where their designs leave room
    (``benchmark_masks``), as the print job has them: for a printer whose prints are
    registered (``read_registered`` leaves the marks out), not the simulator, whose prints
    would be scored with them.
    """
    designs = _designs(designs_dir)
    masks, exposures = benchmark_masks(designs, masks_by_method, doses, pv_band, fiducials)
    with output_dir(out_dir, command="benchmark simulate", inputs=[designs_dir, *masks_by_method.values()]) as tmp:
        prints = printer(masks, exposures)
        rows = score_prints(prints, designs, pixel_size_um)
        write_results(rows, tmp, designs, prints, masks, figures)
    return rows


# ------------------------------------------------------------------- a real printer

README = """\
Benchmark print job: compensated masks against identical masks
=============================================================

What to do
1. Print every mask in masks/ on the DLP printer, one print per mask, each mask in the
   DMD's design region as for the trial prints (255 = 100 % dose).
   Masks whose name ends in __x090 or __x110 are printed at 90 % or 110 % of the
   exposure in batch.yaml ({x090} s and {x110} s instead of {nominal} s): the PV band
   measures how the print changes with dose drift. All other masks: the nominal exposure.
2. Image every print with the fluorescence microscope as for the trial prints, and save
   the image as images/<same id>.tif (or .png, 8 or 16 bit) beside masks/, so that
   masks/star__ilt.png pairs with images/star__ilt.tif.
3. Fill in batch.yaml (pixel size, exposure, intensity, material, notes).
4. Put this folder into data/prints/<name>/ and list it in the config as the
   benchmark's batch (not as a calibration batch). The workflow registers it like
   every batch and scores it against the designs (unscatter.benchmark.score_measured).

Contents: {n} masks, {designs} designs x ({methods}) x exposures ({exposures}).
Ids: <design>__<method or identical_<grey %>>[__x<exposure %>]; job.tsv lists them.
{marks}"""
MARKS_NOTE = """
{marked} of the {designs} designs' masks carry three registration marks: solid squares at
full grey in three corners of the field, with nothing else near them. Print them as they
are. The registration places each print on its marks, whatever the design (a star or a
grating that maps onto itself turned or shifted, a dim print), and the scoring leaves the
marks' corners out.
"""


def write_print_job(masks_by_method: dict, designs, out_dir, pv_band: bool = True, doses=IDENTICAL_DOSES,
                    batch_meta: dict | None = None, fiducials: bool = BENCHMARK.default.fiducials) -> list[dict]:
    """A print batch without images: masks/<id>.png, batch.yaml to fill in, README.txt, job.tsv
    (``out_dir``: a new folder or an earlier print job). ``fiducials``: the registration
    marks on the masks of every design that leaves room for them (``benchmark_masks``)."""
    sources = [designs, *masks_by_method.values()]
    designs = _designs(designs)
    masks, exposures = benchmark_masks(designs, masks_by_method, doses, pv_band, fiducials)
    with output_dir(out_dir, command="benchmark job", inputs=sources) as tmp:
        return _write_job(masks, designs, masks_by_method, tmp, pv_band, doses, batch_meta)


def _write_job(masks: dict, designs: dict, masks_by_method: dict, out_dir: Path, pv_band: bool, doses,
               batch_meta: dict | None) -> list[dict]:
    # Guan et al. 2022, 'Bioprinting setup': 2.96 um per pixel, 20 s exposure, 20.8 mW/cm2 at grey 255
    meta = dict(pixel_size_um=PAPER_PIXEL_SIZE_UM, exposure_s=20.0, max_intensity_mw_cm2=20.8, material="FILL IN",
                notes="FILL IN: benchmark prints; ids ending __x090/__x110 printed at 90/110 % of exposure_s")
    meta.update(batch_meta or {})
    if pv_band:
        meta["exposure_factors"] = {exposure_token(e): e for e in PV_EXPOSURES}
    rows = []
    for pid, m in masks.items():
        write_png(out_dir / "masks" / f"{pid}.png", m)
        q = parse_print_id(pid)
        rows.append(dict(id=pid, design=q["design"], method=q["method"], mask_dose=q["mask_dose"], exposure=q["exposure"],
                         exposure_s=float(meta["exposure_s"]) * q["exposure"]))
    write_yaml(out_dir / "batch.yaml", meta)
    write_tsv(out_dir / "job.tsv", rows)
    (out_dir / "images").mkdir(exist_ok=True)  # where the microscope images go
    methods = ", ".join(list(masks_by_method) + [label(IDENTICAL, d) for d in doses])
    e0 = float(meta["exposure_s"])
    marked = len({parse_print_id(pid)["design"] for pid, m in masks.items() if carries_marks(m)})
    (out_dir / "README.txt").write_text(README.format(
        x090=f"{0.9 * e0:g}", x110=f"{1.1 * e0:g}", nominal=f"{e0:g}", n=len(masks), designs=len(designs), methods=methods,
        exposures=", ".join(f"{int(round(100 * e))} %" for e in ((1.0,) + (tuple(PV_EXPOSURES) if pv_band else ()))),
        marks=MARKS_NOTE.format(marked=marked, designs=len(designs)) if marked else ""))
    return rows


def score_measured(registered_prints_dir, designs_dir, out_dir, pixel_size_um: float | None = None, figures: bool = True) -> list[dict]:
    """Score a registered benchmark batch (the output of registration) like ``run_benchmark``.

    The pixel size comes from the batch.yaml that registration copies (or is given); the
    masks for the Fig. 5 figure from the batch the prints came from, when found.
    """
    reg = Path(registered_prints_dir)
    if pixel_size_um is None:
        pixel_size_um = read_batch_meta(reg).pixel_size_um
    qc = read_tsv(reg / "qc.tsv") if (reg / "qc.tsv").is_file() else None
    masks = registered_masks(reg, qc) if qc is not None else {}
    prints = read_registered(reg, masks)
    rows = score_prints(prints, designs_dir, pixel_size_um)
    if qc is not None:  # a print that failed registration QC is not a print that failed
        failed = {r["id"] for r in qc if r["status"] == "failed"}
        for row in rows:
            if row["status"] == "no print" and print_id(row["design"], row["method"], row["mask_dose"]) in failed:
                row["status"] = "registration failed"
                log.warning("%s: registration failed QC; not scored", print_id(row["design"], row["method"], row["mask_dose"]))
    write_results(rows, out_dir, designs_dir, prints, masks or None, figures)
    return rows


# ------------------------------------------------------------------------- figures


def _contour_rgb(design: np.ndarray, printed: np.ndarray | None, step: int = 2) -> np.ndarray:
    """The design in grey, the print's contour in green over it; where they differ, the
    missing design red and the excess print blue. Every ``step``-th pixel (a figure cell
    is ~200 px wide), with the contour thickened so it survives."""
    from scipy import ndimage

    rgb = np.zeros(design.shape + (3,), np.uint8)
    rgb[design] = 120
    if printed is not None:
        rgb[design & ~printed] = (210, 50, 50)
        rgb[printed & ~design] = (60, 110, 235)
        rgb[ndimage.binary_dilation(metrics.edges(printed), iterations=step // 2 or 1)] = (60, 230, 60)
    return rgb[::step, ::step]


def fig_prints(path, rows: list[dict], designs: dict, prints: dict) -> None:
    """Like Fig. 6: rows are designs; columns the design, each method, and the identical
    mask at each dose; the print's contour in green over the design (grey)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = sorted({r["design"] for r in rows})
    cols = []
    for r in rows:
        c = (r["method"], r["mask_dose"])
        if c not in cols:
            cols.append(c)
    by = {(r["design"], r["method"], r["mask_dose"]): r for r in rows}
    fig, axes = plt.subplots(len(names), len(cols) + 1, figsize=(1.9 * (len(cols) + 1), 2.0 * len(names)), squeeze=False)
    for i, name in enumerate(names):
        d = designs[name]
        axes[i, 0].imshow(d, cmap="gray", interpolation="nearest")
        axes[i, 0].set_ylabel(name)
        for j, (method, dose) in enumerate(cols, start=1):
            p = prints.get(print_id(name, method, dose))
            ax = axes[i, j]
            ax.imshow(_contour_rgb(d, None if p is None else np.asarray(p, bool)), interpolation="nearest")
            r = by.get((name, method, dose))
            if r is not None and r["status"] == "ok":
                ax.set_xlabel(f"IoU {r['iou']:.3f}, EPE {r['epe_um']:.1f} um", fontsize=7)
            else:
                ax.set_xlabel("no print", fontsize=7)
    axes[0, 0].set_title("design", fontsize=9)
    for j, (method, dose) in enumerate(cols, start=1):
        axes[0, j].set_title(label(method, dose), fontsize=9)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle("Prints (green contour) over the designs (grey); red: design not printed, blue: printed outside the design",
                 fontsize=10)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fig_masks(path, designs: dict, masks: dict) -> None:
    """Like Fig. 5(e): each compensated mask in grey with its design's contour in red."""
    import matplotlib
    from scipy import ndimage

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = []
    for pid in masks:
        q = parse_print_id(pid)
        if q["method"] != IDENTICAL and q["exposure"] == 1.0 and q["method"] not in methods:
            methods.append(q["method"])
    names = sorted(designs)
    if not methods:
        return
    fig, axes = plt.subplots(len(names), len(methods), figsize=(2.2 * len(methods), 2.2 * len(names)), squeeze=False)
    for i, name in enumerate(names):
        for j, method in enumerate(methods):
            ax = axes[i, j]
            m = masks.get(print_id(name, method))
            if m is not None:
                rgb = np.repeat(np.asarray(m, np.uint8)[..., None], 3, axis=2)
                rgb[ndimage.binary_dilation(metrics.edges(designs[name]))] = (230, 30, 30)
                ax.imshow(rgb, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(f"{method} mask", fontsize=9)
            if j == 0:
                ax.set_ylabel(name)
    fig.suptitle("Compensated masks (grey) and the design's contour (red)", fontsize=10)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fig_bars(path, summary: list[dict]) -> None:
    """Mean IoU, pixel error, EPE and PV band per method and identical dose: over the
    designs that every full-grey mask printed (``common_*``) where ``compared_on_common``,
    so that the bars compare the masks on the same designs (n/a for a mask without a print
    of one of them)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [s["variant"] for s in summary]
    colours = ["tab:blue" if s["method"] != IDENTICAL else "tab:gray" for s in summary]
    common = compared_on_common(summary)
    prefix = "common_" if common else ""
    fig, axes = plt.subplots(1, 4, figsize=(14, 3.6))
    for ax, (key, name) in zip(axes, [("iou", "IoU (higher is better)"), ("pixel_error", "pixel error"),
                                      ("epe_um", "EPE (um)"), ("pv_band_um", "PV band (um)")]):
        vals = [s[prefix + key] for s in summary]
        bars = ax.bar(range(len(vals)), [0 if (v is None or np.isnan(v)) else v for v in vals], color=colours)
        ax.bar_label(bars, labels=["n/a" if np.isnan(v) else f"{v:.3g}" for v in vals], fontsize=7)
        ax.set_xticks(range(len(vals)))
        ax.set_xticklabels(labels, rotation=45, ha="right", fontsize=8)
        ax.set_title(name, fontsize=9)
        if key == "iou":
            lo = min([v for v in vals if not np.isnan(v)] or [0])
            ax.set_ylim(max(0.0, lo - 0.05), 1.03)
            for i, v in enumerate(vals):  # a missing value's label sits at 0, below the axis here
                if np.isnan(v):
                    ax.text(i, max(0.0, lo - 0.05), "n/a", ha="center", va="bottom", fontsize=7)
    lacking = [s["variant"] for s in summary if s["mask_dose"] == FULL_GREY and s["no_print"]]
    over = (f"the {summary[0]['common_designs']} designs that every full-grey mask printed"
            + (f" (no print of a design: {', '.join(lacking)}; summary.tsv's no_print)" if lacking else "")
            if common else "the designs")
    fig.suptitle(f"Mean over {over}: compensated (blue) vs identical masks (grey)", fontsize=9)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
