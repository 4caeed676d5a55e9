"""The resolution the sliced distance sees, and why its projections are exact.

Before projecting, every normalised value is snapped to a grid of ``2**-VALUE_BITS`` (about 1e-6
of its column's scale: 2e-8 m for a radius spread of 2 cm, 2 µm for lengths spread over 2 m,
3e-5 degrees for angles spread over 30 degrees) and every direction component to a grid of
``2**-DIRECTION_BITS`` (about 1e-6). A projection is then a sum of products that are multiples
of ``2**-(VALUE_BITS + DIRECTION_BITS)``; while the sum stays below ``2**(53 - VALUE_BITS -
DIRECTION_BITS)`` = 8192 in absolute value (a row whose normalised values add up to less than
8192 column scales) every partial sum is a float64 exactly, so the result is the same whatever
order a BLAS kernel sums in, on every CPU. Equal rows give equal projections and ties stay ties;
round-off from another numbering of the tree, a translation or another machine's last bit (far
below the grid) snaps away. See ``docs/validation.md``, "What the distance resolves".
"""

from __future__ import annotations

import numpy as np

__all__ = ["VALUE_BITS", "DIRECTION_BITS", "snap"]

#: bits below the point of a normalised value: grid 2^-20 (about 1e-6) of the column's scale
VALUE_BITS = 20
#: bits below the point of a direction component: grid 2^-20
DIRECTION_BITS = 20


def snap(x: np.ndarray, bits: int) -> np.ndarray:
    """A new array of ``x`` rounded to the nearest multiple of ``2**-bits``.

    Every step is exact in float64 (a scaling by a power of two, a rounding to an integer and
    the scaling back); ``-0.0`` becomes ``+0.0`` (equal values, equal bits: the KS label
    encoding reads the bits).
    """
    s = float(2**bits)
    out = np.multiply(x, s)
    np.rint(out, out=out)
    out /= s
    out += 0.0
    return out
