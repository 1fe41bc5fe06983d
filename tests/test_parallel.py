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
