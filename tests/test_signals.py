"""Nothing a command starts outlives it: after SIGTERM or SIGINT of any command that starts
processes (workers, the report's second process, their helpers), no process of its session is
left; the command says in one line what it kept and exits with 128 + the signal's number.

A new command that starts processes is one entry of ``COMMANDS``: its arguments, made in a
folder of its own, and how many processes to wait for before the signal is sent.
"""

from __future__ import annotations

import os
import shutil
import signal
import sys

import pytest

import bforest_core as bf
from conftest import TOY_DIR, stop_command, toy_config

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="sessions and /proc")

EXE = [sys.executable, "-m", "bforest_core.cli"]


def _slow(tmp_path, budget=400, optimizer="toy-random", optimizer_settings="", sleep=0.2):
    """The toy recipe on 2 worker processes, its model sleeping ``sleep`` s per tree."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    p = toy_config(
        tmp_path,
        budget=budget,
        executor="process",
        executor_settings="workers = 2",
        optimizer=optimizer,
        optimizer_settings=optimizer_settings,
    )
    p.write_text(
        p.read_text()
        .replace('[ssm]\nkind = "toy"\n', f'[ssm]\nkind = "toy"\nsleep = {sleep}\n', 1)
        .replace('[target.generate]\nssm = "toy"', '[target.generate]\nssm = "toy"\nsettings = { sleep = 0.0 }')
    )
    return p


@pytest.fixture(scope="module")
def finished(toy_plugin, tmp_path_factory):
    """A finished run of the slow recipe (its clones and report grow and draw on 2 processes)."""
    d = tmp_path_factory.mktemp("finished")
    bf.fit(bf.load_config(_slow(d, budget=4, sleep=0.0)), d / "run", progress=False)
    cfg = d / "run" / "config.toml"
    cfg.write_text(cfg.read_text().replace("sleep = 0.0\n", "sleep = 0.2\n", 1))  # the clones grow slowly
    return d / "run"


def _copy(run, tmp_path):
    shutil.copytree(run, tmp_path / "run")
    return tmp_path / "run"


#: command -> (arguments made in a fresh folder from the finished run, processes to wait for)
COMMANDS = {
    "fit": (lambda run, tmp: (["fit", _slow(tmp), "-o", tmp / "run", "-q", "--no-report"], 2)),
    "clones": (lambda run, tmp: (["clones", _copy(run, tmp), "-n", "60", "-q", "--no-report"], 2)),
    "report": (lambda run, tmp: (["report", _copy(run, tmp)], 1)),
    "compare": (
        lambda run, tmp: (
            ["compare", _slow(tmp), "--optimizers", "toy-random", "--budget", "40", "--repeats", "2"]
            + ["-o", tmp / "cmp", "-q"],
            2,
        )
    ),
    "calibrate": (
        lambda run, tmp: (
            ["calibrate", _slow(tmp, optimizer="abc-smc", optimizer_settings="particles = 8\ngenerations = 3")]
            + ["-n", "4", "-o", tmp / "cal", "-q"],
            2,
        )
    ),
    "stand": (
        lambda run, tmp: (
            ["stand", _plot(tmp), "--recipe", _slow(tmp), "--realisations", "0", "-o", tmp / "stand", "-q"],
            2,
        )
    ),
}


def _plot(tmp_path):
    """A plot of two sample QSMs (fitted by the toy recipe: each tree a task on 2 workers)."""
    from conftest import qsm_path

    d = tmp_path / "plot"
    d.mkdir(parents=True, exist_ok=True)
    for name in ("pine_ruotsinkyla_3.mat", "coffeetree_treeqsm_optqsm.mat"):
        os.symlink(qsm_path(name), d / name)
    return d


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
@pytest.mark.parametrize("command", list(COMMANDS))
def test_no_process_outlives_a_stopped_command(toy_plugin, finished, tmp_path, command, signum):
    args, children = COMMANDS[command](finished, tmp_path)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(toy_plugin), str(TOY_DIR), os.environ.get("PYTHONPATH", "")]),
    }
    code, err, left = stop_command(EXE + args, env, signum, children)
    assert not left, f"{command}: processes {left} outlived it"
    assert code == 128 + signum, (code, err)
    # the toy site's broken plugin warns (a worker of calibrate in Python's own two-line format)
    lines = [ln for ln in err.splitlines() if "plugin 'broken'" not in ln and not ln.startswith("  ")]
    assert "Traceback" not in err and len(lines) == 1, err
    assert lines[0].startswith(f"stopped by {signal.Signals(signum).name}"), lines
    if command == "report":  # the report's own word, not the fit's
        assert "run bforest report again" in lines[0] and "--resume" not in lines[0]


def test_only_the_users_own_stop_is_taken_for_one():
    """Under user_stops (every command) the user's Ctrl-C is a Stopped and a bare KeyboardInterrupt
    a plugin's; where SIGINT has another handler (Python's own, a notebook's) a KeyboardInterrupt
    cannot be told from the user's and stops; where SIGINT is ignored (a worker) it never does."""
    from bforest_core.pipeline.interrupts import Stopped, user_stops, users_stop

    old = signal.getsignal(signal.SIGINT)
    try:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        assert users_stop(KeyboardInterrupt()) and not users_stop(ValueError())
        with user_stops():
            assert not users_stop(KeyboardInterrupt()) and users_stop(Stopped(signal.SIGTERM))
            with pytest.raises(Stopped) as got:
                os.kill(os.getpid(), signal.SIGINT)
                signal.sigtimedwait([], 0)  # the handler runs at the next instruction
            assert got.value.signum == signal.SIGINT
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # put back
        signal.signal(signal.SIGINT, lambda *a: None)  # a host's own handler
        assert users_stop(KeyboardInterrupt())
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        assert not users_stop(KeyboardInterrupt())
    finally:
        signal.signal(signal.SIGINT, old)
