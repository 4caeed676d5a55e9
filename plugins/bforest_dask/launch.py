"""A Dask cluster of separate processes on this machine: ``dask scheduler`` and ``dask worker``
started as commands, as on a cluster's nodes (docs/dask.md). For trying a stand or a fit the way
it runs on a cluster, and for the tests and benchmarks that kill a worker in the middle of one.

Every process listens on 127.0.0.1 only, over TLS with credentials made for the cluster
(:mod:`bforest_dask.credentials`), and serves no HTTP route. Each worker runs under a nanny that
restarts it when it dies (``SIGKILL`` included), with one thread; the scheduler and the workers
close their HTTP servers as they start (:mod:`bforest_dask.nohttp`).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from .credentials import write_credentials
from .executor import NO_HTTP_PRELOAD, NO_HTTP_ROUTES


@dataclass
class SeparateCluster:
    """A running cluster of separate processes (see :func:`separate_cluster`)."""

    folder: Path
    scheduler_file: Path
    credentials: dict
    scheduler: subprocess.Popen
    workers: list = field(default_factory=list)

    def executor_settings(self) -> dict:
        """The ``[executor]`` table of a run or a stand that uses this cluster."""
        return {
            "kind": "dask",
            "scheduler_file": str(self.scheduler_file),
            "workers": len(self.workers),
            "tls_ca_file": str(self.credentials["ca"]),
            "tls_cert": str(self.credentials["cert"]),
            "tls_key": str(self.credentials["key"]),
        }


def _env() -> dict:
    env = dict(os.environ)
    for key, value in NO_HTTP_ROUTES.items():
        env["DASK_" + key.upper().replace(".", "__").replace("-", "_")] = json.dumps(value)
    return env


@contextlib.contextmanager
def separate_cluster(folder, workers: int = 2, timeout: float = 60.0):
    """Start ``dask scheduler`` and ``workers`` ``dask worker`` processes (one thread each) with
    fresh TLS credentials in ``folder``; stop them all on leaving the block.

    Yields
    ------
    SeparateCluster
    """
    folder = Path(folder)
    creds = write_credentials(folder / "credentials")
    tls = ["--tls-ca-file", str(creds["ca"]), "--tls-cert", str(creds["cert"]), "--tls-key", str(creds["key"])]
    sched_file = folder / "scheduler.json"
    dask = str(Path(sys.executable).with_name("dask"))
    log = open(folder / "cluster.log", "ab")
    env = _env()
    procs = []
    try:
        sched = subprocess.Popen(
            [
                dask,
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--protocol",
                "tls",
                "--scheduler-file",
                str(sched_file),
            ]
            + ["--no-dashboard", "--dashboard-address", "127.0.0.1:0", "--preload", NO_HTTP_PRELOAD, *tls],
            stdout=log,
            stderr=log,
            env=env,
            start_new_session=True,
        )
        procs.append(sched)
        t0 = time.monotonic()
        while not sched_file.exists():
            if sched.poll() is not None or time.monotonic() - t0 > timeout:
                raise RuntimeError(f"the dask scheduler did not start (see {folder / 'cluster.log'})")
            time.sleep(0.2)
        cluster = SeparateCluster(folder, sched_file, creds, sched)
        for _ in range(workers):
            w = subprocess.Popen(
                [dask, "worker", "--scheduler-file", str(sched_file), "--nthreads", "1", "--host", "127.0.0.1"]
                + ["--no-dashboard", "--nanny", "--preload", NO_HTTP_PRELOAD, *tls],
                stdout=log,
                stderr=log,
                env=env,
                start_new_session=True,
            )
            procs.append(w)
            cluster.workers.append(w)
        yield cluster
    finally:
        for p in reversed(procs):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
        log.close()
