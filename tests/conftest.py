import numpy as np
import pytest
import torch

from unscatter.io import write_png

# One torch thread for the whole suite, whatever the machine's cores and whichever tests run:
# a fit's float sums then add in one order, and a test that compares a fit with its start
# (tests/test_diagnosis.py) gives the same verdict alone and in the full suite.
torch.set_num_threads(1)


@pytest.fixture(scope="session")
def trial_dir(tmp_path_factory):
    """Nine trial masks (three of each family), as the workflow writes them."""
    from unscatter.masks import write_trial_masks

    d = tmp_path_factory.mktemp("trial_masks")
    write_trial_masks(d, count=9, seed=5)
    return d


@pytest.fixture(scope="session")
def lab_batch(tmp_path_factory, trial_dir):
    """A virtual-lab batch of the nine trial masks plus an under-dosed and a faint print."""
    from unscatter.lab import print_batch

    root = tmp_path_factory.mktemp("lab")
    masks = root / "masks"
    masks.mkdir()
    for p in trial_dir.glob("*.png"):
        (masks / p.name).write_bytes(p.read_bytes())
    square = np.zeros((512, 512), np.uint8)
    square[150:350, 180:380] = 60  # dose 0.24: below the gel point, nothing cures
    write_png(masks / "underdosed.png", square)
    faint = np.zeros((512, 512), np.uint8)
    faint[100:400, 120:300] = 112  # dose 0.44: polymer gels but stays below the print level
    faint[300:420, 330:450] = 255
    write_png(masks / "faint.png", faint)
    batch = root / "batch"
    print_batch(masks, batch, seed=11, progress=False)
    return batch
