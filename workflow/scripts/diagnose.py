"""Adapter of rule diagnose: unscatter.diagnosis.diagnose."""

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    from unscatter.diagnosis import diagnose

    p = snakemake.params
    r = diagnose(
        list(snakemake.input.prints),
        snakemake.input.base,
        snakemake.output[0],
        folds=p.folds,
        seed=p.seed,
        candidates=p.candidates or None,
        quick=p.quick,
        gain_test=p.gain_test,
        progress=False,
        workers=snakemake.threads,
    )
    b, a = r["before"], r["after"]
    log.info("effects added: %s; held-out IoU %.4f -> %.4f, pixel error %.4f -> %.4f; unexplained residual: %s",
             ", ".join(r["effects"]) or "none", b["heldout_iou"], a["heldout_iou"], b["heldout_pixel_error"],
             a["heldout_pixel_error"], ", ".join(r["unexplained_diagnostics"]) or "none")


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
