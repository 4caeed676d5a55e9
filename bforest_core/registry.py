"""Entry-point discovery of plugins (group ``bforest``) with pluggy.

Each plugin is loaded and registered in isolation: one that fails to import or to register is
recorded (``bforest plugins`` lists it, a warning is issued) and skipped, so the others still
work. ``BFOREST_STRICT_PLUGINS=1`` makes such a failure fatal. Two plugins registering the same
(kind, name) make that name ambiguous: selecting it raises an error naming both distributions.
"""

from __future__ import annotations

import importlib.metadata as md
import os
import threading
import warnings
from dataclasses import dataclass, field
from typing import Any

import pluggy

from . import hookspecs
from .errors import PluginError, validation_error_text
from .interfaces import INTERFACES, KINDS, Component

GROUP = "bforest"


@dataclass
class ComponentEntry:
    """One component class a plugin registered.

    Parameters
    ----------
    kind : str
        Component kind, one of :data:`bforest_core.interfaces.KINDS`.
    name : str
        The name the component is selected by in a config.
    cls : type
        The component class (a subclass of the interface of ``kind``).
    plugin : str
        Name of the entry point that registered it.
    distribution : str
        Name of the distribution that provides the entry point.
    version : str
        Version of that distribution.
    """

    kind: str
    name: str
    cls: type
    plugin: str  # entry point name
    distribution: str  # distribution name
    version: str


@dataclass
class LoadError:
    """A plugin that failed to load or register and was skipped.

    Parameters
    ----------
    plugin : str
        Name of the entry point.
    distribution : str
        Name of the distribution that provides it.
    error : str
        The failure as ``"ExceptionType: message"``.
    """

    plugin: str
    distribution: str
    error: str


@dataclass
class Registry:
    """The components of the installed plugins, by ``(kind, name)``.

    Parameters
    ----------
    components : dict of (str, str) to ComponentEntry
        The unambiguous components.
    conflicts : dict of (str, str) to list of ComponentEntry
        Names registered by more than one plugin, with every entry; selecting one raises.
    errors : list of LoadError
        Plugins that failed to load and were skipped.
    """

    components: dict[tuple[str, str], ComponentEntry] = field(default_factory=dict)
    conflicts: dict[tuple[str, str], list[ComponentEntry]] = field(default_factory=dict)
    errors: list[LoadError] = field(default_factory=list)

    def names(self, kind: str) -> list[str]:
        """List the registered names of a kind, conflicting ones included.

        Parameters
        ----------
        kind : str
            Component kind.

        Returns
        -------
        list of str
            Sorted names.
        """
        return sorted({n for (k, n) in list(self.components) + list(self.conflicts) if k == kind})

    def get(self, kind: str, name: str) -> type:
        """Return the component class registered as ``name`` of ``kind``.

        Parameters
        ----------
        kind : str
            Component kind, one of :data:`bforest_core.interfaces.KINDS`.
        name : str
            Component name.

        Returns
        -------
        type
            The component class.

        Raises
        ------
        PluginError
            For an unknown kind, an unknown name (listing the known ones) or a name that more
            than one plugin registers (naming their distributions).
        """
        if kind not in KINDS:
            raise PluginError(f"unknown component kind {kind!r} (kinds: {', '.join(KINDS)})")
        if (kind, name) in self.conflicts:
            who = " and ".join(f"{e.distribution} ({e.plugin})" for e in self.conflicts[(kind, name)])
            raise PluginError(f"{kind} '{name}' is registered by more than one plugin: {who}; uninstall one of them")
        try:
            return self.components[(kind, name)].cls
        except KeyError:
            known = ", ".join(self.names(kind)) or "none"
            raise PluginError(f"unknown {kind} '{name}' (known: {known})") from None

    def add(self, cls: type, plugin: str, dist: str, version: str) -> None:
        """Register a component class; a second class under the same name makes a conflict.

        Registering the same class twice under one name is a no-op.

        Parameters
        ----------
        cls : type
            A subclass of an interface in :data:`bforest_core.interfaces.INTERFACES` with a
            non-empty ``name``.
        plugin : str
            Name of the entry point that provides it.
        dist : str
            Name of the distribution.
        version : str
            Version of the distribution.

        Raises
        ------
        PluginError
            If ``cls`` is not a subclass of an interface or has no ``name``.
        """
        kind = getattr(cls, "kind", None)
        name = getattr(cls, "name", None)
        if kind not in INTERFACES or not isinstance(cls, type) or not issubclass(cls, INTERFACES[kind]):
            raise PluginError(f"{cls!r} is not a subclass of a bforest interface")
        if not isinstance(name, str) or not name:
            raise PluginError(f"{cls.__qualname__} has no 'name'")
        entry = ComponentEntry(kind, name, cls, plugin, dist, version)
        key = (kind, name)
        if key in self.conflicts:
            self.conflicts[key].append(entry)
        elif key in self.components:
            if self.components[key].cls is cls:
                return
            self.conflicts[key] = [self.components.pop(key), entry]
        else:
            self.components[key] = entry


_lock = threading.Lock()
_registry: Registry | None = None


def _strict() -> bool:
    return os.environ.get("BFOREST_STRICT_PLUGINS", "") not in ("", "0", "false", "no")


def discover(refresh: bool = False) -> Registry:
    """Load every entry point of the group ``bforest`` (once per process unless ``refresh``).

    Parameters
    ----------
    refresh : bool, optional
        Load the entry points again instead of returning the cached registry.

    Returns
    -------
    Registry
        The components, conflicts and load errors of the installed plugins.

    Raises
    ------
    PluginError
        With ``BFOREST_STRICT_PLUGINS`` set: if a plugin fails to load or two plugins register
        the same name.

    Warns
    -----
    RuntimeWarning
        For each plugin that fails to load and is skipped.
    """
    global _registry
    with _lock:
        if _registry is not None and not refresh:
            return _registry
        reg = Registry()
        seen = set()
        for ep in md.entry_points(group=GROUP):
            dist = ep.dist.name if ep.dist is not None else "?"
            version = ep.dist.version if ep.dist is not None else "?"
            if (ep.name, ep.value, dist) in seen:
                continue
            seen.add((ep.name, ep.value, dist))
            try:
                module = ep.load()
                pm = pluggy.PluginManager(hookspecs.PROJECT)
                pm.add_hookspecs(hookspecs)
                pm.register(module, name=f"{dist}:{ep.name}")
                classes = [c for lst in pm.hook.bforest_components() for c in (lst or [])]
                if not classes:
                    raise PluginError("registered no components (no @hookimpl bforest_components?)")
                for cls in classes:
                    reg.add(cls, ep.name, dist, version)
            except KeyboardInterrupt:
                raise
            except BaseException as exc:  # noqa: BLE001 - one plugin never takes the others down, not even
                # with sys.exit() at import (which would end every command silently with exit 0)
                msg = f"{type(exc).__name__}: {exc}"
                reg.errors.append(LoadError(ep.name, dist, msg))
                if _strict():
                    raise PluginError(f"plugin '{ep.name}' from {dist} failed to load: {msg}") from exc
                warnings.warn(
                    f"bforest plugin '{ep.name}' from {dist} failed to load and is skipped: {msg}",
                    RuntimeWarning,
                    stacklevel=2,
                )
        if _strict() and reg.conflicts:
            k, entries = next(iter(reg.conflicts.items()))
            reg.get(*k)
        _registry = reg
        return reg


def component_class(kind: str, name: str) -> type:
    """Return the class of the installed component ``name`` of ``kind``.

    Parameters
    ----------
    kind : str
        Component kind, one of :data:`bforest_core.interfaces.KINDS`.
    name : str
        Component name.

    Returns
    -------
    type
        The component class.

    Raises
    ------
    PluginError
        For an unknown or ambiguous name (see :meth:`Registry.get`).
    """
    return discover().get(kind, name)


def component(kind: str, name: str, **settings: Any) -> Component:
    """Return a configured instance of the component ``name`` of ``kind``.

    Parameters
    ----------
    kind : str
        Component kind, one of :data:`bforest_core.interfaces.KINDS`.
    name : str
        Component name.
    **settings
        The component's settings.

    Returns
    -------
    Component
        The configured instance.

    Raises
    ------
    PluginError
        For an unknown name (listing the known ones) or an ambiguous one.
    ConfigError
        For invalid settings.
    """
    import pydantic

    from .errors import ConfigError

    cls = component_class(kind, name)
    try:
        return cls(**settings)
    except pydantic.ValidationError as exc:
        raise ConfigError(f"{kind} '{name}': {validation_error_text(exc)}") from None
