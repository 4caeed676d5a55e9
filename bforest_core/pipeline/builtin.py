"""Components shipped inside the core (the ``serial`` and ``process`` executors), registered
through the same entry-point mechanism as every plugin."""

from ..hookspecs import hookimpl
from .executors import ProcessExecutor, SerialExecutor


@hookimpl
def bforest_components():
    return [SerialExecutor, ProcessExecutor]
