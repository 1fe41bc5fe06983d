"""bonecap.parallel.fork_map: order, closures, errors, the serial fallback."""

from __future__ import annotations

import os

import numpy as np
import pytest

from bonecap.errors import DataError
from bonecap.parallel import fork_map


def test_results_in_order_from_other_processes():
    big = np.arange(1000.0)          # inherited by the fork, not pickled

    def work(i):
        return i, float(big[i] * 2), os.getpid()

    out = fork_map(work, range(6), workers=2)
    assert [o[0] for o in out] == list(range(6)) and [o[1] for o in out] == [2.0 * i for i in range(6)]
    assert any(pid != os.getpid() for *_, pid in out)


def test_an_error_in_a_worker_is_raised_here():
    def work(i):
        if i == 3:
            raise DataError("no ulna in this stack", f"stack_{i}")
        return i

    with pytest.raises(DataError, match="stack_3: no ulna"):
        fork_map(work, range(5), workers=2)


def test_unpicklable_error_still_says_what_happened():
    class Local(Exception):            # a local class cannot be pickled back
        pass

    def work(i):
        raise Local(f"bad item {i}")

    with pytest.raises(Exception, match="bad item 0"):
        fork_map(work, range(2), workers=2)


def test_one_worker_runs_here(monkeypatch):
    monkeypatch.setenv("BONECAP_WORKERS", "1")
    assert {pid for pid in fork_map(lambda i: os.getpid(), range(3))} == {os.getpid()}


def test_no_nesting():
    inner = fork_map(lambda i: fork_map(lambda j: os.getpid(), range(3), workers=2), range(2), workers=2)
    for pids in inner:                 # each worker ran its inner map itself
        assert len(set(pids)) == 1


def test_fork_start_runs_beside_the_caller_on_a_snapshot():
    """The workers start at once and see the caller's data as it was then; the caller goes on (and may
    run a fork_map of its own meanwhile); result() gives the results in order."""
    import time

    from bonecap.parallel import fork_start

    data = {"x": 1.0}

    def work(i):
        time.sleep(0.3)
        return i, data["x"], os.getpid()

    t0 = time.perf_counter()
    pending = fork_start(work, range(3), workers=3)
    data["x"] = 2.0                                   # after the fork: the workers keep 1.0
    inner = fork_map(lambda i: i * i, range(4), workers=2)
    out = pending.result()
    assert inner == [0, 1, 4, 9]
    assert [o[0] for o in out] == [0, 1, 2] and all(o[1] == 1.0 for o in out)
    assert all(o[2] != os.getpid() for o in out)
    assert time.perf_counter() - t0 < 0.85          # three 0.3 s items at once, not one after the other
    assert pending.result() is out                    # asked twice: the same list


def test_fork_start_serial_runs_at_result_and_close_drops_the_work(monkeypatch):
    from bonecap.parallel import fork_start

    calls = []
    monkeypatch.setenv("BONECAP_WORKERS", "1")
    pending = fork_start(lambda i: calls.append(i) or i, range(3))
    assert calls == []                                # nothing ran yet: the caller's work comes first
    assert pending.result() == [0, 1, 2] and calls == [0, 1, 2]
    monkeypatch.delenv("BONECAP_WORKERS")
    stopped = fork_start(lambda i: (_ for _ in ()).throw(DataError("never seen")), range(2), workers=2)
    stopped.close()                                   # an error elsewhere: the workers are stopped
    with pytest.raises(DataError, match="never seen"):
        stopped.result()                              # asked anyway: the work is done here, errors and all
    # cancel(), as fork_child's join has it (build-subject stops either kind alike when it fails)
    cancelled = fork_start(lambda i: i, range(2), workers=2)
    assert cancelled._pool is not None
    cancelled.cancel()
    assert cancelled._pool is None and cancelled.result() == [0, 1]


def test_workers_run_blas_single_threaded():
    from threadpoolctl import threadpool_info

    def blas_threads(_):
        return max((d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"), default=1)

    assert fork_map(blas_threads, range(2), workers=2) == [1, 1]


def test_fork_child_returns_its_result_raises_its_error_and_may_fork_workers():
    """fork_child runs one function in a child on a snapshot of the caller's data; its result comes
    back, its error is raised here; a non-daemonic child may fork a pool of its own (the skeleton's
    meshing parent does)."""
    from bonecap.parallel import fork_child

    data = {"x": np.arange(4.0)}
    join = fork_child(lambda: (os.getpid(), data["x"] * 2))
    data["x"] = None                                   # after the fork: the child keeps its copy
    pid, doubled = join()
    assert pid != os.getpid() and np.array_equal(doubled, [0.0, 2.0, 4.0, 6.0])
    # the objects were frozen for the fork only: this process's collector has them back
    import gc

    assert gc.get_freeze_count() == 0
    assert fork_child(gc.get_freeze_count)() > 0      # the child's collector leaves the shared pages alone
    gc.freeze()                                        # a caller's own freeze is left as it was
    try:
        frozen = gc.get_freeze_count()
        fork_child(gc.get_freeze_count)()
        assert gc.get_freeze_count() > 0.9 * frozen    # still frozen here (less what died meanwhile)
    finally:
        gc.unfreeze()

    def boom():
        raise DataError("no capsule", "stack_2")

    with pytest.raises(DataError, match="stack_2: no capsule"):
        fork_child(boom)()

    def parent():
        import multiprocessing as mp

        with mp.get_context("fork").Pool(2) as pool:
            return os.getpid(), set(pool.map(_pid_of, range(8), chunksize=1))

    me, workers = fork_child(parent, daemon=False)()
    assert me != os.getpid() and me not in workers and os.getpid() not in workers


def _pid_of(_):
    return os.getpid()


def test_fork_child_cancel_stops_a_child_the_caller_no_longer_waits_for():
    """A child whose result is larger than the pipe's buffer waits in send() until joined; a caller
    that failed meanwhile cancels it instead, and the child is gone."""
    import time

    from bonecap.parallel import fork_child

    join = fork_child(lambda: (os.getpid(), np.zeros(1_000_000)))
    time.sleep(0.5)
    join.cancel()
    import multiprocessing as mp

    assert not [p for p in mp.active_children() if p.is_alive()]
