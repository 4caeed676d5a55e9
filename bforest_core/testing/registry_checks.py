"""Checks of any component by kind, and of every registered component."""

from __future__ import annotations

import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from ..interfaces import KINDS
from ._base import Check, ConformanceError, Report, _run
from .amortised import amortised_checks
from .distance import distance_checks
from .executor import executor_checks
from .features import feature_set_checks
from .io import reader_checks, writer_checks
from .optimizer import optimizer_checks
from .samples import sample_tree
from .ssm import ssm_checks

_CHECKS = {
    "ssm": ssm_checks,
    "features": feature_set_checks,
    "distance": distance_checks,
    "qsm_reader": reader_checks,
    "qsm_writer": writer_checks,
    "optimizer": optimizer_checks,
    "executor": executor_checks,
    "amortised": amortised_checks,
}


def component_checks(component, **options) -> list[Check]:
    """The checks of any component (class or instance), chosen by its ``kind``; ``options`` go
    to the kind's ``*_checks`` function (readers need ``paths``, writers ``out_dir``)."""
    cls = component if isinstance(component, type) else type(component)
    kind = getattr(cls, "kind", None)
    if kind not in _CHECKS:
        raise ConformanceError(f"{cls.__qualname__}", [("class", f"kind {kind!r} is not one of {KINDS}")])
    return _CHECKS[kind](component, **options)


def check_component(component, *, raise_on_failure: bool = True, **options) -> Report:
    """Run :func:`component_checks`; raises :class:`ConformanceError` listing the failures.

    Examples
    --------
    >>> import bforest_core as bf
    >>> from bforest_core.testing import check_component
    >>> print(check_component(bf.component_class("executor", "serial")))   # doctest: +SKIP
    executor 'serial': 4/4 checks passed
    ...
    """
    checks = component_checks(component, **options)
    return _run(checks, checks[0].component, raise_on_failure)


def _written_sample(reg, name: str, folder: Path) -> Path | None:
    """:func:`sample_tree` written by the registered writer ``name`` (for the reader of that
    name), or None when no writer has that name."""
    writer = reg.components.get(("qsm_writer", name))
    if writer is None:
        return None
    return Path(writer.cls().write(sample_tree(), folder / f"sample_{name}{writer.cls.suffixes[0]}"))


def run_all(
    distribution: str | None = None,
    kinds: Iterable[str] | None = None,
    names: Iterable[str] | None = None,
    options: Mapping[tuple[str, str], Mapping[str, Any]] | None = None,
    *,
    raise_on_failure: bool = True,
) -> dict[tuple[str, str], Report]:
    """Check every registered component (of one distribution, kinds or names).

    Parameters
    ----------
    distribution : str, optional
        Only components registered by this distribution (e.g. ``"bforest-example-ssm"``).
    kinds, names : iterable of str, optional
        Only these kinds / names.
    options : mapping, optional
        ``{(kind, name): {option: value}}`` passed to the kind's checks (e.g. fast SSM
        ``params``, a reader's sample ``paths``, a writer's ``out_dir``). A writer without
        ``out_dir`` writes to a temporary folder; a reader without ``paths`` reads
        :func:`sample_tree` as written by the registered writer of the same name, and is
        skipped (``Report.skipped`` says why) only when there is no such writer.
    raise_on_failure : bool
        Raise one :class:`ConformanceError` listing every failed check of every component.

    Returns
    -------
    dict
        ``(kind, name) -> Report``.
    """
    from ..registry import discover

    reg = discover()
    options = dict(options or {})
    kinds = set(kinds) if kinds is not None else None
    names = set(names) if names is not None else None
    reports: dict[tuple[str, str], Report] = {}
    with tempfile.TemporaryDirectory(prefix="bforest-conformance-") as tmp:
        for (kind, name), entry in sorted(reg.components.items()):
            if distribution is not None and entry.distribution != distribution:
                continue
            if (kinds is not None and kind not in kinds) or (names is not None and name not in names):
                continue
            opts = dict(options.get((kind, name), {}))
            opts.setdefault("registered", entry.distribution)
            label = f"{kind} '{name}'"
            if kind == "qsm_writer":
                opts.setdefault("out_dir", tmp)
            if kind == "qsm_reader" and "paths" not in opts:
                sample = _written_sample(reg, name, Path(tmp))
                if sample is None:
                    reports[(kind, name)] = Report(
                        label,
                        skipped="needs sample files (no writer of the same name "
                        "writes one): options={(kind, name): {'paths': [...]}}",
                    )
                    continue
                opts["paths"] = [sample]
            reports[(kind, name)] = _run(component_checks(entry.cls, **opts), label, False)
    if distribution is not None and not reports:
        raise ConformanceError(
            f"distribution {distribution!r}",
            [
                (
                    "registered",
                    "registers no components (is it installed? known distributions: "
                    f"{sorted({e.distribution for e in reg.components.values()})})",
                )
            ],
        )
    if raise_on_failure:
        failures = [(f"{r.component}: {f.check}", f.problem) for r in reports.values() for f in r.failures]
        if failures:
            raise ConformanceError("conformance run", failures)
    return reports
