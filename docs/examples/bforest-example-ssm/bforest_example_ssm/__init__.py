"""bforest-example-ssm: an example third-party Bayes Forest plugin (a stochastic L-system SSM)."""

from .model import PARAMETERS, LSystemSettings, LSystemSSM, grow

__all__ = ["LSystemSSM", "LSystemSettings", "PARAMETERS", "grow"]
__version__ = "0.1.0"
