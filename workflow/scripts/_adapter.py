"""What every Snakemake adapter does first: log to the rule's log file, cap threads.

Snakemake runs each `script:` in its own Python process and puts this folder on its
path, so the adapters import this module as `_adapter`.
"""

from __future__ import annotations

import logging
import os
import sys

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def start(snakemake) -> logging.Logger:
    """Send stdout, stderr (tracebacks, warnings, native libraries) and logging to the log.

    Call it before importing numpy or unscatter: native thread pools read their size
    when they load, and a rule must not use more cores than its `threads`.
    """
    for var in _THREAD_VARS:
        os.environ[var] = str(snakemake.threads)
    # Idle OpenMP (torch) threads sleep instead of spinning: spinning threads slow a
    # machine shared with other jobs many times over.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    # Progress bars in a log file are noise: the adapters log one line per step instead.
    os.environ.setdefault("TQDM_DISABLE", "1")
    try:  # OpenCV sizes its own pool, whatever the variables say
        import cv2

        cv2.setNumThreads(int(snakemake.threads))
    except ImportError:
        pass
    if snakemake.log:
        sys.stdout.flush()
        sys.stderr.flush()
        fd = os.open(snakemake.log[0], os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        os.close(fd)
    logging.basicConfig(
        level=logging.INFO,
        stream=sys.stderr,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        force=True,
    )
    return logging.getLogger(f"workflow.{snakemake.rule}")
