"""Bundled Bayes Forest plugin ``bforest_amortised``: amortised posterior estimators.

``flow``: a conditional neural spline flow (flowjax on JAX, on the CPU) of a growth model's
parameters given a tree's summaries, trained once on simulations (``bforest train``) and asked
for any tree in one pass (``bforest posterior``). Its libraries come with the optional extra
``bayesforest[amortised]``; without them the plugin still registers and says what to install.
The trained estimators shipped with the package live in ``estimators/``.
"""
