"""The ``dask`` executor on a 2-worker LocalCluster (processes, one thread each).

One cluster for the whole module (a module-scoped fixture); other clients connect to it by
address. The functions below run in the worker processes, which import this module by name.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import socket
import subprocess
import sys
from pathlib import Path

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


def test_second_client_by_address_with_its_own_initializer(executor, tmp_path):
    """Another of the owner's runs joins the local cluster with its credentials."""
    from bforest_dask.credentials import write_credentials
    from bforest_dask.executor import DaskExecutor

    c = write_credentials(tmp_path / "creds", executor.security)
    tls = {"tls_ca_file": str(c["ca"]), "tls_cert": str(c["cert"]), "tls_key": str(c["key"])}
    other = bf.component("executor", "dask", address=executor.scheduler_address, workers=2, **tls)
    assert isinstance(other, DaskExecutor)
    with other.started(init_other, ("run-b",)):
        assert other.map(work_other, [1, 2, 3]) == ["run-b:1", "run-b:2", "run-b:3"]
        assert other.workers == 2
    # the first run's worker state is untouched and the cluster still serves it
    states = executor.client.run(report_state)
    assert all(s["inits"] == 1 and s["other"] == {"tag": "run-b"} for s in states.values())
    assert executor.map(work, ITEMS[:2])[1]["value"] == pytest.approx(10.0 + TABLE[1] * 0.5)


def _listening_ports(pids) -> list[int]:
    """TCP ports on which the processes ``pids`` listen (Linux: /proc)."""
    inodes = set()
    for pid in pids:
        fd_dir = Path(f"/proc/{pid}/fd")
        for fd in fd_dir.iterdir() if fd_dir.is_dir() else []:
            with contextlib.suppress(OSError):
                link = os.readlink(fd)
                if link.startswith("socket:["):
                    inodes.add(link[8:-1])
    ports = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] == "0A" and f[9] in inodes:  # 0A: LISTEN
                ports.append(int(f[1].rsplit(":", 1)[1], 16))
    return sorted(ports)


def _process_tree(pid) -> list[int]:
    kids = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout.split()
    return [pid] + [q for k in kids for q in _process_tree(int(k))]


def _owner_only_cluster() -> dict:
    """What a new local cluster shows a stranger (run in a process of its own, where no other
    cluster listens): its listening ports, which answer HTTP, and whether clients without its
    credentials (none, or another cluster's) connect."""
    from distributed import Client
    from distributed.security import Security

    from bforest_dask.executor import DaskExecutor

    out = {"http": [], "strangers": []}
    ex = DaskExecutor(workers=2)
    with ex.started(None):
        out["ports"] = _listening_ports(_process_tree(os.getpid()))
        for port in out["ports"]:
            with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
                sock.sendall(b"GET /health HTTP/1.0\r\n\r\n")
                sock.settimeout(5)
                with contextlib.suppress(OSError):
                    if sock.recv(64).startswith(b"HTTP"):
                        out["http"].append(port)
        out["address"] = ex.scheduler_address
        for who in (None, Security.temporary()):  # no credentials; another cluster's
            try:
                Client(ex.scheduler_address, security=who, timeout=5, set_as_default=False).close()
                out["strangers"].append("connected")
            except (OSError, TypeError) as exc:
                out["strangers"].append(type(exc).__name__)
        out["owner"] = ex.map(abs, [-2, -3])  # its owner's client still works
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads the listening sockets from /proc (Linux)")
def test_the_local_cluster_serves_no_http_and_only_its_owner():
    """A local cluster (no dashboard asked): its scheduler, 2 nannies and 2 workers listen on
    127.0.0.1 over TLS only, none answers HTTP; a client without the cluster's credentials (none,
    or another cluster's) cannot connect."""
    import json

    code = "import json, test_dask_executor as t; print('RESULT', json.dumps(t._owner_only_cluster()))"
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=Path(__file__).parent, capture_output=True, text=True, timeout=240
    )
    line = next((ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")), None)
    assert line, r.stderr[-2000:]
    got = json.loads(line[7:])
    assert len(got["ports"]) == 5, got  # scheduler, 2 nannies, 2 workers: no HTTP server among them
    assert got["http"] == [] and got["address"].startswith("tls://127.0.0.1:")
    assert "connected" not in got["strangers"] and len(got["strangers"]) == 2
    assert got["owner"] == [2, 3]


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
    with pytest.raises(ConfigError, match="give tls_ca_file, tls_cert and tls_key together"):
        bf.component("executor", "dask", address="tls://10.0.0.5:8786", tls_ca_file=__file__)
    with pytest.raises(ConfigError, match="tls_key: file not found"):
        bf.component(
            "executor", "dask", address="tls://h:1", tls_ca_file=__file__, tls_cert=__file__, tls_key="/no/key"
        )


def test_missing_dask_gives_a_clear_import_error(monkeypatch):
    """Without distributed the plugin module fails to import with the install hint (the registry
    then lists it as a load error; other plugins are unaffected)."""
    monkeypatch.setitem(sys.modules, "distributed", None)
    for mod in ("bforest_dask.executor", "bforest_dask.plugin"):
        if mod in sys.modules:
            monkeypatch.delitem(sys.modules, mod)
    with pytest.raises(ImportError, match=r"pip install 'bayesforest\[dask\]'"):
        importlib.import_module("bforest_dask.plugin")


def test_a_dashboard_address_without_a_host_binds_to_loopback():
    """A dashboard asked without a host binds to 127.0.0.1, not every interface."""
    from bforest_dask.executor import dashboard_address

    assert dashboard_address(":8787") == "127.0.0.1:8787" and dashboard_address("8787") == "127.0.0.1:8787"
    assert dashboard_address("0.0.0.0:8787") == "0.0.0.0:8787"  # an address that says otherwise


def kill_my_worker(x):
    os._exit(3)


def test_a_task_whose_workers_die_becomes_the_on_lost_result():
    """As with the process executor: a task that kills every worker it runs on ends, once the
    scheduler gives up on it, as the executor's on_lost makes it; the other tasks' results come
    back (a stand's tree whose worker dies is a failed row, the other trees go on)."""
    import dask

    from bforest_dask.executor import DaskExecutor

    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        ex = DaskExecutor(workers=2)
        ex.on_lost = lambda fn, item, status, message: ("lost", item, status, "died" in message)
        with ex.started(None):
            out = dict(ex.map_unordered(kill_my_worker, [7]))
            assert out == {0: ("lost", 7, "crashed", True)}
            assert ex.map(abs, [-1, -5]) == [1, 5]
