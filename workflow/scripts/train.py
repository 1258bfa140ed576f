"""Adapter of rule train: unscatter.training.train.

Snakemake deletes a directory output before a job reruns, so the training runs in a
work folder beside it (``<results>/train/.work/<model>``) that keeps checkpoint.pt
between attempts: an interrupted run resumes there, and the finished folder is copied
to the output. A checkpoint from other settings or another dataset (the rule reruns
because they changed, e.g. after a new print batch) is not resumed: training starts over.
"""

import shutil
from pathlib import Path

from _adapter import start


def main(snakemake):
    log = start(snakemake)
    from unscatter.training import train

    p = snakemake.params
    out = Path(snakemake.output[0])
    work = out.parent / ".work" / out.name
    settings = {"seed": p.seed}
    if p.epochs:
        settings["epochs"] = p.epochs
    r = train(snakemake.input.dataset, work, preset=p.preset, settings=settings, resume="matching",
              threads=snakemake.threads, progress=False)
    shutil.copytree(work, out, dirs_exist_ok=True)
    ev = {row["method"]: row for row in r["eval"] if row["family"] == "all"}
    log.info("trained %d epochs (%.0f s this run): %s -> %s", r["epochs"], sum(r["seconds_per_epoch"]),
             ", ".join(f"{m} IoU {ev[m]['iou']:.4f}" for m in ("slave", "master", "identity") if m in ev), out)


if __name__ == "__main__":
    main(snakemake)  # noqa: F821 (Snakemake puts `snakemake` into the script's globals)
