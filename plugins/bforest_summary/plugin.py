"""Registers the summary components with Bayes Forest: ``tree-summary`` and ``summary``."""

from bforest_core.hookspecs import hookimpl

from .summary import SummaryDistance, TreeSummary


@hookimpl
def bforest_components():
    return [TreeSummary, SummaryDistance]
