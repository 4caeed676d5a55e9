"""pluggy hook specifications: registration hooks only.

A plugin is a module named by an entry point in the group ``bforest``; it defines::

    from bforest_core.hookspecs import hookimpl

    @hookimpl
    def bforest_components():
        return [MyModel, MyReader]
"""

import pluggy

PROJECT = "bforest"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def bforest_components():
    """Return the component classes this plugin provides.

    Returns
    -------
    list of type
        Subclasses of the interfaces in :mod:`bforest_core.interfaces`.
    """
