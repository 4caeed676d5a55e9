"""The ``serial`` and ``process`` executors.

Results never depend on the executor or on the number of workers: every evaluation carries its
own seed (derived from the run seed and the evaluation index by the objective), and workers hold
no random state.

The ``process`` executor contains what a plugin can do to a worker: a task whose worker dies
(a segfault, ``os.abort``, ``os._exit``) or runs past its time limit (a simulation stuck in C,
where the worker's own alarm cannot reach it) costs that task only: the worker is killed and
replaced, and the task's result is what the executor's ``on_lost`` hook makes of it (the
objective makes a failed evaluation of it). An exception that cannot be pickled comes back as
text (:class:`WorkerError`). Every worker dies with its owner (``PR_SET_PDEATHSIG`` on Linux,
and a thread watching the owner everywhere).
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
import os
import pickle
import signal
import time
import warnings
from collections import deque
from multiprocessing.connection import wait as _wait
from typing import Literal

from pydantic import Field

from ..errors import BayesForestError
from ..interfaces import ComponentSettings, Executor
from ..processes import available_cores, bind_to_owner, release_forkserver


class WorkerLost(BayesForestError):
    """A worker process died, or was stopped past its time limit, while running a task that has
    no stand-in result (the executor's ``on_lost`` hook gave none), or while starting."""


class WorkerError(BayesForestError):
    """An exception raised in a worker that could not be sent back as itself (it could not be
    pickled): its type name and message as text."""


def _worker_init(initializer, initargs):
    Executor.worker_setup()
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
    workers: int = Field(
        default_factory=lambda: max(1, os.cpu_count() or 1),
        ge=1,
        le=1024,
        description="number of worker processes (default: all cores; at most the cores there are: "
        "more would only wait their turn, each holding the target in memory)",
    )
    start_method: Literal["fork", "spawn", "forkserver"] = Field(
        "spawn" if os.name == "nt" else "forkserver",
        description="multiprocessing start method: fork, spawn or forkserver",
    )


def _portable(exc: BaseException) -> BaseException:
    """``exc`` if it survives pickling, else a :class:`WorkerError` holding its text."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return WorkerError(f"{type(exc).__name__}: {exc}")


def _worker_main(conn, initializer, initargs, owner) -> None:
    """A worker's life: start-up, then tasks ``(seq, fn, item)`` until ``None`` or end of file.
    Every exception of a task (``SystemExit`` too) goes back to the owner; the worker stays."""
    bind_to_owner(owner)
    release_forkserver()
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the owner's to handle (it stops us)
        _worker_init(initializer, initargs)
    except BaseException as exc:  # noqa: BLE001 - a plugin's start-up may raise anything
        _send(conn, ("init-error", None, _portable(exc)))
        return
    if not _send(conn, ("ready", None, None)):
        return
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        seq, fn, item = msg
        try:
            out = ("ok", seq, fn(item))
        except BaseException as exc:  # noqa: BLE001 - sys.exit() in a plugin must not end the worker
            out = ("error", seq, _portable(exc))
        try:
            sent = _send(conn, out)
        except Exception as exc:  # a result that cannot be pickled
            sent = _send(
                conn, ("error", seq, WorkerError(f"the result could not be sent back: {type(exc).__name__}: {exc}"))
            )
        if not sent:
            return


def _send(conn, message) -> bool:
    """Send ``message`` to the owner; False when the owner has gone (it was stopped and closed
    its end): the worker then ends quietly, no ``BrokenPipeError`` traceback on the terminal."""
    try:
        conn.send(message)
    except (BrokenPipeError, ConnectionResetError, EOFError):
        return False
    return True


def _death_text(exitcode) -> str:
    if exitcode is None:
        return "ended"
    if exitcode < 0:
        try:
            return f"killed by signal {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exited with code {exitcode}"


class _Worker:
    """One worker process and the pipe to it; ``task`` is ``(seq, index, started, limit)``
    while it runs one (``index`` None: a task of an abandoned map, whose result is dropped)."""

    def __init__(self, ctx, initializer, initargs):
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(
            target=_worker_main, args=(child, initializer, initargs, os.getpid()), daemon=True, name="bforest-worker"
        )
        self.proc.start()
        child.close()
        self.ready = False
        self.task = None

    def kill(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join(5)
        self.conn.close()


class ProcessExecutor(Executor):
    """A pool of worker processes, each started with the initializer.

    The initializer runs once per worker, so the target tree and its data sets are loaded once
    per worker, and each worker uses one BLAS/OpenMP thread. A worker that dies or runs past
    ``time_limit(item)`` seconds is replaced, and its task ends as ``on_lost(fn, item, status,
    message)`` makes it (status ``"crashed"`` or ``"timeout"``); without a hook (or when the hook
    returns :data:`NotImplemented`) :class:`WorkerLost` is raised.
    """

    name = "process"
    summary = "local worker processes (one BLAS thread each)"
    Settings = ProcessSettings

    #: how many workers in a row may die while starting before the pool gives up
    MAX_START_DEATHS = 3

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self._workers = None
        self.time_limit = None  # item -> seconds or None (set by whoever knows the tasks)
        self.on_lost = None  # (fn, item, status, message) -> stand-in result

    def __getstate__(self):
        return {**self.__dict__, "_workers": None, "time_limit": None, "on_lost": None}

    @property
    def workers(self) -> int:
        """The workers started: ``workers``, or the cores there are when that is fewer."""
        return min(self.settings.workers, available_cores())

    def start(self, initializer=None, initargs=()):
        if self.settings.workers > self.workers:
            warnings.warn(
                f"executor.workers = {self.settings.workers} is more than the {self.workers} cores here: "
                f"{self.workers} workers are started (the results are the same)",
                stacklevel=2,
            )
        self._ctx = mp.get_context(self.settings.start_method)
        self._init = (initializer, initargs)
        self._seq = itertools.count()
        self._start_deaths = 0
        self._workers = [self._spawn() for _ in range(self.workers)]

    def _spawn(self) -> _Worker:
        return _Worker(self._ctx, *self._init)

    def _replace(self, w: _Worker) -> None:
        w.kill()
        if not w.ready:
            self._start_deaths += 1
            if self._start_deaths >= self.MAX_START_DEATHS:
                raise WorkerLost(
                    f"worker processes die while starting ({_death_text(w.proc.exitcode)}, "
                    f"{self._start_deaths} in a row); a plugin's start-up crashes"
                )
        self._workers[self._workers.index(w)] = self._spawn()

    def _lost(self, fn, item, status, message):
        res = NotImplemented if self.on_lost is None else self.on_lost(fn, item, status, message)
        if res is NotImplemented:
            raise WorkerLost(f"{message} (task {getattr(fn, '__name__', fn)})")
        return res

    def map_unordered(self, fn, items):
        if self._workers is None:
            raise RuntimeError("executor not started (use executor.started(...))")
        items = list(items)
        queue, done = deque(range(len(items))), 0
        name = getattr(fn, "__name__", "task")
        try:
            while done < len(items):
                for w in self._workers:  # hand out work
                    if queue and w.ready and w.task is None and w.proc.is_alive():
                        i = queue.popleft()
                        seq = next(self._seq)
                        try:
                            w.conn.send((seq, fn, items[i]))
                        except (BrokenPipeError, EOFError, ConnectionError):
                            queue.appendleft(i)  # it died idle: replaced below, the task goes to another
                            continue
                        limit = self.time_limit(items[i]) if self.time_limit is not None else None
                        w.task = (seq, i, time.monotonic(), limit)
                now = time.monotonic()
                ends = [w.task[2] + w.task[3] - now for w in self._workers if w.task and w.task[3] is not None]
                waits = {w.conn: w for w in self._workers}
                waits.update({w.proc.sentinel: w for w in self._workers})
                ready = _wait(list(waits), timeout=max(0.0, min(ends)) if ends else None)
                for w in list({id(waits[r]): waits[r] for r in ready}.values()):
                    messages, dead = [], False
                    try:
                        while w.conn.poll():
                            messages.append(w.conn.recv())
                    except (EOFError, OSError):
                        dead = True
                    for kind, seq, payload in messages:
                        if kind == "ready":
                            w.ready, self._start_deaths = True, 0
                        elif kind == "init-error":
                            raise payload
                        elif w.task is not None and seq == w.task[0]:
                            i, w.task = w.task[1], None
                            if i is None:
                                continue  # an abandoned map's task
                            if kind == "error":
                                raise payload
                            done += 1
                            yield i, payload
                    if dead or not w.proc.is_alive():
                        w.proc.join(5)
                        task = w.task
                        if task is not None and task[1] is not None:
                            done += 1
                            msg = (
                                f"the worker process {_death_text(w.proc.exitcode)} while running {name}; "
                                "it was replaced"
                            )
                            yield task[1], self._lost(fn, items[task[1]], "crashed", msg)
                        self._replace(w)
                now = time.monotonic()
                for w in list(self._workers):  # tasks past their limit: stop the worker
                    if w.task and w.task[3] is not None and now - w.task[2] > w.task[3]:
                        task = w.task
                        w.task = None
                        self._replace(w)
                        if task[1] is not None:
                            done += 1
                            msg = (
                                f"still running after {task[3]:g} s (stuck outside Python?); its worker "
                                "was stopped and replaced"
                            )
                            yield task[1], self._lost(fn, items[task[1]], "timeout", msg)
        finally:  # the caller stopped early or a task raised: results still to come are dropped
            for w in self._workers or []:
                if w.task is not None:
                    w.task = (w.task[0], None, w.task[2], w.task[3])

    def shutdown(self):
        if self._workers is None:
            return
        workers, self._workers = self._workers, None
        for w in workers:
            try:
                if w.task is None:
                    w.conn.send(None)
            except (OSError, ValueError):
                pass
        deadline = time.monotonic() + 2.0
        for w in workers:
            if w.task is None:
                w.proc.join(max(0.0, deadline - time.monotonic()))
            w.kill()  # a worker still busy (or slow to end) is stopped
