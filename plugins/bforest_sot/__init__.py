"""Bundled Bayes Forest plugin `bforest_sot`."""
