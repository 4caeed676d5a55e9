"""Bayes Forest core: the cylinder tree, component interfaces, registry, config and pipeline.

Public names (see ``DESIGN.md``)::

    import bforest_core as bf
    tree = bf.read_qsm(path)
    ssm = bf.component("ssm", "sot"); t = ssm.simulate({}, seed=1)
"""
from importlib.metadata import PackageNotFoundError, version as _version

from .errors import (BayesForestError, ConfigError, PluginError, QSMFormatError, SimulationFailed,
                     TreeError)
from .tree import TOPOLOGY_RULES, BranchTable, Tree
from .interfaces import (KINDS, SSM, Component, ComponentSettings, Distance, Executor, FeatureSet,
                         OptimizeResult, Optimizer, ParameterSpec, Problem, QSMReader, QSMWriter)
from .registry import component, component_class, discover
from .io import read_qsm, write_tree

try:
    __version__ = _version("bayesforest")
except PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+local"


def __getattr__(name):
    # heavier parts are imported lazily so `import bforest_core` stays fast
    if name in ("load_config", "RunConfig"):
        from . import config
        return getattr(config, name)
    if name in ("classical_metrics", "relative_errors"):
        from . import metrics
        return getattr(metrics, name)
    if name == "fit":
        from .fit import fit
        return fit
    if name == "clones":
        from .clones import clones
        return clones
    raise AttributeError(f"module 'bforest_core' has no attribute {name!r}")
