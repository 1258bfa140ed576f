"""Adapter of rule compensate: unscatter.compensation.compensate_designs."""

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    from unscatter.compensation import compensate_designs

    p, method = snakemake.params, snakemake.wildcards.method
    settings = {} if method == "nn" else {"robust": p.robust}
    rows = compensate_designs(
        p.folder,
        snakemake.output[0],
        method,
        params_path=None if method == "nn" else snakemake.input.model,
        train_dir=None if method == "ilt" else snakemake.input.train,
        names=p.names or None,
        **settings,
    )
    log.info("%s masks for %d designs (%.2f s each on average) -> %s", method, len(rows),
             sum(r["seconds"] for r in rows) / len(rows), snakemake.output[0])


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
