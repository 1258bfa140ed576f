"""The `unscatter` command: one subcommand per stage, each calling the package function
that the Snakemake rule calls too. Heavy imports happen inside the commands."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import click

from . import __version__
from .io import InputError


class _Group(click.Group):
    """Bad input ends with one clear line (file: problem) and exit code 2, no traceback."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except InputError as exc:
            click.echo(f"error: {exc}", err=True)
            ctx.exit(2)


@click.group(cls=_Group)
@click.version_option(__version__)
@click.option("-v", "--verbose", is_flag=True, help="Debug logging.")
def main(verbose):
    """unscatter: compensate cell-induced light scattering in DLP bioprinting."""
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")


# ----------------------------------------------------------------------- masks
@main.group(cls=_Group)
def masks():
    """Mask sets."""


@masks.command("trial")
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--count", default=32, show_default=True, help="Number of trial masks (paper: 32).")
@click.option("--seed", default=0, show_default=True)
@click.option("--size", default=512, show_default=True, help="Mask side in DMD pixels (paper: 512).")
def masks_trial(out_dir, count, seed, size):
    """The paper's trial masks: checkerboards, rectangles, circles (8-bit PNG)."""
    from .masks import write_trial_masks

    paths = write_trial_masks(out_dir, count=count, seed=seed, size=size)
    click.echo(f"wrote {len(paths)} trial masks to {out_dir}")


# ------------------------------------------------------------------------- lab
@main.group(cls=_Group)
def lab():
    """The virtual lab (printer + microscope)."""


@lab.command("print")
@click.argument("mask_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("out_batch", type=click.Path(file_okay=False, path_type=Path))
@click.option("--lab-config", type=click.Path(exists=True, dir_okay=False, path_type=Path), help="Overrides of the lab's defaults (YAML).")
@click.option("--truth-dir", type=click.Path(file_okay=False, path_type=Path), help="Where the truth goes (default OUT_BATCH.truth).")
@click.option("--seed", type=int, help="Lab seed (overrides the config).")
def lab_print(mask_dir, out_batch, lab_config, truth_dir, seed):
    """Print every mask of MASK_DIR on the virtual lab; write a batch in the data contract."""
    from .lab import print_batch

    rows = print_batch(mask_dir, out_batch, lab_config=lab_config, truth_dir=truth_dir, seed=seed)
    click.echo(f"printed and imaged {len(rows)} masks into {out_batch}")


# -------------------------------------------------------------------- register
@main.command("register")
@click.argument("batch_dir", type=click.Path(file_okay=False, path_type=Path))
@click.argument("out_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--mode", type=click.Choice(["similarity", "affine"]), default="similarity", show_default=True)
@click.option("--level", default=0.5, show_default=True, help="Print = density above this fraction of the batch's dense-polymer level.")
@click.option("--min-score", default=0.6, show_default=True, help="QC: lowest registration score accepted.")
@click.option("--skip-failed/--no-skip-failed", default=False, show_default=True, help="Go on when a print fails QC (it is still never used).")
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


if __name__ == "__main__":  # pragma: no cover
    main()
