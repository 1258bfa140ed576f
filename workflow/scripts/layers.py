"""Adapter of the multi-layer rules (workflow/rules/layers.smk): unscatter.calibration3d,
unscatter.lab.print_layers, unscatter.imaging.register_stacks, unscatter.compensation3d."""

from pathlib import Path

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    rule, p, out = snakemake.rule, snakemake.params, snakemake.output[0]
    if rule == "trial_masks3d":
        from unscatter.calibration3d import write_trial_masks3d

        paths = write_trial_masks3d(out, count=p.n, layers=p.layers, size=p.size, seed=p.seed)
        log.info("wrote %d 3-D trial prints -> %s", len(paths), out)
    elif rule == "virtual_lab3d":
        from unscatter.lab import print_layers

        masks = Path(snakemake.input.masks)
        masks = masks / "masks" if (masks / "masks").is_dir() else masks  # a print job holds masks/
        lab_config = snakemake.input.lab_config[0] if snakemake.input.lab_config else None
        rows = print_layers(masks, snakemake.output.batch, lab_config=lab_config, truth_dir=snakemake.output.truth,
                            seed=p.seed, progress=False)
        log.info("printed and imaged %d multi-layer prints -> %s", len(rows), snakemake.output.batch)
    elif rule == "register3d":
        from unscatter.imaging import register_stacks

        rows = register_stacks(snakemake.input.batch, out, level=p.level, skip_failed=True, progress=False)
        for r in rows:
            if r["status"] == "failed":
                log.warning("%s: failed QC, not used: %s", r["id"], r["reason"])
        log.info("registered %d z-stacks, %d ok -> %s", len(rows), sum(r["status"] == "ok" for r in rows), out)
    elif rule == "calibrate3d":
        from unscatter.calibration3d import calibrate3d

        r = calibrate3d(list(snakemake.input.prints), snakemake.input.model, out, free2d=tuple(p.free),
                        bootstrap=p.bootstrap)
        log.info("depth: %s (spread %s); held-out voxel IoU %s -> %s", r["values"], r.get("spread"),
                 r["heldout_voxel_iou"], out)
    elif rule == "compensate3d":
        from unscatter.compensation3d import compensate3d_designs

        cal = Path(snakemake.input.calibration)
        rows = compensate3d_designs(p.folder, out, cal / "params.yaml", cal / "depth.yaml", names=p.names or None)
        for r in rows:
            log.info("%s: 3-D IoU %.4f (identical at %.2f: %.4f), %.1f s", r["design"], r["model_iou"],
                     r["identical_best_dose"], r["identical_model_iou"], r["seconds"])
    elif rule == "benchmark3d_job":
        from unscatter.compensation3d import write_job3d

        cal = Path(snakemake.input.calibration)
        rows = write_job3d(p.folder, snakemake.input.compensated, cal / "params.yaml", cal / "depth.yaml", out)
        log.info("3-D print job of %d prints -> %s", len(rows), out)
    elif rule == "benchmark3d_score":
        from unscatter.compensation3d import score3d_batch

        for r in score3d_batch(snakemake.input.prints[0], p.folder, out, names=p.names or None):
            log.info("%s", r)
    else:
        raise ValueError(f"no adapter for rule {rule!r}")


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
