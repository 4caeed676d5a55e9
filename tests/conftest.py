"""Shared fixtures: the real sample QSMs live in ../shared/data/qsm (never copied here)."""

from __future__ import annotations

import contextlib
import functools
import http.server
import os
import socket
import threading
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
QSM_DIR = Path(os.environ.get("BFOREST_QSM_DIR", ROOT.parent / "shared" / "data" / "qsm"))
if QSM_DIR.is_dir():  # sample:NAME (the examples' recipes) reads the samples here, as from a fetch
    os.environ.setdefault("BFOREST_DATA_DIR", str(QSM_DIR))


def qsm_path(name: str) -> Path:
    """Path of a real sample file; skips the test with a reason when the data folder is absent."""
    p = QSM_DIR / name
    if not p.exists():
        pytest.skip(f"real QSM sample {name} not found in {QSM_DIR} (needs ../shared/data/qsm beside the repo)")
    return p


def read_sample(name: str, **options):
    """A real sample QSM read with the bundled readers (skips when the data folder is absent)."""
    from bforest_core import read_qsm

    return read_qsm(qsm_path(name), **options)


@pytest.fixture
def qsm_dir() -> Path:
    if not QSM_DIR.is_dir():
        pytest.skip(f"real QSM samples not found: {QSM_DIR} is missing (needs ../shared/data/qsm)")
    return QSM_DIR


def hand_tree(topology: str = "source"):
    """The hand-built tree of docs/features-and-distance.md §7 (trunk of 3 vertical cylinders and
    three laterals with known beta/alpha/L_t/R_f/L_a)."""
    from bforest_core import Tree

    s60, c60 = np.sin(np.radians(60)), np.cos(np.radians(60))
    start = [
        [0, 0, 0],
        [0, 0, 1],
        [0, 0, 2],  # trunk 0,1,2
        [0, 0, 1],
        [0.8 * s60, 0, 1 + 0.8 * c60],  # lateral A (2 cyl) on trunk 0's end
        [0, 0, 1.5],  # lateral B mid trunk 1
        [0, 0, 2.25],
    ]  # lateral C on trunk 2
    axis = [[0, 0, 1]] * 3 + [[s60, 0, c60]] * 2 + [[0, 1, 0], [-1, 0, 0]]
    length = [1, 1, 1, 0.8, 0.5, 0.6, 0.6]
    radius = [0.20, 0.15, 0.10, 0.05, 0.04, 0.04, 0.03]
    parent = [-1, 0, 1, 0, 3, 1, 2]
    extension = [1, 2, -1, 4, -1, -1, -1]
    return Tree(start, axis, length, radius, parent, extension, topology=topology)


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie waiting for its parent counts as gone; Linux)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):  # gone before or while /proc was read
        return False


def gone_within(pids, seconds: float) -> bool:
    """Wait up to ``seconds`` for every process of ``pids`` to end; whether they all did."""
    import time

    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and any(pid_alive(p) for p in pids):
        time.sleep(0.1)
    return not any(pid_alive(p) for p in pids)


@contextlib.contextmanager
def served(folder: Path):
    """An HTTP server on 127.0.0.1 serving ``folder``; yields (its URL, the paths asked for)."""
    asked = []

    class Handler(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args):  # quiet
            pass

        def do_GET(self):
            asked.append(self.path)
            super().do_GET()

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(folder)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", asked
    finally:
        server.shutdown()
        server.server_close()


def closed_port() -> int:
    """A port of 127.0.0.1 nothing listens on."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


TOY_DIR = Path(__file__).resolve().parent / "toy_plugin"


def install_toy_plugin(tmp_dir: Path, broken: bool = True) -> Path:
    """Make the toy plugin discoverable through a real entry point: a ``.dist-info`` folder with
    ``entry_points.txt`` on ``sys.path`` (what ``pip install`` of a plugin creates)."""
    import sys

    from bforest_core import registry

    dist = tmp_dir / "bforest_toy-1.2.3.dist-info"
    dist.mkdir(parents=True, exist_ok=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: bforest-toy\nVersion: 1.2.3\n")
    eps = "[bforest]\ntoy = bforest_toy\n" + ("broken = bforest_toy_broken\n" if broken else "")
    (dist / "entry_points.txt").write_text(eps)
    for p in (str(tmp_dir), str(TOY_DIR)):
        if p not in sys.path:
            sys.path.insert(0, p)
    registry.discover(refresh=True)
    from bforest_core import config

    config._run_config_model.cache_clear()
    return tmp_dir


def uninstall_toy_plugin(tmp_dir: Path) -> None:
    import sys

    from bforest_core import config, registry

    for p in (str(tmp_dir), str(TOY_DIR)):
        while p in sys.path:
            sys.path.remove(p)
    registry.discover(refresh=True)
    config._run_config_model.cache_clear()


@pytest.fixture(scope="session")
def toy_plugin(tmp_path_factory):
    """The toy plugin installed for the whole session (SSM ``toy``, features ``toy-features``,
    distance ``toy-distance``) plus a broken plugin that fails to import."""
    import warnings

    d = tmp_path_factory.mktemp("toy_site")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        install_toy_plugin(d)
    yield d
    uninstall_toy_plugin(d)


TOY_CONFIG = """
seed = 3
[target.generate]
ssm = "toy"
seed = 11
params = {{ angle = 30.0, segments = 12 }}
[ssm]
kind = "toy"
fixed = {{ noise = 2.0 }}
free.angle = {{ lower = 5.0, upper = 80.0 }}
free.segments = {{ lower = 4, upper = 30 }}
[features]
kind = "toy-features"
[distance]
kind = "toy-distance"
[optimizer]
kind = "{optimizer}"
{optimizer_settings}
[executor]
kind = "{executor}"
{executor_settings}
[stop]
max_evaluations = {budget}
[clones]
count = 4
"""


def toy_config(
    tmp_path: Path, optimizer="toy-random", optimizer_settings="", executor="serial", executor_settings="", budget=40
) -> Path:
    p = tmp_path / "run.toml"
    p.write_text(
        TOY_CONFIG.format(
            optimizer=optimizer,
            optimizer_settings=optimizer_settings,
            executor=executor,
            executor_settings=executor_settings,
            budget=budget,
        )
    )
    return p


def fit_killed_after(cfg, run_dir: Path, n: int, monkeypatch) -> None:
    """Run ``bf.fit(cfg, run_dir)`` and kill it (a KeyboardInterrupt, as a Ctrl-C) when it is about
    to log its evaluation ``n + 1``: the run store then holds exactly ``n`` evaluations."""
    import bforest_core as bf
    from bforest_core.pipeline.store import RunStore

    real_add, calls = RunStore.add, {"n": 0}

    def crashing_add(self, ev):
        if calls["n"] == n:
            raise KeyboardInterrupt("simulated kill")
        calls["n"] += 1
        real_add(self, ev)

    monkeypatch.setattr(RunStore, "add", crashing_add)
    try:
        with pytest.raises(KeyboardInterrupt):
            bf.fit(cfg, run_dir, progress=False)
    finally:
        monkeypatch.setattr(RunStore, "add", real_add)


def pytest_terminal_summary(terminalreporter):
    """The conformance kit's coverage (test_conformance records it) at the end of the run."""
    for rep in terminalreporter.stats.get("passed", []):
        for key, value in getattr(rep, "user_properties", []):
            if key == "conformance_components":
                terminalreporter.write_line(f"conformance kit: {value}")


def session_pids(sid: int) -> list[int]:
    """The processes of session ``sid`` that still run (Linux: /proc), zombies left out."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
        except (FileNotFoundError, ProcessLookupError, IndexError):
            continue
        if int(fields[3]) == sid and fields[0] != "Z":
            out.append(int(d.name))
    return out


def stop_command(argv, env, signum: int, children: int = 1, timeout: float = 90.0):
    """Run ``argv`` in a session of its own, send it ``signum`` once it has started ``children``
    processes (``kill -TERM PID``: the command alone, not its group) and wait for it to end.

    Returns (exit code, standard error, the processes of its session still running 10 s after
    it ended): whatever a command starts must end with it, whatever it was doing.
    """
    import subprocess
    import tempfile
    import time

    with tempfile.TemporaryFile("w+") as err:  # not a pipe: a process left behind would hold it open
        proc = subprocess.Popen(
            [str(a) for a in argv], env=env, stdout=subprocess.DEVNULL, stderr=err, text=True, start_new_session=True
        )
        try:
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline and proc.poll() is None:
                if len([p for p in session_pids(proc.pid) if p != proc.pid]) >= children:
                    break
                time.sleep(0.05)
            assert proc.poll() is None, f"{argv[3:5]} ended before it started {children} processes"
            time.sleep(0.3)  # at work
            proc.send_signal(signum)
            proc.wait(60)
            left = session_pids(proc.pid)
            deadline = time.monotonic() + 10
            while left and time.monotonic() < deadline:
                time.sleep(0.1)
                left = session_pids(proc.pid)
            err.seek(0)
            return proc.returncode, err.read(), left
        finally:
            if proc.poll() is None:
                proc.kill()
            for pid in session_pids(proc.pid):  # never leave a stray process behind a failed test
                try:
                    os.kill(pid, 9)
                except ProcessLookupError:
                    pass
