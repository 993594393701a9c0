"""Intervals for reporting results over seeds and episodes."""

from __future__ import annotations

import math

import numpy as np

Z95 = 1.959963984540054  # the standard normal's 97.5 % quantile

# two-sided 95 % Student-t quantiles by degrees of freedom (seeds - 1)
T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306,
        9: 2.262, 10: 2.228, 11: 2.201, 12: 2.179, 13: 2.160, 14: 2.145, 15: 2.131,
        16: 2.120, 17: 2.110, 18: 2.101, 19: 2.093, 20: 2.086}  # fmt: skip


def t975(dof: int) -> float:
    """The 95 % two-sided Student-t quantile; beyond 20 degrees of freedom, the one at 20
    (slightly wider than exact, never narrower)."""
    if dof < 1:
        raise ValueError(f"a t interval needs at least 1 degree of freedom, got {dof}")
    return T975[min(dof, 20)]


def interval95(values: np.ndarray) -> tuple[float, float]:
    """Mean and the half-width of its 95 % Student-t interval over seeds (NaN for one)."""
    n = len(values)
    half = t975(n - 1) * values.std(ddof=1) / np.sqrt(n) if n > 1 else np.nan
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


def difference95(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Mean of ``a`` minus mean of ``b`` (independent seeds), and the half-width of its
    95 % interval: Welch's standard error with the conservative ``min(n_a, n_b) - 1``
    degrees of freedom (NaN when either side has one seed).

    Examples:
        >>> diff, half = difference95(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 3.0]))
        >>> diff, round(half, 3)  # 4.303 * sqrt(1 / 3 + 3 / 3)
        (1.0, 4.969)
    """
    n = min(len(a), len(b))
    if n < 2:
        return float(a.mean() - b.mean()), float("nan")
    se = np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    return float(a.mean() - b.mean()), float(t975(n - 1) * se)
