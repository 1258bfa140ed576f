"""Adapter of rule report: unscatter.report.build_report."""

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    from unscatter.report import build_report

    out = build_report(snakemake.params.results, snakemake.output[0],
                       benchmark_batches=snakemake.params.benchmark_batches, models=snakemake.params.models)
    log.info("report -> %s", out)


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
