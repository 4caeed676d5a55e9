"""The growth forms of the SOT model: one module per optional form (:mod:`.base` is the interface).

The bundled forms, in the order the growth calls their hooks, are ``bforest_sot.plugin.FORMS``.
"""
