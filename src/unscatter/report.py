"""One self-contained HTML page of a run: the figures and tables of every stage.

Every table says the file under the results folder it was read from, so each number in
the report can be traced to its file; the figures are embedded (PNG, base64), so the
page can be mailed or archived alone. Stages that have not run are listed as missing,
not left out silently. Reads only the stages' outputs (never the virtual lab's truth).
"""

from __future__ import annotations

import base64
import datetime
import html
import math
from pathlib import Path

from . import __version__
from .io import read_tsv, read_yaml

CSS = """
body { font-family: system-ui, sans-serif; max-width: 1150px; margin: 2em auto; color: #222; }
h1 { border-bottom: 2px solid #446; } h2 { margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: .5em 0 1em; font-size: 13px; }
td, th { border: 1px solid #ccc; padding: 2px 7px; text-align: right; }
th { background: #eef; } td:first-child, th:first-child { text-align: left; }
.src { color: #777; font-size: 12px; font-family: monospace; }
.missing { color: #a33; } img { max-width: 100%; border: 1px solid #ddd; margin: .3em 0; }
figure { margin: 1em 0; } figcaption { font-size: 13px; color: #444; }
"""


def _fmt(v) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return "n/a"
        return f"{v:.4g}"
    try:
        f = float(v)
    except (TypeError, ValueError):
        return html.escape(str(v))
    if str(v).strip().lower() in ("nan", ""):
        return "n/a" if str(v).strip() else ""
    return f"{f:.4g}" if "." in str(v) or "e" in str(v).lower() else html.escape(str(v))


class Page:
    """The report under construction: sections of HTML, paths relative to the results."""

    def __init__(self, results: Path):
        self.results = Path(results)
        self.parts: list[str] = []
        self.missing: list[str] = []

    def rel(self, path: Path) -> str:
        """The path as the user knows it: the results folder as given, then the file."""
        try:
            return (self.results / Path(path).resolve().relative_to(self.results.resolve())).as_posix()
        except ValueError:
            return str(path)

    def h(self, level: int, text: str) -> None:
        self.parts.append(f"<h{level}>{html.escape(text)}</h{level}>")

    def p(self, text: str, raw: bool = False) -> None:
        self.parts.append(f"<p>{text if raw else html.escape(text)}</p>")

    def source(self, path: Path) -> None:
        self.parts.append(f'<div class="src">from {html.escape(self.rel(path))}</div>')

    def table(self, rows: list[dict], path: Path, columns: list[str] | None = None, limit: int = 60) -> None:
        if not rows:
            self.p(f"{self.rel(path)} is empty.")
            return
        cols = columns or list(rows[0])
        cols = [c for c in cols if c in rows[0]]
        out = ["<table><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in cols) + "</tr>"]
        for r in rows[:limit]:
            out.append("<tr>" + "".join(f"<td>{_fmt(r.get(c, ''))}</td>" for c in cols) + "</tr>")
        out.append("</table>")
        self.parts.append("".join(out))
        note = f" (first {limit} of {len(rows)} rows)" if len(rows) > limit else ""
        self.parts.append(f'<div class="src">from {html.escape(self.rel(path))}{note}</div>')

    def tsv(self, path: Path, columns: list[str] | None = None, limit: int = 60) -> list[dict]:
        if not Path(path).is_file():
            self.missing.append(self.rel(path))
            self.parts.append(f'<p class="missing">missing: {html.escape(self.rel(path))}</p>')
            return []
        rows = read_tsv(path)
        self.table(rows, path, columns, limit)
        return rows

    def image(self, path: Path, caption: str) -> None:
        path = Path(path)
        if not path.is_file():
            self.missing.append(self.rel(path))
            self.parts.append(f'<p class="missing">missing figure: {html.escape(self.rel(path))}</p>')
            return
        data = base64.b64encode(path.read_bytes()).decode()
        self.parts.append(f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(path.name)}">'
                          f"<figcaption>{html.escape(caption)} <span class=\"src\">{html.escape(self.rel(path))}</span>"
                          "</figcaption></figure>")

    def html(self, title: str) -> str:
        stamp = datetime.datetime.now().isoformat(timespec="seconds")
        miss = ""
        if self.missing:
            miss = ("<h2>Missing outputs</h2><ul>" + "".join(f"<li class=\"missing\">{html.escape(m)}</li>" for m in self.missing)
                    + "</ul>")
        return (f"<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
                f"<style>{CSS}</style></head><body><h1>{html.escape(title)}</h1>"
                f"<p class=\"src\">unscatter {__version__}, {stamp}; results folder {html.escape(str(self.results))}</p>"
                + "".join(self.parts) + miss + "</body></html>")


def _mean(rows: list[dict], key: str) -> float:
    vals = []
    for r in rows:
        try:
            v = float(r[key])
        except (KeyError, TypeError, ValueError):
            continue
        if not math.isnan(v):
            vals.append(v)
    return sum(vals) / len(vals) if vals else math.nan


def _registration(page: Page, prints_dir: Path, note: str = "") -> None:
    name = prints_dir.name
    page.h(3, f"Batch {name}{note}")
    qc = prints_dir / "qc.tsv"
    if not qc.is_file():
        page.tsv(qc)
        return
    rows = read_tsv(qc)
    n = {s: sum(r["status"] == s for r in rows) for s in ("ok", "empty", "failed")}
    ok = [r for r in rows if r["status"] == "ok"]
    page.p(f"{len(rows)} prints: {n['ok']} ok, {n['empty']} empty, {n['failed']} failed QC (never used). "
           f"Mean registration score {_mean(ok, 'score'):.4f}; mean rotation |{_mean([dict(a=abs(float(r['rotation_deg']))) for r in ok], 'a'):.2f}| deg, "
           f"scale {_mean(ok, 'scale'):.3f}; one threshold for the batch: {rows[0].get('threshold', 'n/a')}.")
    page.table(rows, qc, ["id", "status", "reason", "rotation_deg", "scale", "shift_x", "shift_y", "score", "threshold",
                          "solid_fraction"], limit=40)
    page.image(prints_dir / "overlays.png", "Registered images with the mask's contour over them (quality control).")


def _params_table(page: Page, path: Path) -> None:
    """A params file's equation and its parameters (value, spread, bounds)."""
    d = read_yaml(path)
    rows = [dict(parameter=k, value=v.get("value"), std=v.get("std", ""), lower=v.get("lower"), upper=v.get("upper"),
                 fixed=v.get("fixed"), unit=v.get("unit", "")) for k, v in d.get("parameters", {}).items()]
    page.p(str(d.get("equation", "")))
    page.table(rows, path)


def _layers(page: Page, layers: Path) -> None:
    """The multi-layer stages: z-stack registration, depth calibration, compensation,
    and the printed benchmark."""
    page.h(2, "7. Multi-layer (3-D) prints")
    for qc in sorted((layers / "prints").glob("*/qc.tsv")):
        page.h(3, f"z-stacks registered: {qc.parent.name}")
        rows = page.tsv(qc, ["id", "status", "reason", "rotation_deg", "scale", "bottom_um", "axial_sigma_um", "axial_r2"])
        if rows:
            page.p(f"{sum(r['status'] == 'ok' for r in rows)} of {len(rows)} z-stacks ok; the others failed QC and are "
                   "never used.")
    cal = layers / "calibration"
    page.h(3, "Depth calibration")
    if (cal / "summary.yaml").is_file():
        sm = read_yaml(cal / "summary.yaml")
        v = sm.get("values", {})
        sd = sm.get("spread") or {}
        page.p("Fitted: " + ", ".join(f"{k} {_fmt(float(x))}" + (f" ± {_fmt(float(sd[k]))}" if k in sd else "")
                                      for k, x in v.items())
               + (f" (± one standard deviation over {sm.get('bootstrap')} bootstrap resamples of the prints)" if sd else "")
               + f"; held-out voxel IoU {_fmt(sm.get('heldout_voxel_iou'))} on {sm.get('held_out')} prints "
               f"(fit {_fmt(sm.get('fit_voxel_iou'))}).")
        page.source(cal / "summary.yaml")
    page.tsv(cal / "fit.tsv")
    page.h(3, "Compensated layer masks (the model's prediction)")
    page.tsv(layers / "compensated" / "compensation3d.tsv")
    page.h(3, "Printed benchmark: compensated vs identical layer masks at the best uniform dose")
    page.tsv(layers / "benchmark" / "scores" / "metrics.tsv")
    page.image(layers / "benchmark" / "scores" / "sections.png",
               "xz and yz cross-sections (top up) of the registered voxel prints; red: the design's outline.")


def build_report(results_dir, out_html, title: str = "unscatter run report", benchmark_batches=(),
                 models: dict | None = None) -> Path:
    """Write the report of the run under ``results_dir`` to ``out_html``; returns its path.

    ``benchmark_batches``: names of the registered batches that are benchmark prints
    (listed after the trial batches, marked as not calibrated on). ``models``: which
    printer model the networks and masks used and which one the benchmark compares it
    with: ``{"model": "selected", "other": "base"}`` (the workflow's 'model' setting).
    Lists the outputs it expected and did not find under 'Missing outputs'.
    """
    results = Path(results_dir)
    page = Page(results)

    page.h(2, "1. Trial prints: registration and thresholding")
    batches = sorted(p for p in (results / "prints").glob("*") if p.is_dir()) if (results / "prints").is_dir() else []
    if not batches:
        page.p("No registered batches.")
    for b in sorted(batches, key=lambda b: (b.name in benchmark_batches, b.name)):
        _registration(page, b, " (benchmark prints: scored, not calibrated on)" if b.name in benchmark_batches else "")

    page.h(2, "2. Printer simulator calibration (Eq. 1, DEAP)")
    for cal in sorted(p for p in (results / "calibration").glob("*") if p.is_dir()) if (results / "calibration").is_dir() else []:
        page.h(3, f"Model {cal.name}")
        if (cal / "params.yaml").is_file():
            _params_table(page, cal / "params.yaml")
            for w in read_yaml(cal / "params.yaml").get("warnings") or []:
                page.p(f"Warning: {w}")
        cv = cal / "cv.tsv"
        if cv.is_file():
            rows = read_tsv(cv)
            base = (f" The mask itself (printed where its grey level reaches a threshold chosen on the training prints), "
                    f"no model: held-out IoU {_mean(rows, 'mask_iou'):.4f}." if rows and "mask_iou" in rows[0] else "")
            page.p(f"Held-out (k-fold) IoU {_mean(rows, 'iou'):.4f}, pixel error {_mean(rows, 'pixel_error'):.4f} "
                   f"over {len(rows)} prints (in-sample IoU {_mean(rows, 'in_sample_iou'):.4f}).{base}")
        page.tsv(cv, limit=40)
        page.image(cal / "fit.png", "Measured vs simulated prints.")

    diag = results / "diagnosis"
    if diag.is_dir():
        page.h(2, "3. Residual diagnosis: effects the model lacks")
        if (diag / "model.yaml").is_file():
            d = read_yaml(diag / "model.yaml")
            page.p(f"Accepted effects: {', '.join(d.get('effects') or []) or 'none'}; unexplained residual: "
                   f"{d.get('unexplained_residual')}. The selected model {d.get('model')}:")
            _params_table(page, diag / "model.yaml")
        page.tsv(diag / "before_after.tsv")
        page.tsv(diag / "ranking.tsv")
        for png in sorted(diag.glob("*.png")):
            page.image(png, png.stem.replace("_", " "))

    page.h(2, "4. Augmentation and U-Net training (Eq. 2)")
    for z in sorted((results / "augment").glob("*.zarr")) if (results / "augment").is_dir() else []:
        attrs = z / "zarr.json"
        if attrs.is_file():
            import json

            a = json.loads(attrs.read_text()).get("attributes", {})
            fam = ", ".join(f"{k} {v}" for k, v in (a.get("families") or {}).items())
            page.p(f"{z.name}: {a.get('count', '?')} pairs of {a.get('size', '?')} px ({a.get('n_train', '?')} train / "
                   f"{a.get('n_test', '?')} test), seed {a.get('seed', '?')}; families: {fam}; "
                   f"mean print fraction {a.get('print_fraction', math.nan):.3f}, empty prints {a.get('empty_prints', '?')}.")
            page.source(attrs)
    for t in sorted(p for p in (results / "train").glob("*") if p.is_dir() and not p.name.startswith(".")) if (results / "train").is_dir() else []:
        page.h(3, f"Networks for model {t.name}")
        page.image(t / "curves.png", "Every term of Eq. 2, train and test, per epoch.")
        page.tsv(t / "eval.tsv")

    page.h(2, "5. Compensated masks")
    comp = results / "compensated"
    for model in sorted(p for p in comp.glob("*") if p.is_dir()) if comp.is_dir() else []:
        for m in sorted(p for p in model.glob("*") if p.is_dir()):
            page.h(3, f"{m.name} (model {model.name})")
            page.tsv(m / "compensation.tsv", ["design", "method", "seconds", "mean_grey", "offset_row", "offset_col"])

    page.h(2, "6. Benchmark: compensated vs identical masks")
    bench = results / "benchmark"
    if models:
        page.p(f"Masks named by their method (nn, ilt, nn+ilt) were computed with the {models['model']} printer model; "
               f"<method>_{models['other']} with the {models['other']} model, for comparison (the selected model is the "
               "diagnosis's: the base model plus the effects it accepted).")
    if (bench / "summary.tsv").is_file():
        page.h(3, "Printed (registered and thresholded like the trial prints)")
        page.tsv(bench / "summary.tsv")
        page.image(bench / "metrics_bars.png", "Mean metrics per mask.")
        page.image(bench / "fig6_prints.png", "Like Fig. 6: print contours (green) over the designs; red: missing, blue: excess.")
        page.image(bench / "fig5_masks.png", "Like Fig. 5: the masks with the design's contour.")
        page.tsv(bench / "metrics.tsv", limit=80)
    elif (bench / "print_job").is_dir():
        page.p(f"Not printed yet: the print job is in {page.rel(bench / 'print_job')} (README.txt says how to print it).")
    if (bench / "simulated").is_dir():
        page.h(3, "On the calibrated simulator (the model's prediction)")
        page.tsv(bench / "simulated" / "summary.tsv")
        page.image(bench / "simulated" / "metrics_bars.png", "Mean metrics per mask, simulated prints.")

    layers = results / "layers"
    if layers.is_dir():
        _layers(page, layers)

    runtimes = results / "benchmarks"
    if runtimes.is_dir():
        page.h(2, "8. Run times")
        rows = []
        for f in sorted(runtimes.rglob("*.tsv")):
            r = read_tsv(f)
            if r:
                rows.append(dict(job=f.relative_to(runtimes).with_suffix("").as_posix(), seconds=r[0].get("s", ""),
                                 max_rss_mb=r[0].get("max_rss", "")))
        page.table(rows, runtimes)

    out = Path(out_html)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(page.html(title))
    return out
