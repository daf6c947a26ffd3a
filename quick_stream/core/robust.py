"""The median of the robust scales (the scene flow's outlier test, the motion's Cauchy weights).

:func:`median` is ``np.median`` of a 1-D float array, the same value bit for bit (the middle order
statistic, or the mean of the two middle ones; NaN when there is a NaN), without the generic
reduction machinery that costs more than the selection itself on a few thousand values.
"""
from __future__ import annotations

import numpy as np


def median(a: np.ndarray) -> float:
    """``float(np.median(a))`` for a 1-D float array ``a`` (NaN when empty or holding a NaN)."""
    n = a.size
    if n == 0:
        return float("nan")
    k = n // 2
    part = np.partition(a, k)  # part[k] is the k-th order statistic, part[:k] the k below it
    if np.isnan(part[k:].max()):  # NaN sorts last
        return float("nan")
    return float(part[k]) if n % 2 else float((part[:k].max() + part[k]) / 2.0)
