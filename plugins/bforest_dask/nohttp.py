"""A Dask preload that closes the HTTP server of a scheduler or worker as it starts: its
dashboard, ``/health``, ``/metrics`` and info pages (docs/dask.md)::

    dask scheduler --preload bforest_dask.nohttp ...
    dask worker --preload bforest_dask.nohttp ...

The comm port (TLS with the cluster's credentials) is then the process's only listener.
"""

from __future__ import annotations


def dask_setup(server) -> None:
    """Close ``server``'s HTTP server (Dask calls this with the scheduler or worker it starts)."""
    http = getattr(server, "http_server", None)
    if http is not None:
        http.stop()
