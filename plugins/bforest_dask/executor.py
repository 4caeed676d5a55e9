"""The ``dask`` executor: evaluations on a Dask ``distributed`` cluster.

Without an ``address`` it starts a :class:`distributed.LocalCluster` of ``workers`` processes
with one thread each (like the ``process`` executor, but with Dask's dashboard, spilling and
resilience); with an ``address`` it connects to a running scheduler (e.g. one started by
dask-jobqueue's ``SLURMCluster`` or ``dask scheduler`` on a cluster login node; see
``docs/dask.md``).

The run's initializer (which loads the target data sets and builds the components) is wrapped
in a worker plugin: it runs once on every worker that is connected when the run starts *and* on
every worker that joins later (an adaptive cluster, a restarted worker), and its arguments
travel to each worker once, inside the plugin, never with the tasks.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import uuid
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any

from pydantic import Field

from bforest_core.interfaces import ComponentSettings, Executor

if TYPE_CHECKING:
    from distributed import Client, LocalCluster

# checked without importing: `distributed` costs ~0.3 s, paid only when a dask run starts
for _mod in ("dask", "distributed"):
    if importlib.util.find_spec(_mod) is None:  # pragma: no cover - exercised where dask is absent
        raise ImportError(
            f"the 'dask' executor needs dask and distributed; '{_mod}' is not installed. "
            "Install them with: pip install 'bayesforest[dask]'"
        )


class DaskSettings(ComponentSettings):
    address: str | None = Field(
        None,
        description="address of a running Dask scheduler (e.g. "
        "tcp://10.0.0.5:8786 or a scheduler file path with scheduler_file); "
        "none: start a local cluster",
    )
    scheduler_file: str | None = Field(
        None, description="JSON scheduler file written by `dask scheduler --scheduler-file` (alternative to address)"
    )
    workers: int | None = Field(
        None,
        ge=1,
        le=1024,
        description="local cluster: number of worker processes "
        "(default: all cores); remote scheduler: wait until this many workers "
        "are connected (default 1)",
    )
    timeout: float = Field(120.0, gt=0, le=86400, description="seconds to wait for the scheduler and its workers")
    dashboard_address: str | None = Field(
        None,
        description="local cluster: where to serve the Dask "
        "dashboard (e.g. ':8787', on 127.0.0.1 unless a host is given; "
        "needs bokeh); none: no dashboard and no HTTP port",
    )


def dashboard_address(address: str | None) -> str:
    """Where the local cluster's scheduler serves HTTP: ``address`` on 127.0.0.1 unless it names
    a host (``":8787"`` or ``"8787"`` would otherwise listen on every interface); without one, a
    free loopback port, closed at once (:func:`_stop_http_server`)."""
    if address is None:
        return "127.0.0.1:0"
    text = str(address).strip()
    if text.isdigit():
        return f"127.0.0.1:{text}"
    if text.startswith(":"):
        return f"127.0.0.1{text}"
    return text


async def _stop_http_server(scheduler) -> None:
    """Close the scheduler's HTTP server (dashboard, health, metrics): nobody asked for it."""
    server = getattr(scheduler, "http_server", None)
    if server is not None:
        server.stop()


class DaskExecutor(Executor):
    """Runs evaluations as Dask tasks, yielding results as they complete.

    Results never depend on the cluster: every evaluation carries its own seed and workers hold
    no random state (the same contract as the ``process`` executor).
    """

    name = "dask"
    summary = "Dask distributed: a local cluster or a running scheduler (SLURM etc. via dask-jobqueue)"
    Settings = DaskSettings

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self._client: Client | None = None
        self._cluster: LocalCluster | None = None
        self._plugin_name: str | None = None

    # ------------------------------------------------------------------ lifecycle
    @property
    def client(self) -> Client:
        """The connected :class:`distributed.Client` (after :meth:`start`)."""
        if self._client is None:
            raise RuntimeError("dask executor not started (use executor.started(...))")
        return self._client

    @property
    def workers(self) -> int:
        if self._client is not None:
            return max(1, len(self._client.nthreads()))
        if self.settings.workers is not None:
            return self.settings.workers
        return 1 if (self.settings.address or self.settings.scheduler_file) else max(1, os.cpu_count() or 1)

    @property
    def scheduler_address(self) -> str:
        """Address of the scheduler in use (e.g. to let another client connect)."""
        return self.client.scheduler.address

    def start(self, initializer: Callable | None = None, initargs: tuple = ()) -> None:
        from distributed import Client, LocalCluster

        from ._worker_plugin import RunInitializer

        s: DaskSettings = self.settings
        if self._client is not None:
            raise RuntimeError("dask executor already started")
        if s.address and s.scheduler_file:
            raise ValueError("dask executor: give address or scheduler_file, not both")
        if s.address or s.scheduler_file:
            client = Client(s.address, scheduler_file=s.scheduler_file, timeout=s.timeout, set_as_default=False)
            n_wait = s.workers or 1
        else:
            n = s.workers or max(1, os.cpu_count() or 1)
            self._cluster = LocalCluster(
                n_workers=n,
                threads_per_worker=1,
                processes=True,
                dashboard_address=dashboard_address(s.dashboard_address),
                silence_logs=logging.WARNING,
            )
            if s.dashboard_address is None:  # the scheduler starts an HTTP server whatever it is told
                self._cluster.sync(_stop_http_server, self._cluster.scheduler)  # on the cluster's event loop
            client = Client(self._cluster, set_as_default=False)
            n_wait = n
        self._client = client
        try:
            client.wait_for_workers(n_wait, timeout=s.timeout)
            # a unique name: several runs may share one scheduler, each with its own target
            self._plugin_name = f"bforest-init-{uuid.uuid4().hex}"
            client.register_plugin(RunInitializer(initializer, initargs, self._plugin_name), name=self._plugin_name)
        except BaseException:
            self.shutdown()
            raise

    def map_unordered(self, fn: Callable, items: Sequence) -> Iterator[tuple[int, Any]]:
        """Submit every item as one task; yield ``(index, result)`` as tasks complete.

        A task's exception is re-raised here; leaving the loop early cancels the tasks still
        pending.
        """
        from distributed import as_completed

        client = self.client
        items = list(items)
        if not items:
            return
        futures = client.map(fn, items, pure=False)
        index = {f.key: i for i, f in enumerate(futures)}
        try:
            for fut in as_completed(futures, loop=client.loop):
                yield index[fut.key], fut.result()
        finally:
            pending = [f for f in futures if not f.done()]
            if pending:
                client.cancel(pending)

    def shutdown(self) -> None:
        client, cluster = self._client, self._cluster
        self._client = self._cluster = None
        if client is not None:
            if self._plugin_name is not None and cluster is None:
                try:  # leave a shared cluster clean
                    client.unregister_worker_plugin(self._plugin_name)
                except Exception:
                    pass
            client.close()
        if cluster is not None:
            cluster.close()
        self._plugin_name = None
