"""Adapter of rule next_trial_masks: unscatter.design.design_masks (sequential)."""

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    from unscatter.design import design_masks, write_design

    p = snakemake.params
    prints = list(snakemake.input.prints)
    r = design_masks(p.n, model=snakemake.input.model, prints=prints, pool=p.pool, draws=p.draws, seed=p.seed,
                     size=p.size, fiducials=p.fiducials, criterion=p.criterion, progress=False)
    write_design(snakemake.output[0], r, inputs=[snakemake.input.model, *prints])
    log.info("designed %d masks for the next batch (focus: %s; criterion %.1f, random paper masks %.1f) in %.0f s -> %s",
             p.n, ", ".join(r["focus"]) or "none", r["criterion"], r["criterion_paper"], r["seconds"], snakemake.output[0])


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
