"""Adapter of rules benchmark_job, benchmark_simulated and benchmark_score:
unscatter.benchmark.write_print_job, run_benchmark (simulator) and score_measured."""

from pathlib import Path

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    from unscatter import benchmark as bm
    from unscatter.io import read_mask

    designs = {Path(f).stem: read_mask(f) for f in snakemake.input.designs}
    rule = snakemake.rule
    if rule == "benchmark_score":
        out = Path(snakemake.output.metrics).parent
        rows = bm.score_measured(snakemake.input.prints[0], designs, out)
        missing = [k for k in ("fig6", "fig5", "bars") if not Path(snakemake.output[k]).is_file()]
        if missing:
            raise RuntimeError(f"the benchmark figures {missing} were not written (are the batch's masks there?)")
    else:
        p = snakemake.params
        masks = dict(zip(p.methods, snakemake.input.masks))
        if rule == "benchmark_job":
            rows = bm.write_print_job(masks, designs, snakemake.output[0], doses=tuple(p.doses), fiducials=p.fiducials)
            log.info("print job of %d masks -> %s", len(rows), snakemake.output[0])
            return
        from unscatter.model import load_params

        params = load_params(snakemake.input.model)
        rows = bm.run_benchmark(designs, masks, snakemake.output[0], bm.printer_pixel_size(params, snakemake.input.model),
                                bm.simulator_printer(params), doses=tuple(p.doses))
    for s in bm.summarise(rows):
        # a mask at full grey without a print of every design: its mean is not over the others' designs
        (log.warning if s["no_print"] and s["mask_dose"] == bm.FULL_GREY else log.info)("%s", bm.summary_line(s))


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
