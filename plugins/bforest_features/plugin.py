"""Entry point of this plugin: registers the ``branch-segment`` feature set with Bayes Forest."""

from bforest_core.hookspecs import hookimpl

from .branch_segment import BranchSegmentFeatures


@hookimpl
def bforest_components():
    return [BranchSegmentFeatures]
