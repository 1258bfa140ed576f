"""Adapter of rule calibrate: unscatter.calibration.calibrate."""

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    from unscatter.calibration import calibrate

    p = snakemake.params
    params = calibrate(
        list(snakemake.input.prints),
        snakemake.output[0],
        model=snakemake.wildcards.model,
        seed=p.seed,
        population=p.population,
        generations=p.generations,
        folds=p.folds,
        bootstrap=p.bootstrap,
        free_c0=p.free_c0,
        objective=p.objective,
        workers=snakemake.threads,  # the refits of the folds and the bootstrap, one process a thread
        progress=False,
    )
    for w in params.info.get("warnings", []):
        log.warning("%s", w)
    log.info("calibrated %s: %s -> %s", snakemake.wildcards.model,
             ", ".join(f"{k}={params.values[k]:.4g}" for k in params.free), snakemake.output[0])


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
