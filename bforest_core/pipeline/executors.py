"""The ``serial`` and ``process`` executors.

Results never depend on the executor or on the number of workers: every evaluation carries its
own seed (derived from the run seed and the evaluation index by the objective), and workers hold
no random state.
"""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os

from pydantic import Field

from ..interfaces import ComponentSettings, Executor

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
                "VECLIB_MAXIMUM_THREADS", "BLIS_NUM_THREADS")


def limit_threads() -> None:
    """One BLAS/OpenMP thread in this process (a worker of a pool)."""
    for v in _THREAD_VARS:
        os.environ[v] = "1"
    try:  # effective even after numpy is imported, when threadpoolctl is present
        from threadpoolctl import threadpool_limits
        threadpool_limits(1)
    except Exception:
        pass


def _exit_with(owner: int, every: float = 1.0) -> None:
    """End this worker when the process that owns its pool is gone.

    A pool's workers hold both ends of its task queue, so a killed owner (SIGKILL, an out-of-memory
    kill, a closed terminal) never gives them an end of file: without this they would wait for
    tasks for ever, each holding its target tree in memory. A daemon thread checks the owner every
    ``every`` seconds."""
    import threading
    import time

    def watch():
        while True:
            time.sleep(every)
            try:
                os.kill(owner, 0)
            except (ProcessLookupError, PermissionError):  # gone (or its number now another user's)
                os._exit(1)

    threading.Thread(target=watch, name="bforest-owner-watch", daemon=True).start()


def _worker_init(initializer, initargs, owner=None):
    limit_threads()
    if owner is not None and os.name == "posix":
        _exit_with(owner)
    if initializer is not None:
        initializer(*initargs)


class SerialExecutor(Executor):
    """Evaluates in the calling process, one item after another."""

    name = "serial"
    summary = "in-process, one evaluation at a time"

    def start(self, initializer=None, initargs=()):
        if initializer is not None:
            initializer(*initargs)

    def map_unordered(self, fn, items):
        for i, it in enumerate(items):
            yield i, fn(it)


class ProcessSettings(ComponentSettings):
    workers: int = Field(default_factory=lambda: max(1, os.cpu_count() or 1), ge=1,
                         description="number of worker processes (default: all cores)")
    start_method: str = Field("spawn" if os.name == "nt" else "forkserver",
                              description="multiprocessing start method: fork, spawn or forkserver")


class ProcessExecutor(Executor):
    """A pool of worker processes (``concurrent.futures.ProcessPoolExecutor``).

    The initializer runs once per worker, so the target tree and its data sets are loaded once
    per worker, and each worker uses one BLAS/OpenMP thread.
    """

    name = "process"
    summary = "local worker processes (one BLAS thread each)"
    Settings = ProcessSettings

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self._pool = None

    @property
    def workers(self) -> int:
        return self.settings.workers

    def start(self, initializer=None, initargs=()):
        ctx = mp.get_context(self.settings.start_method)
        self._pool = cf.ProcessPoolExecutor(max_workers=self.settings.workers, mp_context=ctx,
                                            initializer=_worker_init, initargs=(initializer, initargs, os.getpid()))

    def map_unordered(self, fn, items):
        if self._pool is None:
            raise RuntimeError("executor not started (use executor.started(...))")
        futs = {self._pool.submit(fn, it): i for i, it in enumerate(items)}
        try:
            for f in cf.as_completed(futs):
                yield futs[f], f.result()
        finally:
            for f in futs:
                f.cancel()

    def shutdown(self):
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
