"""The ``dask`` executor on a 2-worker LocalCluster (processes, one thread each).

One cluster for the whole module (a module-scoped fixture); other clients connect to it by
address. The functions below run in the worker processes, which import this module by name.
"""

from __future__ import annotations

import importlib
import os
import sys

import numpy as np
import pytest

pytest.importorskip("dask", reason="dask is not installed (optional extra: pip install 'bayesforest[dask]')")
pytest.importorskip(
    "distributed", reason="distributed is not installed (optional extra: pip install 'bayesforest[dask]')"
)

import bforest_core as bf  # noqa: E402
from bforest_core.errors import ConfigError  # noqa: E402
from bforest_core.pipeline.executors import SerialExecutor  # noqa: E402

TABLE = np.arange(1.0, 8.0)  # stands in for the target data sets a worker loads once

# ------------------------------------------------------------------ run inside the workers
_STATE: dict = {}
_OTHER: dict = {}


def init_state(offset, table):
    """Executor initializer: per-process state, counting how often it ran."""
    _STATE["offset"] = float(offset)
    _STATE["table"] = np.asarray(table)
    _STATE["inits"] = _STATE.get("inits", 0) + 1


def work(item):
    i, x = item
    value = float(_STATE["table"][i % len(_STATE["table"])] * x + _STATE["offset"])
    return {"value": value, "inits": _STATE["inits"], "pid": os.getpid()}


def report_state():
    return {"inits": _STATE.get("inits", 0), "offset": _STATE.get("offset"), "other": dict(_OTHER)}


def init_other(tag):
    _OTHER["tag"] = tag


def work_other(x):
    return f"{_OTHER['tag']}:{x}"


def fail_on_three(x):
    if x == 3:
        raise ValueError("item 3 is bad")
    return x


# ------------------------------------------------------------------ tests
ITEMS = [(i, 0.5 * i) for i in range(40)]


@pytest.fixture(scope="module")
def executor():
    from bforest_dask.executor import DaskExecutor

    ex = DaskExecutor(workers=2)
    ex.start(init_state, (10.0, TABLE))
    yield ex
    ex.shutdown()


def test_same_results_as_serial_executor(executor):
    serial = SerialExecutor()
    with serial.started(init_state, (10.0, TABLE)):
        expected = [r["value"] for r in serial.map(work, ITEMS)]
    seen, results = [], {}
    for i, r in executor.map_unordered(work, ITEMS):
        seen.append(i)
        results[i] = r
    assert sorted(seen) == list(range(len(ITEMS)))  # every index exactly once
    assert [results[i]["value"] for i in range(len(ITEMS))] == expected
    # evaluated in the worker processes, each initialised exactly once
    worker_pids = set(executor.client.run(os.getpid).values())
    assert len(worker_pids) == 2 and os.getpid() not in worker_pids
    assert {r["pid"] for r in results.values()} <= worker_pids
    assert {r["inits"] for r in results.values()} == {1}
    assert executor.workers == 2


def test_map_preserves_order(executor):
    out = executor.map(work, ITEMS)
    assert [r["value"] for r in out] == [10.0 + TABLE[i % 7] * x for i, x in ITEMS]


def test_initializer_ran_once_on_every_worker(executor):
    states = executor.client.run(report_state)
    assert len(states) == 2
    assert all(s["inits"] == 1 and s["offset"] == 10.0 for s in states.values())


def test_task_error_is_raised_to_the_caller(executor):
    with pytest.raises(ValueError, match="item 3 is bad"):
        dict(executor.map_unordered(fail_on_three, list(range(6))))


def test_leaving_the_loop_early_cancels_the_rest(executor):
    gen = executor.map_unordered(work, ITEMS)
    next(gen)
    gen.close()  # must not hang or raise
    assert executor.map(work, ITEMS[:3])[2]["value"] == pytest.approx(10.0 + TABLE[2] * 1.0)


def test_second_client_by_address_with_its_own_initializer(executor):
    from bforest_dask.executor import DaskExecutor

    other = bf.component("executor", "dask", address=executor.scheduler_address, workers=2)
    assert isinstance(other, DaskExecutor)
    with other.started(init_other, ("run-b",)):
        assert other.map(work_other, [1, 2, 3]) == ["run-b:1", "run-b:2", "run-b:3"]
        assert other.workers == 2
    # the first run's worker state is untouched and the cluster still serves it
    states = executor.client.run(report_state)
    assert all(s["inits"] == 1 and s["other"] == {"tag": "run-b"} for s in states.values())
    assert executor.map(work, ITEMS[:2])[1]["value"] == pytest.approx(10.0 + TABLE[1] * 0.5)


def test_late_joining_worker_is_initialised(executor):
    cluster = executor._cluster
    cluster.scale(3)
    executor.client.wait_for_workers(3, timeout=60)
    states = executor.client.run(report_state)
    assert len(states) == 3
    assert all(s["inits"] == 1 and s["offset"] == 10.0 for s in states.values())
    cluster.scale(2)


def test_settings_are_validated():
    with pytest.raises(ConfigError):
        bf.component("executor", "dask", wokers=2)
    with pytest.raises(ConfigError):
        bf.component("executor", "dask", workers=0)


def test_missing_dask_gives_a_clear_import_error(monkeypatch):
    """Without distributed the plugin module fails to import with the install hint (the registry
    then lists it as a load error; other plugins are unaffected)."""
    monkeypatch.setitem(sys.modules, "distributed", None)
    for mod in ("bforest_dask.executor", "bforest_dask.plugin"):
        if mod in sys.modules:
            monkeypatch.delitem(sys.modules, mod)
    with pytest.raises(ImportError, match=r"pip install 'bayesforest\[dask\]'"):
        importlib.import_module("bforest_dask.plugin")


def test_no_http_port_unless_asked_and_then_on_loopback(executor):
    """The scheduler of a local cluster serves HTTP whatever it is told; with no dashboard_address
    nothing listens, and a dashboard address without a host binds to 127.0.0.1, not every
    interface."""
    from bforest_dask.executor import dashboard_address

    assert all(sock.fileno() == -1 for sock in executor._cluster.scheduler.http_server._sockets.values())
    assert dashboard_address(":8787") == "127.0.0.1:8787" and dashboard_address("8787") == "127.0.0.1:8787"
    assert dashboard_address("0.0.0.0:8787") == "0.0.0.0:8787"  # an address that says otherwise
