"""Components shipped inside the core (the ``serial`` and ``process`` executors), registered
through the same entry-point mechanism as every plugin."""
from .executors import ProcessExecutor, SerialExecutor
from ..hookspecs import hookimpl


@hookimpl
def bforest_components():
    return [SerialExecutor, ProcessExecutor]
