"""Bundled Bayes Forest plugin `bforest_lignum`."""
