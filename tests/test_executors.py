import os


import bforest_core as bf
from bforest_core.pipeline.objective import clone_seeds, model_seeds

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


def test_model_seeds_depend_only_on_run_seed_and_index():
    assert model_seeds(1, 3) == model_seeds(1, 3)
    assert model_seeds(1, 3) != model_seeds(2, 3)
    assert model_seeds(1, 1, "fixed", 0) == model_seeds(1, 1, "fixed", 99)
    assert model_seeds(1, 1, "per_evaluation", 0) != model_seeds(1, 1, "per_evaluation", 1)
    assert len(set(clone_seeds(1, 50))) == 50 and set(clone_seeds(1, 5)).isdisjoint(model_seeds(1, 5))
