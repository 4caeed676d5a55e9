"""Bundled Bayes Forest plugin `bforest_formats`."""
