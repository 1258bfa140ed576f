"""Registration's heavy per-print steps in forked worker processes.

Registration's threads share one interpreter: the pose search of a print is mostly small
NumPy and OpenCV calls, and between them the threads wait on each other for Python's
lock. Measured on a batch of 32 prints of 829 x 993 (seed 778377244's lab 3 of
``benchmarks/bench_registration.py``): one thread 80 s; two threads 57 s (161 % CPU);
the pose searches and the hot-spot search in two forked processes, 48 s (180 % CPU),
with qc.tsv and registration.yaml byte for byte the same.

The template's Powell fits evaluate one objective hundreds of times over the same prints,
a few ms each: too short a task for a pool (``forked_map`` forks per call), and on two
threads it ran slower than on one (Python's lock again). ``ForkedParts`` keeps one forked
process per half of the prints for the whole fit, each holding its prints' scattered dose
between evaluations; only the template's numbers go out and the NCCs come back. Measured
on lab 1 of seed 1487439214 of the registration benchmark (32 prints of 902 x 902, two
threads): the template fits 19.5 -> 9.4 s, the batch 43.4 -> 33.6 s, qc.tsv and
registration.yaml byte for byte the same.

A forked child inherits the parent's memory, so the work may be any callable (a closure
over the batch's images, its template, its settings): only each item's index goes to a
child and only its result comes back, pickled. Fork, not spawn: spawn would import the
caller's main module again in every child and pickle every image. ``concurrent.futures``'
``ProcessPoolExecutor``, not ``multiprocessing.Pool``: a child that dies (out of memory)
breaks the pool with an error instead of leaving its item waiting forever.

What a callable may do in a child: compute and log. What it must not: change state of
this process that the caller reads afterwards (a set it adds to, an object it alters in
place: the change stays in the child; a cache it fills is only refilled here later), or
hand work to this process's thread pool (its threads do not exist in the child). The
caller's other threads must be idle when it calls (a lock one of them held at the fork
would stay held in the child). Registration runs OpenBLAS and OpenCV on one thread
each while it forks (``batch.one_library_thread``): a child computes each item alone,
as one registration thread does, and the results are those of one thread, whatever the
number of processes. A child must not change the libraries' threads itself: in a child
of a process whose OpenCV had run on two threads, ``cv2.setNumThreads(1)`` waited
forever on the parent's OpenCV workers, which the child does not have (seen in the test
suite; ``tests/test_parallel.py`` runs OpenCV in children of such a process).

The children run no PyTorch: a forked child that uses OpenMP after its parent's OpenMP
threads have run can hang (``fitting.Refits`` spawns for that reason), but registration's
libraries are OpenCV (pthreads), OpenBLAS (which forks safely) and pocketfft. Fork is
used on Linux only, and named (it is not every platform's safe default: macOS, Windows,
and Python 3.14's default start method on Linux is forkserver); elsewhere, where
processes cannot be started and where a child dies, the fallback map does the work.
"""

from __future__ import annotations

import logging
import multiprocessing
import sys
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool

log = logging.getLogger(__name__)

_work = None  # in a child: (the callable, the items), inherited from the parent at the fork


def _set_work(fn, items) -> None:
    global _work
    _work = (fn, items)


def _one(i: int):
    fn, items = _work
    return fn(items[i])


def can_fork() -> bool:
    """Fork is available and safe for registration's libraries (Linux)."""
    return sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()


def forked_map(fn, items, processes: int, fallback=map, done=None) -> list:
    """``[fn(item) for item in items]``, computed in up to ``processes`` forked processes
    (the module's doc says what ``fn`` may do there). ``fallback``: the map that does the
    work where processes do not (one process or item, no fork, a pool that broke); for
    instance a thread pool's. ``done(1)`` is called as each item is done (a progress
    bar), in this process."""
    items = list(items)
    processes = min(int(processes), len(items))
    counted = [0]  # items reported done

    def tick():
        counted[0] += 1
        if done is not None:
            done(1)

    if processes > 1 and can_fork():
        out, ex, futures = [None] * len(items), None, None
        try:
            with warnings.catch_warnings():  # Python 3.12+ warns of a fork with threads; the module's doc says why it is safe
                warnings.filterwarnings("ignore", message=r".*use of fork\(\) may lead to deadlocks", category=DeprecationWarning)
                # the work is handed to the children at the fork (initializer arguments are
                # inherited, not pickled, under fork): only indices and results travel
                ex = ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("fork"), initializer=_set_work,
                                         initargs=(fn, items))
                futures = {ex.submit(_one, i): i for i in range(len(items))}
        except (OSError, NotImplementedError, BrokenProcessPool) as exc:  # no processes to be had (memory, a limit)
            log.warning("registration's worker processes could not start (%s); the work goes on here", exc)
            if ex is not None:
                ex.shutdown(wait=True, cancel_futures=True)
        if futures is not None:
            try:
                for f in as_completed(futures):
                    out[futures[f]] = f.result()  # an error of ``fn`` is raised here, as it would be without processes
                    tick()
                return out
            except BrokenProcessPool as exc:
                log.warning("registration's worker processes stopped (%s); the work goes on here", exc)
            finally:
                ex.shutdown(wait=True, cancel_futures=True)  # on an error, the items not yet started are dropped
    out, reported = [], counted[0]
    for i, r in enumerate(fallback(fn, items)):
        out.append(r)
        if i >= reported:
            tick()
    return out


def _serve(conn, fn, part) -> None:
    """A ``ForkedParts`` child: ``fn(part, arg)`` for each ``arg`` received, until None or
    the parent's end closes; the result, or the error, is sent back."""
    while True:
        try:
            arg = conn.recv()
        except (EOFError, OSError):
            return
        if arg is None:
            return
        try:
            out = (True, fn(part, arg))
        except BaseException as exc:  # raised in the parent (``ForkedParts.__call__``)
            out = (False, exc)
        conn.send(out)


class ForkedParts:
    """``[fn(part, arg) for part in parts]`` for many ``arg`` in turn, each part in its own
    forked process that lives across the calls: a search that evaluates one objective
    many times over the same prints, each evaluation a few ms. Only ``arg`` goes to a
    child and its part's result comes back (pickled, through a pipe: a round trip of well
    under a ms). Each part stays in one process, so what ``fn`` keeps of its part between
    calls (a print's scattered dose while the search moves only the cure's numbers) is
    kept there. ``fn`` may do in a child what ``forked_map``'s may (the module's doc).

    Where processes cannot start (not Linux, one part, a limit) or one stops, the parts
    are computed here by ``fallback`` (a map, as ``forked_map``'s; for instance a thread
    pool's), which ``fn`` must allow for: what it keeps of a part it must be able to
    compute again here. Use as a context manager (the children stop at its end)."""

    def __init__(self, fn, parts, processes: int, fallback=map):
        self.fn, self.parts, self.fallback, self.conns, self.procs = fn, list(parts), fallback, [], []
        if min(int(processes), len(self.parts)) < 2 or not can_fork():
            return
        ctx = multiprocessing.get_context("fork")
        try:
            with warnings.catch_warnings():  # as in ``forked_map``
                warnings.filterwarnings("ignore", message=r".*use of fork\(\) may lead to deadlocks", category=DeprecationWarning)
                for part in self.parts:
                    here, there = ctx.Pipe()
                    p = ctx.Process(target=_serve, args=(there, fn, part), daemon=True)
                    p.start()
                    there.close()  # the child's end is the child's alone: its exit is seen here as EOF
                    self.conns.append(here)
                    self.procs.append(p)
        except OSError as exc:
            log.warning("registration's worker processes could not start (%s); the work goes on here", exc)
            self.close()

    def __call__(self, arg) -> list:
        if self.conns:
            try:
                for c in self.conns:
                    c.send(arg)
                outs = [c.recv() for c in self.conns]
            except (EOFError, OSError) as exc:
                log.warning("registration's worker processes stopped (%s); the work goes on here", exc or "no reply")
                self.close()
            else:
                for ok, value in outs:
                    if not ok:
                        raise value
                return [value for _, value in outs]
        return list(self.fallback(lambda part: self.fn(part, arg), self.parts))

    def close(self) -> None:
        for c in self.conns:
            try:
                c.send(None)
            except OSError:
                pass
            c.close()
        for p in self.procs:
            p.join(timeout=5)
            if p.is_alive():
                p.terminate()
                p.join()
        self.conns, self.procs = [], []

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
