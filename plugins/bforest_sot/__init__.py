"""Bundled Bayes Forest plugin `bforest_sot`: the self-organizing tree (SOT) growth model.

Palubicki et al. (2009) with multiplicative shadow propagation, as used by Potapov et al. (2017),
implemented after docs/models.md part B in vectorised numpy:

- :mod:`bforest_sot.light`  -- the voxel light field (log storage, batched shadow pyramids,
  trilinear exposure, gradient probes);
- :mod:`bforest_sot.model`  -- the growth engine (basipetal/acropetal passes, shedding, shoot
  construction) and the inspection records passed to ``on_step``;
- :mod:`bforest_sot.forms`  -- the growth forms (additions to the papers' model), one module each,
  and their interface (:mod:`bforest_sot.forms.base`);
- :mod:`bforest_sot.params` -- the papers' parameter table (names, calibrated defaults, ranges,
  groups), the model's with its forms', and validation;
- :mod:`bforest_sot.plugin` -- the ``ssm`` component ``"sot"`` and the output tree.

Usage::

    import bforest_core as bf
    tree = bf.component("ssm", "sot").simulate({"max_iter": 18}, seed=1)

Deviations from the original LPFG code are those of docs/models.md B.8 (gradients after drops, one shadow
batch per cycle, clean trilinear interpolation, a final width update, the general slot rule,
clone noise, growth stopping at the walls). Only the multiplicative light model is offered.
"""
