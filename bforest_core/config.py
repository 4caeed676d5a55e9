"""Run configuration (TOML) validated by pydantic. (Being built: see issue 2.)"""
from __future__ import annotations

import pydantic


def validation_error_text(exc: pydantic.ValidationError) -> str:
    """One readable line per problem: ``key.path: message (input: value)``."""
    parts = []
    for e in exc.errors():
        loc = ".".join(str(x) for x in e["loc"]) or "(top level)"
        msg = e["msg"]
        if e.get("type") == "extra_forbidden":
            msg = "unknown key"
        inp = e.get("input")
        shown = "" if isinstance(inp, dict) or e.get("type") == "missing" else f" (got {inp!r})"
        parts.append(f"{loc}: {msg}{shown}")
    return "; ".join(parts)
