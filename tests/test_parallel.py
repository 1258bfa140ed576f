"""Registration's forked worker processes (``unscatter.imaging.parallel``)."""

import logging
import os

import numpy as np
import pytest

from unscatter.imaging.parallel import ForkedParts, can_fork, forked_map

needs_fork = pytest.mark.skipif(not can_fork(), reason="fork is registration's only on Linux")


@needs_fork
def test_a_closure_runs_in_child_processes_and_its_results_come_back_in_order():
    image = np.arange(12.0).reshape(3, 4)  # closed over, inherited at the fork, never pickled
    parent = os.getpid()
    ticks = []
    out = forked_map(lambda i: (i, float(image[i].sum()), os.getpid()), [2, 0, 1, 2], 2, done=ticks.append)
    assert [(i, s) for i, s, _ in out] == [(2, 38.0), (0, 6.0), (1, 22.0), (2, 38.0)]
    assert all(pid != parent for _, _, pid in out)
    assert ticks == [1] * 4


@needs_fork
def test_an_error_in_a_child_reaches_the_caller():
    def fn(i):
        if i == 3:
            raise ValueError(f"print {i} is odd")
        return i

    with pytest.raises(ValueError, match="print 3 is odd"):
        forked_map(fn, range(6), 2)


@needs_fork
def test_a_child_that_dies_leaves_the_work_to_the_fallback(caplog):
    parent = os.getpid()

    def fn(i):
        if os.getpid() != parent:
            os._exit(1)  # as a child killed for memory
        return 10 * i

    ticks = []
    with caplog.at_level(logging.WARNING, logger="unscatter.imaging.parallel"):
        out = forked_map(fn, range(5), 2, fallback=map, done=ticks.append)
    assert out == [0, 10, 20, 30, 40]
    assert len(ticks) == 5  # each item counted once
    assert "worker processes stopped" in caplog.text


def test_one_process_works_here():
    parent = os.getpid()
    assert forked_map(lambda i: (i * i, os.getpid()), range(4), 1) == [(i * i, parent) for i in range(4)]


def test_without_fork_the_fallback_does_the_work(monkeypatch):
    import unscatter.imaging.parallel as parallel
    from concurrent.futures import ThreadPoolExecutor

    monkeypatch.setattr(parallel, "can_fork", lambda: False)
    parent, ticks = os.getpid(), []
    with ThreadPoolExecutor(2) as ex:
        out = parallel.forked_map(lambda i: (i + 1, os.getpid()), range(5), 2, fallback=ex.map, done=ticks.append)
    assert out == [(i + 1, parent) for i in range(5)]
    assert ticks == [1] * 5


@needs_fork
def test_processes_that_cannot_start_leave_the_work_to_the_fallback(monkeypatch, caplog):
    import unscatter.imaging.parallel as parallel

    def no_processes(*args, **kw):
        raise OSError(12, "Cannot allocate memory")

    monkeypatch.setattr(parallel, "ProcessPoolExecutor", no_processes)
    with caplog.at_level(logging.WARNING, logger="unscatter.imaging.parallel"):
        assert parallel.forked_map(lambda i: 2 * i, range(4), 2) == [0, 2, 4, 6]
    assert "could not start" in caplog.text


@needs_fork
def test_each_part_stays_in_its_own_child_and_keeps_what_it_kept_across_calls():
    """``ForkedParts``: what ``fn`` keeps of a part (a print's scattered dose) is kept in
    the child that holds the part, call after call; results come back in part order."""
    parent = os.getpid()
    kept = {}

    def fn(part, arg):
        kept.setdefault(part, []).append(arg)  # in the child's copy of ``kept``
        return part, sum(kept[part]), os.getpid()

    with ForkedParts(fn, ["a", "b"], 2) as forked:
        assert forked.conns
        runs = [forked(k) for k in (1, 2, 3)]
    assert [[(p, s) for p, s, _ in r] for r in runs] == [[("a", 1), ("b", 1)], [("a", 3), ("b", 3)], [("a", 6), ("b", 6)]]
    pids = [[pid for _, _, pid in r] for r in runs]
    assert all(pid != parent for r in pids for pid in r) and pids[0][0] != pids[0][1]
    assert pids[0] == pids[1] == pids[2]  # each part in one process throughout
    assert kept == {}  # nothing changed here


@needs_fork
def test_an_error_in_a_part_reaches_the_caller_and_the_children_go_on():
    def fn(part, arg):
        if part == 1 and arg == "bad":
            raise ValueError(f"part {part} cannot take {arg}")
        return (part, arg)

    with ForkedParts(fn, [0, 1], 2) as forked:
        with pytest.raises(ValueError, match="part 1 cannot take bad"):
            forked("bad")
        assert forked("good") == [(0, "good"), (1, "good")]


@needs_fork
def test_a_part_whose_child_dies_is_computed_here(caplog):
    parent = os.getpid()

    def fn(part, arg):
        if os.getpid() != parent and arg == 2:
            os._exit(1)  # as a child killed for memory
        return 10 * part + arg

    with caplog.at_level(logging.WARNING, logger="unscatter.imaging.parallel"):
        with ForkedParts(fn, [1, 2], 2) as forked:
            assert forked(1) == [11, 21]
            assert forked(2) == [12, 22]
            assert not forked.conns and forked(3) == [13, 23]
    assert "worker processes stopped" in caplog.text


def test_one_part_or_process_is_computed_here():
    parent = os.getpid()
    for parts, processes in (([5], 2), ([5, 6], 1)):
        with ForkedParts(lambda part, arg: (part + arg, os.getpid()), parts, processes) as forked:
            assert not forked.conns
            assert forked(1) == [(p + 1, parent) for p in parts]


@needs_fork
def test_children_use_opencv_after_the_parents_opencv_threads_ran():
    """OpenCV has blurred on two threads in this process (its worker threads exist), and
    the children blur too, with the same sums. A child that set OpenCV's threads itself
    waited forever on the parent's workers. Run in a fresh interpreter with a time
    limit, so that a child that waits fails the test instead of stalling the suite."""
    import subprocess
    import sys

    code = (
        "import cv2, numpy as np\n"
        "from unscatter.imaging.parallel import forked_map\n"
        "cv2.setNumThreads(2)\n"
        "a = np.random.default_rng(0).random((1024, 1024)).astype(np.float32)\n"
        "ref = [float(cv2.GaussianBlur(a, (0, 0), s).sum()) for s in (1, 2, 3, 4)]\n"
        "out = forked_map(lambda s: float(cv2.GaussianBlur(a, (0, 0), s).sum()), [1, 2, 3, 4], 2)\n"
        "assert out == ref, (out, ref)\n"
        "assert cv2.getNumThreads() == 2\n"
        "print('ok')\n"
    )
    try:
        run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("a forked child that runs OpenCV waited on its parent's OpenCV threads")
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr
