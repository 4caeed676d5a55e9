"""Bundled Bayes Forest plugin `bforest_treeqsm`."""
