"""Independent pieces of work (MRI stations, forearm stacks) in forked worker processes.

The slice-wise rules are pure Python/numpy loops over slices that hold the GIL,
so threads do not help; each station or stack is independent of the others, so
processes do. Workers are forked: they inherit the caller's data (volumes,
skeletons) without pickling it, and only their results travel back.

``BONECAP_WORKERS`` sets the number of processes (1: everything in this
process, e.g. inside a multi-threaded host or a debugger); the default is the
number of CPUs, at most 4. Where ``fork`` is not available (Windows, macOS'
default) or inside a daemonic process, the work runs serially.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Callable, Iterable
from typing import Any

__all__ = ["fork_map", "default_workers"]

_JOB: tuple | None = None


def default_workers() -> int:
    """``BONECAP_WORKERS`` or the number of CPUs, at most 4."""
    return int(os.environ.get("BONECAP_WORKERS", "0")) or min(os.cpu_count() or 1, 4)


def _run(i: int):
    fn, items = _JOB
    try:
        return True, fn(items[i])
    except Exception as exc:  # travels back and is raised in the parent
        try:
            pickle.dumps(exc)
        except Exception:
            exc = RuntimeError(f"{type(exc).__name__}: {exc}")
        return False, exc


def fork_map(fn: Callable[[Any], Any], items: Iterable[Any], workers: int | None = None) -> list:
    """``[fn(x) for x in items]``, in forked processes where there are several CPUs.

    Parameters
    ----------
    fn : callable
        Any callable, closures included (it is inherited by the fork, not
        pickled); its results must be picklable.
    items : iterable
    workers : int, optional
        Number of processes (default :func:`default_workers`).

    Returns
    -------
    list
        The results in the order of ``items``. The first item whose ``fn``
        raised raises the same exception here.
    """
    global _JOB
    items = list(items)
    workers = default_workers() if workers is None else int(workers)
    pool = None
    if workers > 1 and len(items) > 1 and _JOB is None:   # no nesting
        try:
            import multiprocessing as mp

            if mp.current_process().daemon:
                raise RuntimeError("daemonic processes cannot have children")
            _JOB = (fn, items)
            pool = mp.get_context("fork").Pool(min(workers, len(items)))
        except Exception:                      # no fork here: one after the other
            pool, _JOB = None, None
    if pool is None:
        return [fn(x) for x in items]
    try:
        out = pool.map(_run, range(len(items)), chunksize=1)
    finally:
        pool.terminate()
        pool.join()
        _JOB = None
    for ok, res in out:
        if not ok:
            raise res
    return [res for _, res in out]
