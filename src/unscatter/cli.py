"""The `unscatter` command: one subcommand per stage, each calling the package function
that the Snakemake rule calls too. Heavy imports happen inside the commands."""

from __future__ import annotations

import logging
import math
import sys
from pathlib import Path

import click

from . import __version__
from . import settings as S
from .io import InputError, check_png_name


def _error_line(exc: Exception) -> str:
    """One line for bad input (InputError: file and problem) or a file system error
    (OSError: the path and what the system said, e.g. a read-only folder)."""
    if isinstance(exc, OSError) and exc.filename is not None:
        text = f"{exc.filename}: {exc.strerror or exc}"
    else:
        text = str(exc)
    return " ".join(text.split())


class _Group(click.Group):
    """Bad input and file system errors end with one line (`error: file: problem`) and
    exit code 2; with -v the traceback is shown instead."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (InputError, OSError) as exc:
            if ctx.find_root().params.get("verbose"):
                raise
            click.echo(f"error: {_error_line(exc)}", err=True)
            ctx.exit(2)


@click.group(cls=_Group)
@click.version_option(__version__)
@click.option("-v", "--verbose", is_flag=True, help="Debug logging, and tracebacks instead of one-line errors.")
def main(verbose):
    """unscatter: compensate cell-induced light scattering in DLP bioprinting."""
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")


# ------------------------------------------------------------------ options
def _click_type(s: S.Setting):
    """The click type that enforces a setting's bounds or choices."""
    if s.choices is not None:
        return click.Choice(list(s.choices))
    r = s.range
    if s.kind == "integer":
        if r is None:
            return click.INT
        return click.IntRange(None if math.isinf(r.lo) else int(r.lo), None if math.isinf(r.hi) else int(r.hi),
                              min_open=r.lo_open, max_open=r.hi_open)
    if s.kind == "number":
        if r is None:
            return click.FLOAT
        return click.FloatRange(None if math.isinf(r.lo) else r.lo, None if math.isinf(r.hi) else r.hi,
                                min_open=r.lo_open, max_open=r.hi_open)
    return click.STRING


def option(stage: S.Stage, name: str, *decls: str, **kw):
    """A click option made from ``stage``'s setting ``name`` (unscatter.settings): its
    default, its help and a type that enforces its bounds. ``kw`` adds to or replaces
    what click gets (e.g. ``default=None`` for an option that overrides a file)."""
    s = stage[name]
    flag = "--" + name.replace("_", "-")
    if s.kind == "boolean":
        decls = decls or (f"{flag}/--no-{flag[2:]}",)
    else:
        decls = decls or (flag,)
        kw.setdefault("type", _click_type(s))
    kw.setdefault("default", s.default)
    kw.setdefault("show_default", s.default is not None)
    kw.setdefault("help", s.description)
    return click.option(*decls, name, **kw)


# ----------------------------------------------------------------------- masks
@main.group(cls=_Group)
def masks():
    """Mask sets."""


@masks.command("trial")
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@option(S.TRIAL_MASKS, "count")
@option(S.TRIAL_MASKS, "seed")
@option(S.TRIAL_MASKS, "size")
@option(S.TRIAL_MASKS, "paper_fiducials", "--fiducials/--no-fiducials")
def masks_trial(out_dir, count, seed, size, paper_fiducials):
    """The paper's trial masks: checkerboards, rectangles, circles (8-bit PNG)."""
    from .masks import write_trial_masks

    paths = write_trial_masks(out_dir, count=count, seed=seed, size=size, fiducials=paper_fiducials)
    click.echo(f"wrote {len(paths)} trial masks to {out_dir}")


@masks.command("design")
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@option(S.TRIAL_MASKS, "count")
@click.option("--model", "model", type=click.Path(exists=True, path_type=Path),
              help="Sequential design: a calibration's params.yaml (or folder) or a diagnosis folder; the next "
                   "prints go where its fit is least sure. Default: before any print, a broad prior.")
@click.option("--prints", "prints", multiple=True, type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="Registration folders of prints already made (repeat): the design complements them.")
@option(S.TRIAL_MASKS, "pool")
@option(S.TRIAL_MASKS, "draws")
@option(S.TRIAL_MASKS, "seed")
@option(S.TRIAL_MASKS, "size")
@option(S.TRIAL_MASKS, "fiducials")
@option(S.TRIAL_MASKS, "criterion")
@click.option("--progress/--no-progress", default=True, show_default=True)
def masks_design(out_dir, count, model, prints, pool, draws, seed, size, fiducials, criterion, progress):
    """Trial masks designed to teach the printer model the most (D-optimal, and by default
    each library effect's evidence spread over the prints, as the diagnosis's paired test
    needs it; --criterion d for D-optimality alone, discrimination to tell the library's
    effects apart instead; masks, design.tsv, parameters.tsv with the predicted parameter
    spread against random paper masks, separation.tsv and paired.tsv, design.png)."""
    _passive_threads()
    from .design import design_masks, write_design

    if count > pool:
        raise click.BadParameter(f"{count} masks cannot be chosen from a pool of {pool}", param_hint="--count")
    r = design_masks(count, model=model, prints=list(prints) or None, pool=pool, draws=draws, seed=seed, size=size,
                     fiducials=fiducials, criterion=criterion, progress=progress)
    write_design(out_dir, r, inputs=[p for p in [model, *prints] if p is not None])
    paper = r.get("criterion_paper")
    click.echo(f"designed {count} masks from {pool} candidates in {r['seconds']:.0f} s: criterion {r['criterion']:.1f}"
               + (f" (random paper masks: {paper:.1f})" if paper is not None else "") + f" -> {out_dir}")


@masks.command("trial3d")
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@option(S.LAYERS, "count")
@option(S.LAYERS, "layers")
@option(S.LAYERS, "size")
@option(S.LAYERS, "seed")
def masks_trial3d(out_dir, count, layers, size, seed):
    """3-D trial prints (bridges, channels, towers, stairs): OUT_DIR/<id>/NNN.png, bottom first."""
    from .calibration3d import write_trial_masks3d

    paths = write_trial_masks3d(out_dir, count=count, layers=layers, size=size, seed=seed)
    click.echo(f"wrote {len(paths)} 3-D trial prints of {layers} layers to {out_dir}")


# ------------------------------------------------------------------------- lab
@main.group(cls=_Group)
def lab():
    """The virtual lab (printer + microscope)."""


def _lab_options(fn):
    """MASKS OUT_BATCH, --lab-config, --truth-dir and --seed of the lab's print commands."""
    for deco in reversed((
        click.argument("mask_dir", type=click.Path(exists=True, file_okay=False, path_type=Path)),
        click.argument("out_batch", type=click.Path(file_okay=False, path_type=Path)),
        click.option("--lab-config", type=click.Path(exists=True, dir_okay=False, path_type=Path),
                     help="Overrides of the lab's defaults (YAML)."),
        click.option("--truth-dir", type=click.Path(file_okay=False, path_type=Path),
                     help="Where the truth goes (default OUT_BATCH.truth)."),
        option(S.LAB, "seed", default=None, help="Seed of the lab's randomness (default: the lab config's)."),
    )):
        fn = deco(fn)
    return fn


@lab.command("print")
@_lab_options
@click.option("--job", "job_tsv", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="A print job's job.tsv (columns id, exposure): print each mask at that factor of the nominal exposure.")
def lab_print(mask_dir, out_batch, lab_config, truth_dir, seed, job_tsv):
    """Print every mask of MASK_DIR on the virtual lab; write a batch in the data contract."""
    from .lab import print_batch, read_job

    exposures = read_job(job_tsv) if job_tsv else None
    rows = print_batch(mask_dir, out_batch, lab_config=lab_config, truth_dir=truth_dir, seed=seed, exposures=exposures,
                       inputs=[job_tsv] if job_tsv else ())
    click.echo(f"printed and imaged {len(rows)} masks into {out_batch}")


@lab.command("print3d")
@_lab_options
def lab_print3d(mask_dir, out_batch, lab_config, truth_dir, seed):
    """Print every multi-layer mask folder MASK_DIR/<id>/ (layer PNGs, bottom first) on the
    virtual lab and image it as a confocal z-stack: a multi-layer batch."""
    from .lab import print_layers

    rows = print_layers(mask_dir, out_batch, lab_config=lab_config, truth_dir=truth_dir, seed=seed)
    click.echo(f"printed and imaged {len(rows)} multi-layer prints into {out_batch}")


# -------------------------------------------------------------------- register
@main.command("register")
@click.argument("batch_dir", type=click.Path(file_okay=False, path_type=Path))
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@option(S.REGISTRATION, "mode")
@option(S.REGISTRATION, "level")
@option(S.REGISTRATION, "min_score")
@option(S.REGISTRATION, "skip_failed")
def register(batch_dir, out_dir, mode, level, min_score, skip_failed):
    """Register and threshold the microscope images of a print batch to mask coordinates."""
    from .imaging import RegistrationError, register_batch

    try:
        rows = register_batch(batch_dir, out_dir, mode=mode, level=level, min_score=min_score, skip_failed=skip_failed)
    except RegistrationError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(3)
    n = {s: sum(r["status"] == s for r in rows) for s in ("ok", "empty", "failed")}
    click.echo(f"registered {len(rows)} prints: {n['ok']} ok, {n['empty']} empty, {n['failed']} failed -> {out_dir}")


@main.command("register3d")
@click.argument("batch_dir", type=click.Path(file_okay=False, path_type=Path))
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@option(S.REGISTRATION, "level")
@option(S.REGISTRATION, "skip_failed")
def register3d(batch_dir, out_dir, level, skip_failed):
    """Register the confocal z-stacks of a multi-layer batch to their layer masks (pose and
    z offset) and threshold them into voxel prints (prints/<id>/NNN.png, qc.tsv, overlays)."""
    from .imaging import RegistrationError, register_stacks

    try:
        rows = register_stacks(batch_dir, out_dir, level=level, skip_failed=skip_failed)
    except RegistrationError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(3)
    n = {s: sum(r["status"] == s for r in rows) for s in ("ok", "empty", "failed")}
    click.echo(f"registered {len(rows)} z-stacks: {n['ok']} ok, {n['empty']} empty, {n['failed']} failed -> {out_dir}")


# ------------------------------------------------------------------- calibrate
def _bounds(ctx, param, value):
    out = {}
    for item in value:
        try:
            name, rng = item.split("=", 1)
            lo, hi = (float(x) for x in rng.split(","))
        except ValueError:
            raise click.BadParameter(f"{item!r}: use NAME=LOWER,UPPER, e.g. sigma_px=0.5,10") from None
        out[name.strip()] = (lo, hi)
    return out or None


@main.command("calibrate")
@click.argument("prints_dirs", nargs=-1, required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Output folder.")
@option(S.CALIBRATION, "model")
@option(S.CALIBRATION, "seed")
@option(S.CALIBRATION, "population")
@option(S.CALIBRATION, "generations")
@click.option("--bounds", multiple=True, callback=_bounds, metavar="NAME=LO,HI", help="Search bounds of a parameter (repeatable).")
@option(S.CALIBRATION, "free_c0")
@option(S.CALIBRATION, "objective")
@option(S.CALIBRATION, "refine")
@option(S.CALIBRATION, "folds")
@option(S.CALIBRATION, "bootstrap")
@option(S.CALIBRATION, "measurement")
@click.option("--device", default=None, help="torch device (default: cuda if available, else cpu).")
@option(S.CALIBRATION, "threads")
@option(S.CALIBRATION, "workers")
def calibrate_cmd(prints_dirs, out_dir, model, seed, population, generations, bounds, free_c0, objective, refine, folds,
                  bootstrap, measurement, device, threads, workers):
    """Calibrate the printer simulator on registered prints (PRINTS_DIR: registration outputs)."""
    import warnings

    from .calibration import calibrate
    from .model import default_params

    try:
        default_params(model, bounds=bounds)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--bounds") from None

    with warnings.catch_warnings():  # the flags are echoed below, once, without a source line
        warnings.simplefilter("ignore", UserWarning)
        p = calibrate(list(prints_dirs), out_dir, model=model, seed=seed, population=population, generations=generations,
                      bounds=bounds, free_c0=free_c0, objective=objective, refine=refine, folds=folds,
                      bootstrap=bootstrap, measurement=measurement, device=device, threads=threads,
                      workers=workers)
    v, val = p.values, p.info.get("validation", {})
    msg = ", ".join(f"{k}={v[k]:.4g}" for k in p.free)
    heldout = f", held-out IoU {val['heldout_iou_mean']:.4f}" if val.get("heldout_iou_mean") is not None else ""
    if val.get("mask_baseline"):
        heldout += f" (pooled {val['heldout_iou_pooled']:.4f}; the mask itself {val['mask_baseline']['heldout_iou_pooled']:.4f})"
    click.echo(f"calibrated {model} on {p.info['data']['prints']} prints: {msg}; objective {p.info['objective']['value']:.5f}"
               f"{heldout} -> {out_dir / 'params.yaml'}")
    for w in p.info.get("warnings", []):
        click.echo(f"warning: {w}", err=True)


@main.command("calibrate3d")
@click.argument("prints_dirs", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--params", "params_path", type=click.Path(exists=True, path_type=Path), required=True,
              help="The calibrated 2-D model (params.yaml, or its calibration or diagnosis folder).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Output folder.")
@click.option("--free", default=",".join(S.LAYERS.default.free), show_default=True,
              help=S.LAYERS["free"].description + " Comma-separated; empty: none.")
@option(S.LAYERS, "bootstrap")
def calibrate3d_cmd(prints_dirs, params_path, out_dir, free, bootstrap):
    """Calibrate the depth parameters on registered voxel prints (PRINTS_DIRS: one or more
    folders from `unscatter register3d`, of one layer thickness)."""
    from .calibration3d import calibrate3d

    names = [f.strip() for f in free.split(",") if f.strip()]
    try:
        S.LAYERS.check("free", names)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--free") from None
    r = calibrate3d(list(prints_dirs), params_path, out_dir, free2d=tuple(names), bootstrap=bootstrap)
    v, sd = r["values"], r["spread"] or {}

    def value(k, fmt, unit=""):
        return f"{v[k]:{fmt}}" + (f" +- {sd[k]:{fmt}}" if k in sd else "") + unit

    held = f", held-out voxel IoU {r['heldout_voxel_iou']:.4f}" if r["heldout_voxel_iou"] is not None else ""
    click.echo(f"calibrated on {r['prints'] - r['held_out']} prints: att_length {value('att_length_um', '.1f', ' um')}, "
               f"diffusion {value('diffusion_um', '.3g', ' um')}" + "".join(f", {k} {value(k, '.4g')}" for k in names)
               + f"{held} -> {out_dir}")


# -------------------------------------------------------------------- simulate
@main.command("simulate")
@click.argument("params", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("mask_dir", type=click.Path(file_okay=False, path_type=Path))
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--device", default=None, help="torch device (default: cuda if available, else cpu).")
def simulate_cmd(params, mask_dir, out_dir, device):
    """Simulated binary prints (0/255 <id>.png) of every mask in MASK_DIR under PARAMS (params.yaml)."""
    from .calibration import simulate_dir

    paths = simulate_dir(params, mask_dir, out_dir, device=device)
    click.echo(f"simulated {len(paths)} prints -> {out_dir}")


# ------------------------------------------------------- augment, train, compensate
def _passive_threads():
    """Idle OpenMP threads sleep instead of spinning: on a machine shared with other jobs,
    spinning torch threads slow training many times over. Effective before torch loads."""
    import os

    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _families(values):
    """--family NAME or NAME=WEIGHT, repeated -> None (all), or {name: weight}."""
    if not values:
        return None
    out = {}
    for v in values:
        name, _, w = v.partition("=")
        try:
            out[name] = float(w) if w else 1.0
        except ValueError:
            raise click.BadParameter(f"{v!r}: the weight must be a number", param_hint="--family") from None
    return out


@main.command("augment")
@click.argument("model_params", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("out_zarr", type=click.Path(file_okay=False, path_type=Path))
@option(S.AUGMENTATION, "count", default=S.PRESET_PAIRS["default"], show_default=True,
        help=f"Mask/print pairs (what the default training preset is sized for; paper: {S.PRESET_PAIRS['paper']}).")
@option(S.AUGMENTATION, "seed")
@option(S.AUGMENTATION, "size")
@click.option("--family", "families", multiple=True, metavar="NAME[=WEIGHT]",
              help="Augmentation family and its share (repeat; default: all seven, equal shares).")
@option(S.AUGMENTATION, "test_fraction")
@option(S.AUGMENTATION, "workers")
@click.option("--progress/--no-progress", default=True, show_default=True)
def augment_cmd(model_params, out_zarr, count, seed, size, families, test_fraction, workers, progress):
    """Augmentation masks and their simulated prints under MODEL_PARAMS (params.yaml) -> OUT_ZARR."""
    _passive_threads()
    from .augment import augment

    try:
        s = augment(model_params, out_zarr, count=count, seed=seed, families=_families(families), size=size,
                    test_fraction=test_fraction, workers=workers, progress=progress)
    except ValueError as exc:
        if isinstance(exc, InputError):
            raise
        raise click.UsageError(str(exc)) from None
    click.echo(f"wrote {s['count']} pairs ({size}x{size}; {s['n_train']} train / {s['n_test']} test) in "
               f"{s['elapsed_s']:.1f} s -> {out_zarr}")


@main.command("train")
@click.argument("dataset", type=click.Path(file_okay=False, path_type=Path))
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@option(S.TRAINING, "preset")
@option(S.TRAINING, "epochs")
@option(S.TRAINING, "width")
@option(S.TRAINING, "scale")
@option(S.TRAINING, "crop")
@option(S.TRAINING, "coords")
@option(S.TRAINING, "lr")
@option(S.TRAINING, "batch")
@option(S.TRAINING, "seed")
@option(S.TRAINING, "max_train")
@click.option("--device", default=None, help="torch device (default: cuda if available, else cpu).")
@option(S.TRAINING, "threads")
@click.option("--resume/--no-resume", default=True, show_default=True, help="Continue from OUT_DIR/checkpoint.pt.")
@click.option("--progress/--no-progress", default=True, show_default=True)
def train_cmd(dataset, out_dir, preset, epochs, width, scale, crop, coords, lr, batch, seed, max_train, device,
              threads, resume, progress):
    """Train the master and slave U-Nets on DATASET (an augmentation Zarr) into OUT_DIR.

    The loss is Eq. 2 of the paper; OUT_DIR gets master.pt, slave.pt, checkpoint.pt,
    log.tsv, curves.png and eval.tsv.
    """
    _passive_threads()
    from .training import train

    settings = dict(epochs=epochs, width=width, scale=scale, crop=crop, coords=coords, lr=lr, batch=batch, seed=seed,
                    max_train=max_train)
    try:
        r = train(dataset, out_dir, preset=preset, settings={k: v for k, v in settings.items() if v is not None},
                  resume=resume, device=device, threads=threads, progress=progress)
    except ValueError as exc:
        if isinstance(exc, InputError):
            raise
        raise click.UsageError(str(exc)) from None
    ev = {row["method"]: row for row in r["eval"] if row["family"] == "all"}
    msg = ", ".join(f"{m} IoU {ev[m]['iou']:.4f}" for m in ("slave", "master", "identity") if m in ev)
    click.echo(f"trained {r['epochs']} epochs ({sum(r['seconds_per_epoch']):.0f} s this run): {msg} -> {out_dir}")


def _png_name(ctx, param, value):
    """A mask file to write must be a PNG (a lossy format would change the dose)."""
    if value is not None:
        try:
            check_png_name(value)
        except InputError as exc:
            raise click.BadParameter(str(exc)) from None
    return value


@main.command("compensate")
@click.argument("design", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--model", "model_dir", type=click.Path(path_type=Path), required=True,
              help="nn, nn+ilt: a training folder (master.pt) from `unscatter train`; "
                   "ilt: the calibrated params.yaml or its calibration folder.")
@click.option("--params", "params_path", type=click.Path(path_type=Path),
              help="nn+ilt: the calibrated params.yaml (or its folder) for the ILT refinement.")
@click.option("--method", type=click.Choice(list(S.METHODS)), default="nn", show_default=True)
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True, callback=_png_name,
              help="Mask PNG to write.")
@click.option("--frame", "frame_png", type=click.Path(dir_okay=False, path_type=Path), callback=_png_name,
              help="Also write the full 2560x1600 DMD frame with the mask in it (all other mirrors off).")
@click.option("--offset", type=click.IntRange(min=0), nargs=2, default=None, metavar="ROW COL",
              help="Top-left mirror of the mask in the DMD frame (default: centred).")
@option(S.COMPENSATION, "robust", help=S.COMPENSATION["robust"].description + " Not for --method nn.")
@click.option("--device", default=None, help="torch device (default: cuda if available, else cpu).")
def compensate_cmd(design, model_dir, params_path, method, output, frame_png, offset, robust, device):
    """The grayscale mask that prints DESIGN (PNG, nonzero = solid) despite the scattering."""
    written = [output.resolve()] + ([frame_png.resolve()] if frame_png else [])
    if design.resolve() in written or len(set(written)) < len(written):
        raise click.UsageError("the design, the mask (-o) and the DMD frame (--frame) need three different files")
    if method == "ilt" and params_path is not None:
        raise click.UsageError("for --method ilt, --model is the params.yaml; --params is for nn+ilt")
    if method == "nn+ilt" and params_path is None:
        raise click.UsageError("--method nn+ilt refines the network's mask with ILT: give --params (params.yaml)")
    given = click.get_current_context().get_parameter_source("robust") != click.core.ParameterSource.DEFAULT
    if method == "nn" and given:
        raise click.UsageError("--robust/--no-robust is an ILT setting (use --method ilt or nn+ilt)")
    _passive_threads()
    from .compensation import compensate, frame_offset, write_mask_and_frame
    from .io import read_mask

    design_mask = read_mask(design)
    try:  # before the optimisation, which takes a while
        frame_offset(design_mask.shape, offset=offset)
    except ValueError as exc:
        raise InputError(design, str(exc)) from None
    settings = dict(device=device) if method == "nn" else dict(device=device, robust=robust)
    try:
        mask = compensate(design_mask, method, params_path=model_dir if method == "ilt" else params_path,
                          train_dir=None if method == "ilt" else model_dir, **settings)
        write_mask_and_frame(mask, output, frame_png, offset=offset)
    except ValueError as exc:
        if isinstance(exc, InputError):
            raise
        raise click.UsageError(str(exc)) from None
    click.echo(f"{method} mask for {design.name} -> {output}" + (f" (DMD frame -> {frame_png})" if frame_png else ""))


@main.command("compensate3d")
@click.argument("designs", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--params", "params_path", type=click.Path(exists=True, path_type=Path), required=True,
              help="The calibrated 2-D printer model (params.yaml, or its calibration or diagnosis folder).")
@click.option("--depth", "depth_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), required=True,
              help="The depth parameters (YAML: att_length_um, diffusion_um, layer_um; a calibrate3d folder's depth.yaml).")
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output folder: <design>/NNN.png layer masks and compensation3d.tsv.")
@click.option("--name", "names", multiple=True, help="Only this design (repeat); default: every design.")
def compensate3d_cmd(designs, params_path, depth_path, out_dir, names):
    """Layer masks that print 3-D DESIGNS (a folder of layer PNGs, bottom first, or a folder
    of such folders) despite the light reaching the layers below: ILT over all layers."""
    _passive_threads()
    from .compensation3d import compensate3d_designs

    rows = compensate3d_designs(designs, out_dir, params_path, depth_path, names=list(names) or None)
    for r in rows:
        click.echo(f"{r['design']:<18} 3-D IoU {r['model_iou']:.4f} (identical masks at the best dose "
                   f"{r['identical_best_dose']:.2f}: {r['identical_model_iou']:.4f})  {r['seconds']:.1f} s")
    click.echo(f"-> {out_dir}")


# ------------------------------------------------------------ benchmark, report
def _methods(values) -> dict:
    """--method NAME=DIR, repeated -> {name: folder of <design>.png}."""
    out = {}
    for v in values:
        name, sep, folder = v.partition("=")
        if not sep or not name or not folder:
            raise click.BadParameter(f"{v!r}: give NAME=FOLDER (a folder of <design>.png masks)", param_hint="--method")
        out[name] = Path(folder)
    return out


def _summary_lines(rows) -> None:
    from .benchmark import summarise, summary_line

    for s in summarise(rows):
        click.echo(summary_line(s))


_method_option = click.option("--method", "methods", multiple=True, metavar="NAME=FOLDER",
                              help="Compensated masks of one method (repeat), e.g. ilt=results/compensated/eq1/ilt.")
_doses_option = click.option("--doses", default=",".join(f"{d:g}" for d in S.BENCHMARK.default.doses), show_default=True,
                             help=S.BENCHMARK["doses"].description + " Comma-separated.")


def _doses(text: str) -> tuple:
    try:
        return tuple(S.BENCHMARK.check("doses", [float(x) for x in text.split(",")]))
    except ValueError as exc:
        raise click.BadParameter(f"{text!r}: comma-separated grey levels in (0, 1] ({exc})", param_hint="--doses") from None


@main.group(cls=_Group)
def benchmark():
    """Compensated masks against the identical mask at several doses."""


@benchmark.command("job")
@click.argument("designs_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@_method_option
@_doses_option
@click.option("--fiducials/--no-fiducials", default=S.BENCHMARK.default.fiducials, show_default=True,
              help="Registration marks in three corners of the masks of every design that leaves room for them.")
def benchmark_job(designs_dir, out_dir, methods, doses, fiducials):
    """Write the print job of the benchmark (masks/, job.tsv, batch.yaml, README.txt) to OUT_DIR."""
    from .benchmark import write_print_job

    rows = write_print_job(_methods(methods), designs_dir, out_dir, doses=_doses(doses), fiducials=fiducials)
    click.echo(f"print job of {len(rows)} masks -> {out_dir} (see {out_dir / 'README.txt'})")


@benchmark.command("simulate")
@click.argument("designs_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--params", "params_path", type=click.Path(exists=True, path_type=Path), required=True,
              help="The calibrated params.yaml (or its folder): the simulator that prints.")
@_method_option
@_doses_option
def benchmark_simulate(designs_dir, out_dir, params_path, methods, doses):
    """Score the benchmark's masks printed by the calibrated simulator."""
    from .benchmark import run_benchmark, simulator_printer
    from .model import load_params

    from .benchmark import printer_pixel_size

    params = load_params(params_path)
    rows = run_benchmark(designs_dir, _methods(methods), out_dir, printer_pixel_size(params, params_path),
                         simulator_printer(params), doses=_doses(doses))
    _summary_lines(rows)


@benchmark.command("score")
@click.argument("prints_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("designs_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
def benchmark_score(prints_dir, designs_dir, out_dir):
    """Score a registered benchmark batch (PRINTS_DIR from `unscatter register`) against the designs."""
    from .benchmark import score_measured
    from .io import output_dir

    # here, not in score_measured: the workflow writes its scores beside the benchmark's other outputs
    with output_dir(out_dir, command="benchmark score", inputs=[prints_dir, designs_dir]) as tmp:
        rows = score_measured(prints_dir, designs_dir, tmp)
    _summary_lines(rows)


@main.group(cls=_Group)
def benchmark3d():
    """Compensated layer masks against identical ones at the best uniform dose."""


@benchmark3d.command("job")
@click.argument("designs", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("compensated", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--params", "params_path", type=click.Path(exists=True, path_type=Path), required=True)
@click.option("--depth", "depth_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), required=True)
def benchmark3d_job(designs, compensated, out_dir, params_path, depth_path):
    """The 3-D benchmark's print job: <design>__ilt and <design>__identical layer masks."""
    from .compensation3d import write_job3d

    rows = write_job3d(designs, compensated, params_path, depth_path, out_dir)
    click.echo(f"print job of {len(rows)} multi-layer prints -> {out_dir}")


@benchmark3d.command("score")
@click.argument("registered", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("designs", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
def benchmark3d_score(registered, designs, out_dir):
    """Score registered 3-D benchmark prints (from `unscatter register3d`) against the designs."""
    from .compensation3d import score3d_batch

    for r in score3d_batch(registered, designs, out_dir):
        if r["status"] != "ok":
            click.echo(f"{r['id']:<28} failed registration")
            continue
        click.echo(f"{r['id']:<28} IoU {r['iou']:.4f}  open channels {r['open_channels']:.2f}  overhang "
                   f"{r['overhang_error_um']:.1f} um  wall {r['wall_error_um']:+.1f} um")


@main.command("report")
@click.argument("results_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), help="Default: RESULTS_DIR/report.html.")
def report_cmd(results_dir, output):
    """One self-contained HTML page with every stage's figures and tables."""
    from .report import build_report

    out = build_report(results_dir, output or results_dir / "report.html")
    click.echo(f"report -> {out}")


# -------------------------------------------------------------------- diagnose
@main.command("diagnose")
@click.argument("prints_dirs", nargs=-1, required=True, type=click.Path(file_okay=False, path_type=Path))
@click.option("--base", "base_params", required=True, type=click.Path(path_type=Path),
              help="The base params.yaml from `unscatter calibrate` (or its folder).")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path), help="Output folder.")
@option(S.DIAGNOSIS, "folds")
@option(S.DIAGNOSIS, "seed")
@click.option("--candidates", default=None, metavar="A,B,...", help=S.DIAGNOSIS["candidates"].description + " Comma-separated.")
@option(S.DIAGNOSIS, "quick", "--quick", is_flag=True)
@option(S.DIAGNOSIS, "gain_test")
@option(S.DIAGNOSIS, "threads")
@option(S.DIAGNOSIS, "workers")
@click.option("--progress/--no-progress", default=True, show_default=True)
def diagnose_cmd(prints_dirs, base_params, out_dir, folds, seed, candidates, quick, gain_test, threads, workers, progress):
    """Residual diagnosis of a calibrated model on registered prints (PRINTS_DIR: registration outputs):
    held-out residual diagnostics, effects added while they lower the held-out error, the selected model."""
    from .diagnosis import diagnose

    cands = None
    if candidates:
        cands = [c.strip() for c in candidates.split(",") if c.strip()]
        bad = [c for c in cands if c not in S.EFFECT_NAMES]
        if bad:
            raise click.BadParameter(f"unknown effect(s) {', '.join(bad)}; known: {', '.join(S.EFFECT_NAMES)}",
                                     param_hint="--candidates")
    more = {} if threads is None else dict(threads=threads)
    try:
        r = diagnose(list(prints_dirs), base_params, out_dir, folds=folds, seed=seed, candidates=cands, quick=quick,
                     progress=progress, workers=workers, gain_test=gain_test, **more)
    except ValueError as exc:
        if isinstance(exc, InputError):
            raise
        raise click.UsageError(str(exc)) from None
    b, a = r["before"], r["after"]
    eff = ", ".join(r["effects"]) or "none"
    click.echo(f"effects added: {eff}; held-out IoU {b['heldout_iou']:.4f} -> {a['heldout_iou']:.4f} (the mask itself "
               f"{r['mask']['heldout_iou']:.4f}), pixel error "
               f"{b['heldout_pixel_error']:.4f} -> {a['heldout_pixel_error']:.4f}; unexplained residual: "
               f"{'yes (' + ', '.join(r['unexplained_diagnostics']) + ')' if r['unexplained_residual'] else 'no'} "
               f"({r['seconds']:.0f} s) -> {out_dir / 'model.yaml'}")
    if not r["beats_mask"]:
        click.echo(f"warning: {r['model']} predicts the held-out prints no better than the mask itself: none of the "
                   f"candidate effects tried describes these prints (report.md)", err=True)


if __name__ == "__main__":  # pragma: no cover
    main()
