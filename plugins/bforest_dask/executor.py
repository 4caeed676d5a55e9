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
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import Field, model_validator

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
    tls_ca_file: str | None = Field(
        None, description="remote scheduler: the cluster's CA certificate (PEM file); with tls_cert and tls_key"
    )
    tls_cert: str | None = Field(None, description="remote scheduler: this client's certificate (PEM file)")
    tls_key: str | None = Field(None, description="remote scheduler: this client's private key (PEM file)")

    @model_validator(mode="after")
    def _tls_all_or_none(self):
        given = [k for k in ("tls_ca_file", "tls_cert", "tls_key") if getattr(self, k)]
        if given and len(given) != 3:
            missing = sorted({"tls_ca_file", "tls_cert", "tls_key"} - set(given))
            raise ValueError(f"give tls_ca_file, tls_cert and tls_key together (missing: {', '.join(missing)})")
        if given and not (self.address or self.scheduler_file):
            raise ValueError("tls_ca_file, tls_cert and tls_key are for a remote scheduler (address or scheduler_file)")
        for k in given:
            if not Path(getattr(self, k)).expanduser().is_file():
                raise ValueError(f"{k}: file not found: {getattr(self, k)}")
        return self

    def security(self):
        """The remote cluster's :class:`distributed.security.Security` (None without certificates)."""
        if not self.tls_ca_file:
            return None
        from distributed.security import Security

        return Security(
            tls_ca_file=str(Path(self.tls_ca_file).expanduser()),
            tls_client_cert=str(Path(self.tls_cert).expanduser()),
            tls_client_key=str(Path(self.tls_key).expanduser()),
            require_encryption=True,
        )


def dashboard_address(address: str | None) -> str:
    """Where the local cluster's scheduler serves HTTP: ``address`` on 127.0.0.1 unless it names
    a host (``":8787"`` or ``"8787"`` would otherwise listen on every interface); without one, a
    free loopback port, closed at once (the preload :data:`NO_HTTP_PRELOAD`)."""
    if address is None:
        return "127.0.0.1:0"
    text = str(address).strip()
    if text.isdigit():
        return f"127.0.0.1:{text}"
    if text.startswith(":"):
        return f"127.0.0.1{text}"
    return text


#: no HTTP route at all on a local cluster's scheduler and workers while their HTTP servers stand
#: (from their start until the preload :data:`NO_HTTP_PRELOAD` closes them)
NO_HTTP_ROUTES = {"distributed.scheduler.http.routes": [], "distributed.worker.http.routes": []}
#: the Dask preload that closes a scheduler's or worker's HTTP server as it starts
NO_HTTP_PRELOAD = "bforest_dask.nohttp"


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
        self._security = None
        self.on_lost = None  # (fn, item, status, message) -> stand-in result of a task whose workers died
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
    def security(self):
        """The TLS credentials this executor's client presents (a local cluster's temporary ones,
        or those of the settings; None for a remote scheduler reached without TLS).
        ``bforest_dask.credentials.write_credentials(folder, executor.security)`` lets another
        of the owner's clients join the local cluster."""
        return self._security

    @property
    def scheduler_address(self) -> str:
        """Address of the scheduler in use (e.g. to let another client connect)."""
        return self.client.scheduler.address

    def start(self, initializer: Callable | None = None, initargs: tuple = ()) -> None:
        from distributed import Client

        from ._worker_plugin import RunInitializer

        s: DaskSettings = self.settings
        if self._client is not None:
            raise RuntimeError("dask executor already started")
        if s.address and s.scheduler_file:
            raise ValueError("dask executor: give address or scheduler_file, not both")
        if s.address or s.scheduler_file:
            client = Client(
                s.address,
                scheduler_file=s.scheduler_file,
                timeout=s.timeout,
                set_as_default=False,
                security=s.security(),
            )
            self._security = s.security()
            n_wait = s.workers or 1
        else:
            n = s.workers or max(1, os.cpu_count() or 1)
            client = self._local_cluster(n)
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

    def _local_cluster(self, n: int):
        """A local cluster only its owner can use: its scheduler, nannies and workers listen on
        127.0.0.1 over TLS with credentials made for this cluster alone (distributed's
        ``Security.temporary()``: a client without them cannot connect), and no HTTP server
        stays open unless ``dashboard_address`` asks for the dashboard (docs/dask.md)."""
        import dask
        from distributed import Client, LocalCluster
        from distributed.security import Security

        s: DaskSettings = self.settings
        try:
            security = Security.temporary()
        except ImportError:  # pragma: no cover - cryptography comes with bayesforest[dask]
            raise ImportError(
                "the dask executor's local cluster needs the cryptography package for its TLS credentials: "
                "pip install 'bayesforest[dask]'"
            ) from None
        # the scheduler and the workers start HTTP servers whatever they are told: no routes while
        # they start, and each closes its own as it starts (the preload bforest_dask.nohttp)
        quiet = s.dashboard_address is None
        with dask.config.set(NO_HTTP_ROUTES if quiet else {}):
            self._cluster = LocalCluster(
                n_workers=n,
                threads_per_worker=1,
                processes=True,
                host="127.0.0.1",
                protocol="tls://",
                security=security,
                dashboard_address=dashboard_address(s.dashboard_address),
                silence_logs=logging.WARNING,
                preload=[NO_HTTP_PRELOAD],
                scheduler_kwargs={"preload": [NO_HTTP_PRELOAD]} if quiet else {},
            )
        self._security = security
        return Client(self._cluster, security=security, set_as_default=False)

    def map_unordered(self, fn: Callable, items: Sequence) -> Iterator[tuple[int, Any]]:
        """Submit every item as one task; yield ``(index, result)`` as tasks complete.

        A task's exception is re-raised here, but for a task whose workers died, which becomes
        ``on_lost(fn, item, "crashed", message)`` when that hook is set; leaving the loop early
        cancels the tasks still pending.
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
                i = index[fut.key]
                lost = self._lost_result(fut, fn, items[i])
                yield i, (fut.result() if lost is NotImplemented else lost)
        finally:
            pending = [f for f in futures if not f.done()]
            if pending:
                client.cancel(pending)

    def _lost_result(self, fut, fn, item):
        """What a task becomes whose workers died (the scheduler gave up on it after
        ``distributed.scheduler.allowed-failures`` deaths): the executor's ``on_lost`` result, as
        with the process executor; :data:`NotImplemented` for any other outcome."""
        if self.on_lost is None or fut.status != "error":
            return NotImplemented
        exc = fut.exception()
        if type(exc).__name__ != "KilledWorker":
            return NotImplemented
        return self.on_lost(fn, item, "crashed", f"its workers died: {exc}")

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
