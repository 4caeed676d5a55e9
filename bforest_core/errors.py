"""Typed exceptions of Bayes Forest, and the warning of a repaired QSM read.

Every error a user can cause derives from :class:`BayesForestError`; the CLI turns
those into one readable line and exit code 2.
"""

from __future__ import annotations

import warnings

import pydantic


class BayesForestError(Exception):
    """Base class of every error a user can cause (bad file, bad config, ...)."""


class TreeError(BayesForestError, ValueError):
    """A cylinder table violates an invariant of :class:`bforest_core.Tree`.

    Attributes
    ----------
    problem : str
        What is wrong, in words.
    rows : list of int
        0-based rows of the offending cylinders (may be empty).
    """

    def __init__(self, problem: str, rows=()):
        self.problem = problem
        self.rows = [int(r) for r in rows]
        super().__init__(problem)

    def __reduce__(self):
        """Pickle as the same error, with its problem and rows."""
        return (type(self), (self.problem, self.rows))


class QSMFormatError(BayesForestError, ValueError):
    """A QSM file cannot be read: names the file and the problem.

    Parameters
    ----------
    path : str or path-like
        The file.
    problem : str
        What is wrong, in words.
    rows : iterable of int, optional
        0-based rows of the offending cylinders (may be empty).
    """

    def __init__(self, path, problem: str, rows=()):
        self.path = str(path)
        self.problem = problem
        self.rows = [int(r) for r in rows]
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):  # pickled back from a worker as itself
        """Pickle as the same error, with its path, problem and rows."""
        return (type(self), (self.path, self.problem, self.rows))


class QSMReadWarning(UserWarning):
    """A QSM file was read with a repair or an inconsistency worth knowing about."""


def quiet_read_repairs() -> None:
    """Keep :class:`QSMReadWarning` quiet in this process.

    For a command's helper processes (the executors' workers, the report's second process): the
    command reads the same files first and reports their repairs once; a helper's copy would
    print them again, once per process, in Python's raw format.
    """
    warnings.filterwarnings("ignore", category=QSMReadWarning)


class ConfigError(BayesForestError, ValueError):
    """A run configuration or component setting is invalid (names the key path)."""


class PluginError(BayesForestError):
    """A plugin failed to load, registered a conflicting name, or was not found."""


class SimulationFailed(BayesForestError):
    """A growth model run ended with a non-ok status.

    Attributes
    ----------
    status : str
        Machine-readable status, e.g. ``"collapsed"``, ``"too_many_segments"``,
        ``"negative_balance"``, ``"timeout"``.
    tree : Tree or None
        The partial tree when the model has one.
    message : str
        What happened, in words (may be empty).
    """

    def __init__(self, status: str, message: str = "", tree=None):
        self.status = status
        self.tree = tree
        self.message = message
        super().__init__(f"simulation failed ({status})" + (f": {message}" if message else ""))

    def __reduce__(self):  # pickled back from a worker as itself (the partial tree stays behind)
        """Pickle as the same error with its status and message (without the partial tree)."""
        return (type(self), (self.status, self.message))


#: the fields a discriminated union of the config is told apart by: a component's ``kind``, and the
#: ``ssm`` of ``[target.generate]``
UNION_TAGS = ("kind", "ssm")


def _without_tags(loc: tuple, data) -> list[str]:
    """Return a validation error's location without the union tags pydantic inserts.

    A discriminated union's member adds its tag to the location (``ssm.lignum.free``, an entry's
    ``objective.terms.0.distance.summary.weights``); it is left out where the data the location
    walks through holds it as its ``kind`` or ``ssm`` (and not as a key).
    """
    out = []
    for part in loc:
        if isinstance(data, dict) and part not in data and part in [data.get(t) for t in UNION_TAGS]:
            continue
        out.append(str(part))
        if isinstance(data, dict):
            data = data.get(part)
        elif isinstance(data, list) and isinstance(part, int) and 0 <= part < len(data):
            data = data[part]
        else:
            data = None
    return out


def validation_error_text(
    exc: pydantic.ValidationError, data=None, hint=None, skip: tuple = (), prefix: tuple = ()
) -> str:
    """Render a pydantic validation error as one readable clause per problem.

    Each clause reads ``key.path: message (got value)``.

    Parameters
    ----------
    exc : pydantic.ValidationError
        The error.
    data : object, optional
        The data that was validated: the union tags pydantic inserts in key paths are read
        from it and dropped.
    hint : callable, optional
        ``hint(loc)`` returns text appended to an unknown key's message (e.g. "did you
        mean ...").
    skip : tuple of str, optional
        Top-level keys whose errors are left out (reported otherwise).
    prefix : tuple of str, optional
        The key path in the config of the data that was validated (``("target",)`` for a
        ``[target]`` table validated alone): put before every clause's own.

    Returns
    -------
    str
        The clauses joined by ``"; "``.
    """
    parts = []
    for e in exc.errors():
        if e["loc"] and str(e["loc"][0]) in skip:
            continue
        raw_loc = tuple(str(x) for x in e["loc"])
        loc = [*prefix, *(x for x in _without_tags(e["loc"], data) if not x.startswith("function-"))]
        where = ".".join(loc) or "(top level)"
        msg = e["msg"]
        if e.get("type") == "extra_forbidden":
            msg = "unknown key"
            model = e.get("ctx", {}).get("allowed")
            if model:
                msg += f" (allowed: {model})"
            if hint is not None:
                msg += hint(raw_loc)
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, ") :]
        inp = e.get("input")
        shown = (
            ""
            if isinstance(inp, dict) or e.get("type") in ("missing", "extra_forbidden", "value_error")
            else f" (got {inp!r})"
        )
        parts.append(f"{where}: {msg}{shown}")
    return "; ".join(parts)
