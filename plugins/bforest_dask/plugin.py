"""Entry point of the ``bforest_dask`` plugin: the ``dask`` executor.

Needs the optional extra ``bayesforest[dask]`` (dask + distributed). Without them importing this
module raises ``ImportError`` with the install command, and the registry lists the plugin as a
load error while every other plugin keeps working.
"""

from bforest_core.hookspecs import hookimpl

from .executor import DaskExecutor


@hookimpl
def bforest_components():
    return [DaskExecutor]
