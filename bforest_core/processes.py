"""Kernel utilities for helper processes: how long they live and where they may run.

Shared by the executors' workers and the report's second process. A helper ends with the process
that started it however that ends (:func:`bind_to_owner`: the parent death signal on Linux, and a
thread watching the owner everywhere); the cores a process may run on are its CPU affinity
(:func:`available_cores`); a fit's search runs on one BLAS thread (:func:`one_blas_thread`), so
its answer does not depend on the cores, and a worker among others on one for good
(:func:`one_thread_process`).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

from threadpoolctl import threadpool_limits


def _exit_with(owner: int, every: float = 1.0) -> None:
    """End this process when ``owner`` is gone, checked by a daemon thread every ``every`` seconds.

    A pool's workers hold both ends of its task queue, so a killed owner (SIGKILL, an out-of-memory
    kill, a closed terminal) never gives them an end of file: without this they would wait for
    tasks for ever, each holding its target tree in memory.
    """

    def watch():
        while True:
            time.sleep(every)
            try:
                os.kill(owner, 0)
            except (ProcessLookupError, PermissionError):  # gone (or its number now another user's)
                os._exit(1)

    threading.Thread(target=watch, name="bforest-owner-watch", daemon=True).start()


def _die_with_parent() -> None:
    """Ask the kernel to SIGKILL this process when its parent ends (Linux only).

    Unlike the watching thread, this also ends a worker stuck in C code that holds the
    interpreter lock.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def release_forkserver() -> None:
    """Let go of the forkserver's "alive" pipe, which every child of a forkserver holds.

    While any worker held it, the server (the worker's parent) outlived a killed owner, and so the
    parent death signal never came. Without it the server ends with its owner, and then the worker.
    """
    try:
        from multiprocessing import forkserver

        server = forkserver._forkserver
        fd = getattr(server, "_forkserver_alive_fd", None)
        if fd is not None:
            server._forkserver_alive_fd = None
            os.close(fd)
    except (ImportError, AttributeError, OSError):
        pass


def bind_to_owner(owner: int) -> None:
    """End this helper process with the process that started it, however that ends.

    Parameters
    ----------
    owner : int
        The process id of the owner. The parent death signal (Linux) and a thread watching the
        owner (everywhere) end this process when the owner is gone. A worker of the ``process``
        executor and the report's second process call it first thing.
    """
    _die_with_parent()
    if os.name == "posix":
        _exit_with(owner)


def one_blas_thread():
    """Return a context in which BLAS and OpenMP run on one thread.

    A fit's search runs in it, wherever it runs. An optimiser's linear algebra (eigendecompositions,
    least squares over its archive) rounds otherwise with the number of threads: the same SOT fit
    in a process of 2 BLAS threads and in a Dask worker of one parted at the last digit after about
    900 evaluations, and ended on other answers.

    Returns
    -------
    threadpoolctl.threadpool_limits
        A context manager; the limit ends with the block.
    """
    return threadpool_limits(limits=1)


#: the thread-count variables of the BLAS and OpenMP libraries numpy and scipy may use
THREAD_VARIABLES = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "BLIS_NUM_THREADS",
)


def one_thread_process() -> None:
    """Limit this process, and the processes it starts, to one BLAS/OpenMP thread for good.

    A worker among others that together keep every core busy: its own thread pools would only
    compete with the other workers. The variables reach its children; the limit on the libraries
    already loaded holds from now on (:func:`one_blas_thread` limits one block instead).
    """
    for v in THREAD_VARIABLES:
        os.environ[v] = "1"
    threadpool_limits(limits=1)


def available_cores() -> int:
    """Return the cores this process may run on (its CPU affinity on Linux, else the machine's)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1
