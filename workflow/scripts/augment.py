"""Adapter of rule augment: unscatter.augment.augment."""

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    from unscatter.augment import augment

    p = snakemake.params
    s = augment(
        snakemake.input.model,
        snakemake.output[0],
        count=p.pairs,
        seed=p.seed,
        size=p.size,
        test_fraction=p.test_fraction,
        workers=snakemake.threads,
        progress=False,
    )
    log.info("wrote %d pairs (%d train / %d test) in %.1f s -> %s",
             s["count"], s["n_train"], s["n_test"], s["elapsed_s"], snakemake.output[0])


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
