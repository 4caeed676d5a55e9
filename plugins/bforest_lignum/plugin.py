"""Entry point of this plugin: registers its components with Bayes Forest."""

from bforest_core.hookspecs import hookimpl


@hookimpl
def bforest_components():
    from .ssm import LignumSSM

    return [LignumSSM]
