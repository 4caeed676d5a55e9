"""The user's own stop: Ctrl-C (SIGINT) or SIGTERM, told apart from a plugin's exceptions.

While :func:`user_stops` holds (every ``bforest`` command holds it; :func:`stoppable` gives it to
the pipeline stages that run plugin code in this process, for a caller from Python), SIGINT and
SIGTERM raise :class:`Stopped` in the main thread. The scoring code lets only the user's stop
through (:func:`users_stop`): a ``KeyboardInterrupt`` or any other ``BaseException`` a plugin
raises costs its evaluation, never the fit. As the stop unwinds, every process a command started
is stopped with it (the executors' workers, the report's second process), and a helper process
that outlives its owner anyway (``kill -9``) ends itself (:func:`~bforest_core.processes.bind_to_owner`).
"""

from __future__ import annotations

import contextlib
import functools
import signal
import threading

#: the signals a user stops a command with, and the exit code of each (128 + its number)
SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Stopped(KeyboardInterrupt):
    """The user stopped the command (Ctrl-C or SIGTERM): ``signum`` says which."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)


def _stop(signum, frame):
    raise Stopped(signum)


def _defaults() -> dict:
    """The handlers a stop replaces: Python's own (a signal the caller chose to ignore, as
    ``nohup`` does, stays ignored)."""
    return {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}


@contextlib.contextmanager
def user_stops():
    """SIGINT and SIGTERM raise :class:`Stopped` for the ``with`` block (in the main thread; a
    no-op in another thread, or when the block is already held)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.getsignal(s) for s in SIGNALS}
    mine = [s for s in SIGNALS if old[s] is _defaults()[s]]
    for s in mine:
        signal.signal(s, _stop)
    try:
        yield
    finally:
        for s in mine:
            signal.signal(s, old[s])


def stoppable(fn):
    """Decorate a pipeline stage that runs plugin code in this process: it runs under
    :func:`user_stops`, so a plugin's own ``KeyboardInterrupt`` is never taken for the user's."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with user_stops():
            return fn(*args, **kwargs)

    return wrapper


def users_stop(exc: BaseException) -> bool:
    """Whether ``exc`` is the user's stop, which must end the command, rather than a plugin's
    fault, which costs one evaluation: a :class:`Stopped`, or a ``KeyboardInterrupt`` where
    SIGINT has a handler other than :func:`user_stops`'s (Python's own, or a host's such as a
    notebook's: there it cannot be told from a plugin's, so it stops). Under :func:`user_stops`
    the user's Ctrl-C is a :class:`Stopped`; a worker process ignores SIGINT and a worker
    thread gets no signals: there a ``KeyboardInterrupt`` is always the plugin's."""
    if isinstance(exc, Stopped):
        return True
    return (
        isinstance(exc, KeyboardInterrupt)
        and threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGINT) not in (_stop, signal.SIG_IGN)
    )
