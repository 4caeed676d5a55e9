"""Entry point of the ``bforest_amortised`` plugin: the amortised estimator ``flow``."""

from bforest_core.hookspecs import hookimpl

from .flow import FlowEstimator


@hookimpl
def bforest_components():
    return [FlowEstimator]
