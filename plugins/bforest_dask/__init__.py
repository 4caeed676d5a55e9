"""Bundled Bayes Forest plugin ``bforest_dask``: the ``dask`` executor (optional extra
``bayesforest[dask]``). See ``docs/dask.md``."""
