"""Bayes Forest core: the cylinder tree, component interfaces, registry, config and pipeline.

Public names (see docs/architecture.md)::

    import bforest_core as bf
    tree = bf.read_qsm(path)
    ssm = bf.component("ssm", "sot"); t = ssm.simulate({}, seed=1)
"""

from .config import load_config
from .errors import BayesForestError, ConfigError, PluginError, QSMFormatError, SimulationFailed, TreeError
from .interfaces import (
    KINDS,
    SSM,
    Component,
    ComponentSettings,
    Distance,
    Executor,
    FeatureSet,
    LineDistance,
    Optimizer,
    OptimizeResult,
    ParameterSpec,
    Problem,
    QSMReader,
    QSMWriter,
    RecipeDraft,
    RecipePart,
    RecipePlan,
)
from .io import read_qsm, write_tree
from .pipeline.clones import clones

# binding the functions after importing their modules keeps `bf.fit`/`bf.clones` callable
from .pipeline.fit import fit
from .provenance import __version__
from .registry import component, component_class, discover
from .tree import TOPOLOGY_RULES, BranchTable, Tree


def __getattr__(name):
    """Return ``classical_metrics`` or ``relative_errors`` from :mod:`bforest_core.metrics`.

    The metrics module is imported on first use.

    Parameters
    ----------
    name : str
        The attribute's name.

    Returns
    -------
    callable
        The metric function.

    Raises
    ------
    AttributeError
        For any other name.
    """
    # metrics live in their own module, imported on first use
    if name in ("classical_metrics", "relative_errors"):
        from . import metrics

        return getattr(metrics, name)
    raise AttributeError(f"module 'bforest_core' has no attribute {name!r}")
