import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import bforest_core as bf
from bforest_core.pipeline.seeds import clone_seeds, model_seeds
from conftest import gone_within, pid_alive

_STATE = {}


def _init(value):
    _STATE["value"] = value
    _STATE["pid"] = os.getpid()


def _work(x):
    return x * _STATE["value"], _STATE["pid"], os.environ.get("OMP_NUM_THREADS")


def test_serial_runs_initializer_in_process():
    ex = bf.component("executor", "serial")
    with ex.started(_init, (3,)):
        out = ex.map(_work, [1, 2, 3])
    assert [o[0] for o in out] == [3, 6, 9] and out[0][1] == os.getpid()


def test_process_pool_initializer_once_per_worker_and_one_thread():
    ex = bf.component("executor", "process", workers=2)
    with ex.started(_init, (5,)):
        got = dict(ex.map_unordered(_work, list(range(20))))
    assert sorted(got) == list(range(20))
    assert all(got[i][0] == 5 * i for i in got)
    assert {g[1] for g in got.values()} <= set(range(1, 1 << 22)) and os.getpid() not in {g[1] for g in got.values()}
    assert {g[2] for g in got.values()} == {"1"}


def _warned(_):
    import warnings

    from bforest_core.cylinders import QSMReadWarning

    with warnings.catch_warnings(record=True) as caught:
        warnings.warn("renormalised axes", QSMReadWarning, stacklevel=1)
        warnings.warn("something else", UserWarning, stacklevel=1)
    return [type(w.message).__name__ for w in caught]


def test_workers_keep_a_qsms_read_repairs_quiet_and_show_other_warnings():
    # the command reports a QSM's repairs once when it reads the file; a worker reading it again
    # would print them once more per worker, in Python's raw format
    ex = bf.component("executor", "process", workers=2)
    with ex.started():
        got = [w for _, w in ex.map_unordered(_warned, [0, 1])]
    assert got == [["UserWarning"], ["UserWarning"]]


def test_model_seeds_depend_only_on_run_seed_and_index():
    assert model_seeds(1, 3) == model_seeds(1, 3)
    assert model_seeds(1, 3) != model_seeds(2, 3)
    assert model_seeds(1, 1, "fixed", 0) == model_seeds(1, 1, "fixed", 99)
    assert model_seeds(1, 1, "per_evaluation", 0) != model_seeds(1, 1, "per_evaluation", 1)
    assert len(set(clone_seeds(1, 50))) == 50 and set(clone_seeds(1, 5)).isdisjoint(model_seeds(1, 5))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_end_when_the_process_that_owns_the_pool_is_killed(tmp_path):
    """A fit killed with SIGKILL leaves no worker waiting for tasks for ever (each would hold its
    target tree in memory): the workers see their owner gone and exit within seconds."""
    script = (
        "import os, time\n"
        "import bforest_core as bf\n"
        "from test_executors import _init, _work\n"
        "ex = bf.component('executor', 'process', workers=2)\n"
        "ex.start(_init, (1,))\n"
        "pids = {out[1] for _, out in ex.map_unordered(_work, range(8))}\n"
        "print(' '.join(map(str, sorted(pids))), flush=True)\n"
        "time.sleep(120)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, env=env)
    try:
        pids = [int(p) for p in proc.stdout.readline().split()]
        assert pids and all(pid_alive(p) for p in pids)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        assert gone_within(pids, 15), "workers outlived the killed owner"
    finally:
        proc.kill()
