"""Intervals for reporting results over seeds and episodes."""

from __future__ import annotations

import math

import numpy as np

Z95 = 1.959963984540054  # the standard normal's 97.5 % quantile

# two-sided 95 % Student-t quantiles by degrees of freedom (seeds - 1)
T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262}


def interval95(values: np.ndarray) -> tuple[float, float]:
    """Mean and the half-width of its 95 % Student-t interval over seeds (NaN for one)."""
    n = len(values)
    half = T975[n - 1] * values.std(ddof=1) / np.sqrt(n) if 1 < n <= 10 else np.nan
    return float(values.mean()), float(half)


def wilson_interval(falls: int, episodes: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion ``falls / episodes``.

    Examples:
        >>> lo, hi = wilson_interval(3, 10)
        >>> round(lo, 3), round(hi, 3)
        (0.108, 0.603)
    """
    if episodes <= 0:
        raise ValueError(f"episodes must be > 0, got {episodes}")
    if not 0 <= falls <= episodes:
        raise ValueError(f"falls must lie in [0, {episodes}], got {falls}")
    p = falls / episodes
    z2n = z * z / episodes
    centre = (p + z2n / 2) / (1 + z2n)
    half = z / (1 + z2n) * math.sqrt(p * (1 - p) / episodes + z2n / (4 * episodes))
    return max(0.0, centre - half), min(1.0, centre + half)
