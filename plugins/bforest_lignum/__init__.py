"""Bundled Bayes Forest plugin `bforest_lignum`: the simplified stochastic LIGNUM SSM."""
from .ssm import LignumSSM, LignumSettings

__all__ = ["LignumSSM", "LignumSettings"]
