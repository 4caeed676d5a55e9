"""Bundled Bayes Forest plugin `bforest_optim`."""
