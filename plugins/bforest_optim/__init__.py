"""Bundled Bayes Forest plugin ``bforest_optim``: optimisers of the structural distance.

``ga`` (the papers' genetic algorithm), ``nlopt`` (derivative-free NLopt algorithms), ``emcee``
(ensemble sampling of ``exp(-D/epsilon)``) and ``de`` (scipy differential evolution), all
working on a :class:`bforest_core.interfaces.Problem`.
"""
