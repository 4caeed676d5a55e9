"""Bundled Bayes Forest plugin `bforest_sliced`."""
