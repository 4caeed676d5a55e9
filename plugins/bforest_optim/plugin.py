"""Entry point of the ``bforest_optim`` plugin: the optimisers ``ga``, ``cma``, ``nlopt``, ``emcee``, ``abc-smc``, ``de``."""
from bforest_core.hookspecs import hookimpl

from .abc_smc import AbcSmc
from .cma_es import CMAES
from .de import DifferentialEvolution
from .emcee_sampler import EmceeSampler
from .ga import GeneticAlgorithm
from .nlopt_optimizer import NloptOptimizer


@hookimpl
def bforest_components():
    return [GeneticAlgorithm, CMAES, NloptOptimizer, EmceeSampler, AbcSmc, DifferentialEvolution]
