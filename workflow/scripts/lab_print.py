"""Adapter of rules virtual_lab and virtual_lab_benchmark: unscatter.lab.print_batch."""

from pathlib import Path

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    from unscatter.lab import print_batch, read_job

    lab_config = snakemake.input.lab_config[0] if snakemake.input.lab_config else None
    if "job" in snakemake.input.keys():  # a print job: masks/ and job.tsv (exposure per mask)
        job = Path(snakemake.input.job)
        masks, exposures = job / "masks", read_job(job / "job.tsv")
    else:
        masks, exposures = snakemake.input.masks, None
    rows = print_batch(
        masks,
        snakemake.output.batch,
        lab_config=lab_config,
        truth_dir=snakemake.output.truth,
        seed=snakemake.params.seed,
        progress=False,
        exposures=exposures,
    )
    log.info(
        "printed and imaged %d masks (lab seed %d, config %s) into %s",
        len(rows), snakemake.params.seed, lab_config or "defaults", snakemake.output.batch,
    )


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
