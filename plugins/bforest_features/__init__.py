"""Bundled Bayes Forest plugin `bforest_features`."""
