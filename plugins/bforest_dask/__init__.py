"""Bundled Bayes Forest plugin `bforest_dask`."""
