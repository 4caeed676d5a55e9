"""Entry-point module of the plugin (``[project.entry-points.bforest] lsystem = ...``).

Bayes Forest imports this module at discovery and calls its ``bforest_components`` hook.
"""

from bforest_core.hookspecs import hookimpl

from .model import LSystemSSM


@hookimpl
def bforest_components():
    """The components this distribution provides."""
    return [LSystemSSM]
