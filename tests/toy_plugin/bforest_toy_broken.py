"""A plugin that fails to import (tests that discovery survives it)."""

raise ImportError("bforest_toy_broken needs a package that is not installed")
