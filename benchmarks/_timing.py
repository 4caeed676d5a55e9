"""Timing helper shared by the benchmark scripts (run them from the repository root)."""

from __future__ import annotations

import statistics
import time


def timed(fn, repeats: int):
    """Run ``fn`` ``repeats`` times: ``(median s, min s, last result)``."""
    ts, out = [], None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return float(statistics.median(ts)), float(min(ts)), out


def median_time(fn, repeats: int = 5) -> float:
    """Median wall time of ``repeats`` calls of ``fn`` (s)."""
    return timed(fn, repeats)[0]
