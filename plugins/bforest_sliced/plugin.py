"""Entry point of this plugin: registers the ``sliced`` distance with Bayes Forest."""

from bforest_core.hookspecs import hookimpl

from .sliced import SlicedDistance


@hookimpl
def bforest_components():
    return [SlicedDistance]
