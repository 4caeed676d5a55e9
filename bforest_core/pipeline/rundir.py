"""Ownership and clean-up of a run directory.

A run directory is owned by one process at a time: :func:`run_lock` takes an OS lock
(``fcntl.flock``) on ``RUN/.bforest.lock`` for the whole command (fit, resume, clones, demo), and a
second process asking for it gets a :class:`RunDirError` naming the holder (its pid and command).
The lock is the kernel's: it goes with the process however that ends (kill -9 included), so a
stale lock file never blocks anyone. Within one process the lock is re-entrant (``demo`` holds it
while its ``fit`` and ``clones`` take it again).

What a run writes into its directory, what ``--overwrite`` removes and which files of those names
no run wrote are the run files' own (``RunFiles.DERIVED``, ``store.clear_derived``,
``store.foreign_files``); this module only guards the folder.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import threading
import time
from pathlib import Path

from .store import RunDirError, RunFiles

_held: dict[str, list] = {}  # resolved path -> [fd, depth] of the locks this process holds
_guard = threading.Lock()


def _holder_text(path: Path) -> str:
    try:
        info = json.loads(path.read_text(encoding="utf-8") or "{}")
    except (OSError, ValueError):
        info = {}
    if not info:
        return "another process"
    return f"pid {info.get('pid', '?')}, {info.get('command', '?')}"


def _command_line() -> str:
    prog = os.path.basename(sys.argv[0] or "python")
    argv = ["bforest" if prog == "__main__.py" else prog] + sys.argv[1:]
    text = " ".join(argv)
    return text if len(text) <= 200 else text[:197] + "..."


@contextlib.contextmanager
def run_lock(run_dir, create: bool = True):
    """Hold the lock of ``run_dir`` for the ``with`` block.

    Parameters
    ----------
    run_dir : path
        The run directory (created when ``create``; otherwise a missing one is not a run
        directory and raises :class:`RunDirError`).

    Raises
    ------
    RunDirError
        Another process holds the lock (names its pid and command).

    Notes
    -----
    A command that ends leaving nothing in the folder but the lock file it created (a fit that
    stopped on a missing QSM) takes the lock file with it, and the folder too when it made it.
    """
    run_dir = Path(run_dir)
    made = not run_dir.is_dir()
    if made:
        if not create:
            raise RunDirError(f"{run_dir}: not a run directory (no {RunFiles.CONFIG})")
        if run_dir.exists():
            raise RunDirError(f"{run_dir}: exists and is not a folder; choose another -o")
        run_dir.mkdir(parents=True, exist_ok=True)
    key = str(run_dir.resolve())
    lock = RunFiles(run_dir).lock_path
    with _guard:
        if key in _held:
            _held[key][1] += 1
            fd = None
        else:
            new_lock = not lock.exists()
            fd = _acquire(lock, run_dir)
            _held[key] = [fd, 1, new_lock, made]
    try:
        yield run_dir
    finally:
        with _guard:
            entry = _held[key]
            entry[1] -= 1
            if entry[1] == 0:
                del _held[key]
                try:
                    if entry[2]:  # still holding the lock: nobody else can have started here
                        _leave_no_trace(run_dir, lock, entry[3])
                finally:
                    _release(entry[0])


def _leave_no_trace(run_dir: Path, lock: Path, made: bool) -> None:
    """Remove the lock file this command created when the folder holds nothing else, and the
    folder when the command made it."""
    try:
        if [p.name for p in run_dir.iterdir()] != [lock.name]:
            return
        lock.unlink()
        if made:
            run_dir.rmdir()
    except OSError:  # another process wrote there meanwhile, or the folder cannot be changed
        pass


def _acquire(path: Path, run_dir: Path):
    if os.name != "posix":  # no flock: the run folder is unguarded (documented)
        return None
    import fcntl

    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise RunDirError(
            f"{run_dir}: in use by another bforest command ({_holder_text(path)}); wait for it "
            "to end, or choose another -o"
        ) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps({"pid": os.getpid(), "command": _command_line(), "since": time.time()}).encode(), 0)
    return fd


def _release(fd) -> None:
    if fd is None:
        return
    import fcntl

    try:
        os.ftruncate(fd, 0)
        fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


def holding_run_lock(fn):
    """Decorate a pipeline stage whose arguments name a run directory (``run_dir``): it runs
    holding that directory's lock (created unless the call resumes or reads an existing run)."""
    import functools
    import inspect

    sig = inspect.signature(fn)
    creates = fn.__name__ == "fit"

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        bound = sig.bind_partial(*args, **kwargs)
        bound.apply_defaults()
        create = creates and not bound.arguments.get("resume", False)
        with run_lock(bound.arguments["run_dir"], create=create):
            return fn(*args, **kwargs)

    return wrapper
