"""Adapter of rule trial_masks: unscatter.masks.write_trial_masks."""

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    from unscatter.masks import write_trial_masks

    p = snakemake.params
    out_dir = snakemake.output[0]
    paths = write_trial_masks(out_dir, count=p.n, seed=p.seed, size=p.size)
    log.info("wrote %d trial masks (seed %d, %d px) to %s", len(paths), p.seed, p.size, out_dir)


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
