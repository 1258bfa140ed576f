"""Adapter of rule virtual_lab: unscatter.lab.print_batch."""

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    from unscatter.lab import print_batch

    lab_config = snakemake.input.lab_config[0] if snakemake.input.lab_config else None
    rows = print_batch(
        snakemake.input.masks,
        snakemake.output.batch,
        lab_config=lab_config,
        truth_dir=snakemake.output.truth,
        seed=snakemake.params.seed,
        progress=False,
    )
    log.info(
        "printed and imaged %d masks (lab seed %d, config %s) into %s",
        len(rows), snakemake.params.seed, lab_config or "defaults", snakemake.output.batch,
    )


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
