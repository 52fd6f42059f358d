"""Small statistics of a few floats on the per-epoch paths (decoding, aiding), without
numpy's or :mod:`statistics`' per-call cost."""

from __future__ import annotations

import math
from collections.abc import Sequence


def median(values: Sequence[float]) -> float:
    """The median of ``values`` as :func:`numpy.median` gives it, to the last bit: the middle
    value, or the mean (a + b) / 2 of the two middle ones (:func:`statistics.median`'s too);
    NaN when any value is NaN."""
    if any(v != v for v in values):
        return math.nan
    s = sorted(values)
    mid = len(s) // 2
    return s[mid] if len(s) % 2 else (s[mid - 1] + s[mid]) / 2.0
