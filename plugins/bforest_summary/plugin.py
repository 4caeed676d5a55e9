"""Registers the summary components with Bayes Forest."""
from bforest_core.hookspecs import hookimpl


@hookimpl
def bforest_components():
    return []
