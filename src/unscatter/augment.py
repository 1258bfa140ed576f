"""Augmentation data: masks and their simulated prints in a Zarr store.

Guan et al. 2022, 'Simulator calibration': "After calibration, we apply a new set of
4,000 masks to the simulator and obtain their corresponding simulated structures", and
'Neural network training': "we randomly divide the 4,000 data pairs into 3,600 pairs of
training data and 400 as testing data".

Layout of ``results/augment/<model>.zarr`` (a Zarr v3 group):

```
masks    (N, H, W) uint8   the mask, 255 = 100 % dose           chunks (1, H, W)
prints   (N, H, W) bool    Eq. 1 with the hard threshold        chunks (1, H, W)
family   (N,)      uint8   index into attrs["family_names"]
train    (n_train,) int32  sample indices of the training split (sorted)
test     (n_test,)  int32  sample indices of the test split (sorted)
attrs    format, unscatter_version, params (params.yaml as a mapping), params_path,
         model, seed, count, size, family_names, families (counts), test_fraction,
         split_seed, n_train, n_test, simulation, print_fraction, empty_prints, complete
```

One sample per chunk makes a random read by the trainer one small file per array.
Every chunk is stored, empty prints too, and ``attrs["chunks"]`` counts them, so a store
that lost files is recognised on opening instead of read as empty prints.
Mask ``i`` depends only on (seed, i) and the simulation is deterministic, so the
arrays do not depend on the number of workers. The store is written under a temporary
name and renamed when complete (``io.output_dir``); an existing folder is replaced only
when it is an augmentation store itself.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import __version__
from .io import InputError, output_dir
from .settings import AUGMENTATION

log = logging.getLogger(__name__)

FORMAT = "unscatter-augment/1"
ARRAYS = ("masks", "prints", "family", "train", "test")
TEST_FRACTION = AUGMENTATION.default.test_fraction  # Guan et al. 2022, 'Neural network training': 3,600 / 400 of 4,000
_AUG = AUGMENTATION.default


# ----------------------------------------------------------------------------- split


def split_indices(count: int, test_fraction: float = TEST_FRACTION, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A seeded random train/test split of ``count`` samples (sorted index arrays)."""
    if not 0 <= test_fraction < 1:
        raise ValueError(f"test_fraction must be in [0, 1), got {test_fraction}")
    n_test = int(round(count * test_fraction))
    if test_fraction > 0 and count >= 2:
        n_test = min(max(n_test, 1), count - 1)
    perm = np.random.default_rng([seed, 0x5E1]).permutation(count)
    return np.sort(perm[n_test:]).astype(np.int32), np.sort(perm[:n_test]).astype(np.int32)


# ---------------------------------------------------------------------------- workers


def _make_block(job: tuple) -> dict:
    """Generate, simulate and write samples [i0, i1): one unit of parallel work."""
    import zarr

    from .masks import augmentation_mask
    from .model import load_params, simulate

    store, params_path, seed, size, fams, i0, i1, device = job
    params = load_params(params_path, check_prints=False)  # augment() checked it once
    masks = np.stack([augmentation_mask(f, seed, i, size) for i, f in zip(range(i0, i1), fams)])
    prints = simulate(params, list(masks), device=device, batch=len(masks))
    g = zarr.open_group(store, mode="r+")
    for name, data in (("masks", masks), ("prints", prints)):  # empty prints too: see the module's docstring
        g[name].with_config({"write_empty_chunks": True})[i0:i1] = data
    return dict(i0=i0, print_px=prints.reshape(len(prints), -1).sum(1))


def _default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


# ---------------------------------------------------------------------------- augment


def augment(
    params_path,
    out_zarr,
    count: int,
    seed: int = _AUG.seed,
    families=None,
    size: int = _AUG.size,
    test_fraction: float = TEST_FRACTION,
    workers: int | None = _AUG.workers,
    block: int = 16,
    device: str | None = None,
    progress: bool = True,
) -> dict:
    """Write ``count`` augmentation masks and their simulated prints to ``out_zarr``.

    ``params_path``: a params file from calibration or diagnosis, or its folder (``unscatter.model.load_params``).
    ``families``: names (equal shares) or name -> weight (see ``masks.family_counts``);
    default: all seven augmentation families. ``workers`` threads (default: one per CPU
    core) each generate, simulate and write blocks of ``block`` samples, with one torch
    thread each (the FFTs, OpenCV and zstd release the GIL; threads, unlike processes,
    need no re-import of the caller's main module). ``device``: where to simulate (default: the GPU when there is
    one, then in this process). An existing ``out_zarr`` is replaced if it is an
    augmentation store; any other non-empty folder is an error.
    Returns a summary (the store's attributes plus the elapsed time).
    """
    import torch
    import zarr
    from zarr.codecs import ZstdCodec

    from .masks import AUGMENT_FAMILIES, augmentation_families, family_counts
    from .model import default_device, load_params
    from .model import params_path as params_path_of

    t0 = time.perf_counter()
    params_path = params_path_of(params_path)
    params = load_params(params_path)  # errors name the file
    AUGMENTATION.make(count=count, seed=seed, size=size, test_fraction=test_fraction, workers=workers)
    counts = family_counts(count, families)
    labels = augmentation_families(count, seed, families)
    names = list(AUGMENT_FAMILIES)
    train, test = split_indices(count, test_fraction, seed)
    device = str(device or default_device())
    if workers is None:
        workers = 1 if device.startswith("cuda") else _default_workers()
    workers = max(1, min(int(workers), math.ceil(count / block)))

    out = Path(out_zarr)
    with output_dir(out, command="augment", inputs=[params_path], recognise=is_store, marker=False) as tmp:
        g = zarr.open_group(str(tmp), mode="w")
        comp = ZstdCodec(level=1)
        every = {"write_empty_chunks": True}  # a missing chunk then means a lost file, never an empty print
        g.create_array("masks", shape=(count, size, size), chunks=(1, size, size), dtype="uint8", compressors=comp,
                       fill_value=0, config=every)
        g.create_array("prints", shape=(count, size, size), chunks=(1, size, size), dtype="bool", compressors=comp,
                       fill_value=False, config=every)
        g.create_array("family", data=np.array([names.index(f) for f in labels], np.uint8), chunks=(count,), config=every)
        g.create_array("train", data=train, chunks=(max(1, len(train)),), config=every)
        g.create_array("test", data=test, chunks=(max(1, len(test)),), config=every)

        jobs = [
            (str(tmp), str(params_path), int(seed), int(size), labels[i : min(i + block, count)], i, min(i + block, count), device)
            for i in range(0, count, block)
        ]
        print_px = np.zeros(count, np.int64)
        from tqdm import tqdm

        bar = tqdm(total=count, desc="augment", unit="pair", disable=not progress)
        if workers == 1:
            threads = torch.get_num_threads()
            for job in jobs:
                r = _make_block(job)
                print_px[r["i0"] : r["i0"] + len(r["print_px"])] = r["print_px"]
                bar.update(len(r["print_px"]))
            torch.set_num_threads(threads)
        else:
            threads = torch.get_num_threads()
            torch.set_num_threads(1)
            try:
                with ThreadPoolExecutor(workers) as ex:
                    for r in ex.map(_make_block, jobs):
                        print_px[r["i0"] : r["i0"] + len(r["print_px"])] = r["print_px"]
                        bar.update(len(r["print_px"]))
            finally:
                torch.set_num_threads(threads)
        bar.close()

        frac = print_px / float(size * size)
        attrs = dict(
            format=FORMAT,
            unscatter_version=__version__,
            params=params.to_dict(),
            params_path=str(params_path),
            model=params.model,
            seed=int(seed),
            count=int(count),
            size=int(size),
            family_names=names,
            families={f: int(n) for f, n in counts.items()},
            test_fraction=float(test_fraction),
            split_seed=int(seed),
            n_train=int(len(train)),
            n_test=int(len(test)),
            simulation="unscatter.model.simulate, hard threshold (Guan et al. 2022, Eq. 1)",
            print_fraction=float(frac.mean()),
            empty_prints=int((print_px == 0).sum()),
            chunks={k: int(g[k].nchunks) for k in ARRAYS},
            complete=True,
        )
        g.attrs.update(attrs)
    elapsed = time.perf_counter() - t0
    log.info("wrote %d pairs (%dx%d) to %s in %.1f s with %d worker(s)", count, size, size, out, elapsed, workers)
    return dict(attrs, path=str(out), elapsed_s=elapsed, workers=workers)


def is_store(folder) -> bool:
    """Whether ``folder`` is an augmentation store (its zarr.json says so)."""
    try:
        meta = json.loads((Path(folder) / "zarr.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(meta, dict) and isinstance(meta.get("attributes"), dict) and meta["attributes"].get("format") == FORMAT


# --------------------------------------------------------------------------- reading


@dataclass
class AugmentDataset:
    """An augmentation store opened for reading."""

    path: Path
    group: object  # zarr.Group

    @property
    def attrs(self) -> dict:
        return dict(self.group.attrs)

    @property
    def masks(self):
        return self.group["masks"]

    @property
    def prints(self):
        return self.group["prints"]

    @property
    def train(self) -> np.ndarray:
        return np.asarray(self.group["train"][:], np.int64)

    @property
    def test(self) -> np.ndarray:
        return np.asarray(self.group["test"][:], np.int64)

    @property
    def size(self) -> int:
        return int(self.masks.shape[-1])

    def __len__(self) -> int:
        return int(self.masks.shape[0])

    def params(self):
        """The printer parameters the prints were simulated with."""
        import tempfile

        from .io import write_yaml
        from .model import load_params

        # load_params reads files only: round-trip the stored mapping through one
        with tempfile.TemporaryDirectory() as d:
            p = Path(d) / "params.yaml"
            write_yaml(p, self.attrs["params"])
            return load_params(p)

    def pairs(self, idx) -> tuple[np.ndarray, np.ndarray]:
        """masks (uint8) and prints (bool) of samples ``idx``, in the order given."""
        idx = np.asarray(idx, np.int64).reshape(-1)
        if idx.size == 0:
            s = self.size
            return np.zeros((0, s, s), np.uint8), np.zeros((0, s, s), bool)
        order = np.argsort(idx, kind="stable")
        sidx = idx[order]
        m = self.masks.oindex[sidx]
        p = self.prints.oindex[sidx]
        inv = np.empty_like(order)
        inv[order] = np.arange(len(order))
        return m[inv], p[inv]


def open_dataset(path) -> AugmentDataset:
    """Open an augmentation store (checked: format, arrays, completeness)."""
    import zarr

    path = Path(path)
    if not path.is_dir():
        raise InputError(path, "augmentation store does not exist (run `unscatter augment` first)")
    try:
        g = zarr.open_group(str(path), mode="r")
    except Exception as exc:  # zarr raises several kinds
        raise InputError(path, f"not a Zarr group ({exc})") from exc
    a = dict(g.attrs)
    if a.get("format") != FORMAT:
        raise InputError(path, f"not an augmentation store (format {a.get('format')!r}, expected {FORMAT!r})")
    if not a.get("complete"):
        raise InputError(path, "augmentation store is incomplete (interrupted write?)")
    for k in ("masks", "prints", "train", "test"):
        if k not in g:
            raise InputError(path, f"array {k!r} missing")
    if g["masks"].shape != g["prints"].shape:
        raise InputError(path, f"masks {g['masks'].shape} and prints {g['prints'].shape} differ in shape")
    for k, n in (a.get("chunks") or {}).items():  # stores written before the count was kept are not checked
        found = g[k].nchunks_initialized if k in g else 0
        if found != n:
            raise InputError(path, f"{n - found} of the {n} chunk files of {k!r} are missing (deleted, or not copied?); "
                                   "write the store again with `unscatter augment`")
    return AugmentDataset(path, g)
