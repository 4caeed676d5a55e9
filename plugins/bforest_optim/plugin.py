"""Entry point of the ``bforest_optim`` plugin: the optimisers ``ga``, ``cma``, ``nlopt``, ``emcee``, ``de``."""
from bforest_core.hookspecs import hookimpl

from .cma_es import CMAES
from .de import DifferentialEvolution
from .emcee_sampler import EmceeSampler
from .ga import GeneticAlgorithm
from .nlopt_optimizer import NloptOptimizer


@hookimpl
def bforest_components():
    return [GeneticAlgorithm, CMAES, NloptOptimizer, EmceeSampler, DifferentialEvolution]
