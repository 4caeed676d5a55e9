"""The worker plugin that runs a fit's initializer on every Dask worker (imported only when a
dask run starts, so discovering the plugin does not import ``distributed``)."""

from __future__ import annotations

from collections.abc import Callable

from distributed.diagnostics.plugin import WorkerPlugin

from bforest_core.interfaces import Executor


class RunInitializer(WorkerPlugin):
    """Worker plugin running ``initializer(*initargs)`` once in each worker process.

    ``setup`` is called by the worker when the plugin is registered and when a worker joins the
    cluster later, so late workers are initialised too.
    """

    def __init__(self, initializer: Callable | None, initargs: tuple, name: str):
        self.initializer = initializer
        self.initargs = tuple(initargs)
        self.name = name

    def setup(self, worker) -> None:
        Executor.worker_setup()
        if self.initializer is not None:
            self.initializer(*self.initargs)
