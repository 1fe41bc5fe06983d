"""Independent pieces of work (MRI stations, forearm stacks) in forked worker processes.

The slice-wise rules are pure Python/numpy loops over slices that hold the GIL,
so threads do not help; each station or stack is independent of the others, so
processes do. Workers are forked: they inherit the caller's data (volumes,
skeletons) without pickling it, and only their results travel back.

``BONECAP_WORKERS`` sets the number of processes (1: everything in this
process, e.g. inside a multi-threaded host or a debugger); the default is the
number of CPUs, at most 4. Where ``fork`` is not available (Windows, macOS'
default) or inside a daemonic process, the work runs serially.

:func:`fork_map` waits for its workers; :func:`fork_start` returns at once so
that the caller works beside them (build-subject places the markers while the
forearm stacks are registered). Each worker runs BLAS on one thread: the
workers fill the cores already.
"""

from __future__ import annotations

import gc
import os
import pickle
from collections.abc import Callable, Iterable
from typing import Any

from threadpoolctl import threadpool_limits

__all__ = ["fork_map", "fork_start", "fork_child", "fork_or_here", "Pending", "default_workers", "one_blas_thread"]

# the jobs whose pools are alive, by id: a worker forked for job k looks its function and items up here
# (inherited with the fork, never pickled); several can be running at once (fork_start)
_JOBS: dict[int, tuple[Callable[[Any], Any], list]] = {}
_NEXT = [0]


def default_workers() -> int:
    """``BONECAP_WORKERS`` or the number of CPUs, at most 4."""
    return int(os.environ.get("BONECAP_WORKERS", "0")) or min(os.cpu_count() or 1, 4)


def one_blas_thread():
    """Context manager: BLAS on one thread, for work in a worker process.

    The workers already fill the cores, and OpenBLAS's threads spin while they
    wait: two workers with two threads each ran the warp's RBF and ICP solves
    1.4x slower on two cores (the same results to 1e-6 mm: only the summation
    order differs). Every worker this package forks runs under it (here, the
    generic skeleton's meshing pool, the phantom's trials child).
    """
    return threadpool_limits(limits=1)


def _run(job_i: tuple[int, int]):
    job, i = job_i
    fn, items = _JOBS[job]
    try:
        with one_blas_thread():
            return True, fn(items[i])
    except Exception as exc:  # travels back and is raised in the parent
        try:
            pickle.dumps(exc)
        except Exception:
            exc = RuntimeError(f"{type(exc).__name__}: {exc}")
        return False, exc


class Pending:
    """Work started by :func:`fork_start`; :meth:`result` waits for it.

    Without worker processes (one CPU, ``BONECAP_WORKERS=1``, no ``fork``, or
    inside a worker) nothing runs until :meth:`result`, which then does the
    work itself, one item after the other.
    """

    def __init__(self, fn: Callable[[Any], Any], items: list, workers: int):
        self._fn, self._items, self._pool, self._async, self._job = fn, items, None, None, None
        self._out: list | None = None
        if workers > 1 and len(items) > 1:
            try:
                import multiprocessing as mp

                if mp.current_process().daemon:      # a worker itself: no nesting
                    raise RuntimeError("daemonic processes cannot have children")
                self._job = _NEXT[0]
                _NEXT[0] += 1
                _JOBS[self._job] = (fn, items)
                # the fork happens here: the workers see the caller's data as it is now
                self._pool = mp.get_context("fork").Pool(min(workers, len(items)))
                self._async = self._pool.map_async(_run, [(self._job, i) for i in range(len(items))],
                                                   chunksize=1)
            except Exception:                         # no fork here: serial, at result()
                self.close()

    def close(self) -> None:
        """Stop the workers, dropping their work (the caller failed meanwhile); :meth:`result`
        closes them itself. A :meth:`result` after this does the work here, one item after the other."""
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
        self._pool = self._async = None
        _JOBS.pop(self._job, None)

    #: The same as :meth:`close`, under the name :func:`fork_child`'s ``join.cancel`` has: a caller
    #: that stops its background work when it fails stops either kind alike.
    cancel = close

    def result(self) -> list:
        """The results in the order of the items; the first item whose function raised raises here."""
        if self._out is None:
            if self._async is None:
                self._out = [self._fn(x) for x in self._items]
            else:
                try:
                    out = self._async.get()
                finally:
                    self.close()
                for ok, res in out:
                    if not ok:
                        raise res
                self._out = [res for _, res in out]
        return self._out


def fork_start(fn: Callable[[Any], Any], items: Iterable[Any], workers: int | None = None) -> Pending:
    """Start ``[fn(x) for x in items]`` in forked processes and return at once.

    The caller goes on with other work while the workers run (build-subject
    places its markers while the forearm stacks are registered); the workers
    see the caller's data as it was when this was called. Same parameters as
    :func:`fork_map`; call :meth:`Pending.result` for the results.
    """
    items = list(items)
    return Pending(fn, items, default_workers() if workers is None else int(workers))


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
    return fork_start(fn, items, workers).result()


def fork_child(fn: Callable[[], Any], *, daemon: bool = True) -> Callable[[], Any]:
    """Start ``fn()`` in one forked child process; return a ``join()`` that waits and gives its result.

    The child inherits the caller's data as it is now (nothing is pickled on the way
    in); only the result comes back, through a pipe. An exception in the child is
    raised again by ``join()``.

    Parameters
    ----------
    fn : callable
        Called without arguments in the child, BLAS on one thread (the caller may
        go on beside it); its result must be picklable.
    daemon : bool
        A daemonic child (default) is killed when the caller exits; a child that
        forks workers of its own must not be one.

    Returns
    -------
    callable
        ``join()``; ``join.cancel()`` stops the child instead (the caller failed
        meanwhile and will not ask for the result).

    Raises
    ------
    RuntimeError
        This process cannot fork (no ``fork`` start method, or a daemonic process itself).
    """
    import multiprocessing as mp

    try:
        ctx = mp.get_context("fork")
    except ValueError:
        raise RuntimeError("no fork start method here") from None
    if mp.current_process().daemon:
        raise RuntimeError("daemonic processes cannot have children")
    recv, send = ctx.Pipe(duplex=False)

    def child():
        try:
            with one_blas_thread():
                result = fn()
            send.send(("ok", result))
        except BaseException as exc:  # noqa: BLE001 - handed to the parent, which raises it
            try:
                send.send(("error", exc))
            except Exception:  # noqa: BLE001 - an exception that does not pickle
                send.send(("error", RuntimeError(f"{type(exc).__name__}: {exc}")))
        finally:
            send.close()

    proc = ctx.Process(target=child, daemon=daemon)
    # The child shares this process's pages until either writes to them. The cyclic collector's
    # passes in the child would write to every object alive now and copy their pages (the phantom's
    # decimation child held ~15 MiB more): frozen, the child's collector leaves them alone. This
    # process's own collector gets them back at once -- unless a caller had frozen objects already
    # (gc.unfreeze() would thaw those too): then only those stay out of the child's passes.
    freeze = gc.get_freeze_count() == 0
    if freeze:
        gc.freeze()
    try:
        proc.start()
    finally:
        if freeze:
            gc.unfreeze()
    send.close()

    def join():
        try:
            status, value = recv.recv()
        except EOFError:
            proc.join()
            raise RuntimeError(f"a worker process died (exit code {proc.exitcode})") from None
        proc.join()
        if status == "error":
            raise value
        return value

    def cancel():
        # a child whose result is larger than the pipe's buffer waits in send() until joined
        if proc.is_alive():
            proc.terminate()
        proc.join()
        recv.close()

    join.cancel = cancel
    return join


def fork_or_here(fn: Callable[[], Any], *, beside: bool = False) -> Callable[[], Any]:
    """:func:`fork_child` where it can and should run, else ``fn()`` here at once; a ``join()`` either way.

    ``fn`` runs here with ``BONECAP_WORKERS=1`` (no child processes, e.g. inside a
    multi-threaded host), where there is no ``fork``, inside a daemonic process, and,
    with ``beside=True`` (the caller means to work while the child runs), on one CPU.
    Without ``beside`` the child is for memory, not speed: what ``fn`` leaves
    allocated (a decimation library's vectors) goes with it.
    """
    env = os.environ.get("BONECAP_WORKERS", "").strip()
    here = env == "1" or (beside and (int(env or "0") or os.cpu_count() or 1) < 2)
    if not here:
        try:
            return fork_child(fn)
        except RuntimeError:
            pass
    result = fn()
    return lambda: result
