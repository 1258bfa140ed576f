"""Adapter of rule trial_masks: unscatter.masks.write_trial_masks, or with
trial_masks.kind 'designed' unscatter.design.design_masks."""

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    p = snakemake.params
    out_dir = snakemake.output[0]
    if p.kind == "designed":
        from unscatter.design import design_masks, write_design

        r = design_masks(p.n, pool=p.pool, draws=p.draws, seed=p.seed, size=p.size, fiducials=p.fiducials,
                         criterion=p.criterion, progress=False)
        write_design(out_dir, r)
        log.info("designed %d trial masks from %d candidates (criterion %.1f; random paper masks %.1f) in %.0f s -> %s",
                 p.n, p.pool, r["criterion"], r["criterion_paper"], r["seconds"], out_dir)
        return
    from unscatter.masks import write_trial_masks

    paths = write_trial_masks(out_dir, count=p.n, seed=p.seed, size=p.size, fiducials=p.paper_fiducials)
    log.info("wrote %d trial masks (seed %d, %d px%s) to %s", len(paths), p.seed, p.size,
             ", registration marks" if p.paper_fiducials else "", out_dir)


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
