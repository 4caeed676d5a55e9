"""The ``bforest`` command line (``main``) and the demo. Imports everything below it; nothing
imports it."""

from .main import main

__all__ = ["main"]
