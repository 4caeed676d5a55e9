"""Bundled Bayes Forest plugin `bforest_lignum`: the simplified stochastic LIGNUM SSM."""

from .ssm import LignumSettings, LignumSSM

__all__ = ["LignumSSM", "LignumSettings"]
