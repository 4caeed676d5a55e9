"""Entry point of the ``bforest_optim`` plugin: the optimisers ``ga``, ``cma``, ``nlopt``, ``emcee``, ``abc-smc``, ``de``, ``turbo``."""

from bforest_core.hookspecs import hookimpl

from .abc_smc import AbcSmc
from .cma_es import CMAES
from .de import DifferentialEvolution
from .emcee_sampler import EmceeSampler
from .ga import GeneticAlgorithm
from .nlopt_optimizer import NloptOptimizer
from .turbo import Turbo


@hookimpl
def bforest_components():
    return [GeneticAlgorithm, CMAES, NloptOptimizer, EmceeSampler, AbcSmc, DifferentialEvolution, Turbo]
