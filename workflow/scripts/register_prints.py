"""Adapter of rule register_prints: unscatter.imaging.register_batch."""

import sys

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    from unscatter.imaging import RegistrationError, register_batch

    p = snakemake.params
    out_dir = snakemake.output[0]
    try:
        rows = register_batch(
            snakemake.input.batch,
            out_dir,
            mode=p.mode,
            level=p.level,
            min_score=p.min_score,
            skip_failed=p.skip_failed,
        )
    except RegistrationError as exc:
        log.error("%s", exc)
        log.error(
            "a print failed quality control. To see why, run "
            "`unscatter register %s DIR --mode %s --level %s --min-score %s --skip-failed` "
            "and look at DIR/qc.tsv and DIR/overlays/; to go on without the print, set "
            "registration.skip_failed: true",
            snakemake.input.batch, p.mode, p.level, p.min_score,
        )
        sys.exit(1)
    counts = {s: sum(r["status"] == s for r in rows) for s in ("ok", "empty", "failed")}
    log.info(
        "registered %d prints (%s mode): %d ok, %d empty, %d failed -> %s",
        len(rows), p.mode, counts["ok"], counts["empty"], counts["failed"], out_dir,
    )


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
