"""Intervals for reporting results over seeds and episodes (quantiles, Wilson intervals
and bootstrap resampling from ``scipy.stats``)."""

from __future__ import annotations

import numpy as np


def t975(dof: int) -> float:
    """The 95 % two-sided Student-t quantile at ``dof`` degrees of freedom
    (``scipy.stats.t``).

    Examples:
        >>> round(t975(1), 4), round(t975(2), 4)
        (12.7062, 4.3027)
    """
    if dof < 1:
        raise ValueError(f"a t interval needs at least 1 degree of freedom, got {dof}")
    from scipy.stats import t

    return float(t.ppf(0.975, dof))


def interval95(values: np.ndarray) -> tuple[float, float]:
    """Mean and the half-width of its 95 % Student-t interval over seeds (NaN for one)."""
    n = len(values)
    half = t975(n - 1) * values.std(ddof=1) / np.sqrt(n) if n > 1 else np.nan
    return float(values.mean()), float(half)


def wilson_interval(falls: int, episodes: int) -> tuple[float, float]:
    """The 95 % Wilson score interval of a binomial proportion ``falls / episodes``
    (``scipy.stats.binomtest``).

    Examples:
        >>> lo, hi = wilson_interval(3, 10)
        >>> round(lo, 3), round(hi, 3)
        (0.108, 0.603)
    """
    if episodes <= 0:
        raise ValueError(f"episodes must be > 0, got {episodes}")
    if not 0 <= falls <= episodes:
        raise ValueError(f"falls must lie in [0, {episodes}], got {falls}")
    from scipy.stats import binomtest

    ci = binomtest(falls, episodes).proportion_ci(confidence_level=0.95, method="wilson")
    return float(ci.low), float(ci.high)


def difference95(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Mean of ``a`` minus mean of ``b`` (independent seeds), and the half-width of its
    95 % interval: Welch's standard error with the conservative ``min(n_a, n_b) - 1``
    degrees of freedom (NaN when either side has one seed).

    Examples:
        >>> diff, half = difference95(np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 3.0]))
        >>> diff, round(half, 3)  # t(0.975, 2) = 4.3027, times sqrt(1 / 3 + 3 / 3)
        (1.0, 4.968)
    """
    n = min(len(a), len(b))
    if n < 2:
        return float(a.mean() - b.mean()), float("nan")
    se = np.sqrt(a.var(ddof=1) / len(a) + b.var(ddof=1) / len(b))
    return float(a.mean() - b.mean()), float(t975(n - 1) * se)


# Few-seed statistics as the field reports them (Agarwal et al., 2021, "Deep RL at the edge
# of the statistical precipice": the `rliable` package). rliable 1.2 does not run against
# this stack's pandas 3 (its `arch` dependency fails to import, and the `arch` that imports
# breaks rliable's bootstrap), so the resampling is scipy's.
BOOTSTRAP_RESAMPLES = 10_000


def iqm(values: np.ndarray, axis: int | None = None) -> float | np.ndarray:
    """The interquartile mean: the mean of the middle half of ``values`` (flattened, or
    along ``axis``), a quarter cut from each end as ``scipy.stats.trim_mean`` cuts it (no
    cut below 4 values).

    Examples:
        >>> iqm(np.array([0.0, 1.0, 2.0, 3.0, 100.0, -100.0, 4.0, 5.0]))
        2.5
    """
    from scipy.stats import trim_mean

    if axis is None:
        return float(trim_mean(np.ravel(values), 0.25))
    return trim_mean(values, 0.25, axis=axis)


def mean(values: np.ndarray, axis: int | None = None) -> float | np.ndarray:
    """The mean of ``values`` (flattened, or along ``axis``), as :func:`iqm` is called."""
    return float(np.mean(values)) if axis is None else np.mean(values, axis=axis)


def stratified_interval(
    samples: list[np.ndarray], statistic, *, seed: int = 0
) -> tuple[float, float, float]:
    """``statistic`` (:func:`iqm` or :func:`mean`: called with an ``axis``) of the pooled
    ``samples`` (one array of per-seed scores per task) and its 95 % percentile interval from a stratified bootstrap: each task's seeds are
    resampled with replacement within that task, ``BOOTSTRAP_RESAMPLES`` times
    (``scipy.stats.bootstrap``, seeded, so a report is reproduced exactly). The interval is
    NaN where a task has fewer than two seeds or every score is equal.

    Examples:
        >>> value, lo, hi = stratified_interval([np.array([1.0, 2.0, 3.0, 4.0])], iqm)
        >>> value, lo <= value <= hi
        (2.5, True)
    """
    from scipy.stats import bootstrap

    samples = [np.ravel(s) for s in samples]
    pooled = np.concatenate(samples)
    value = float(statistic(pooled))
    if min(len(s) for s in samples) < 2 or np.all(pooled == pooled[0]):
        return value, float("nan"), float("nan")
    result = bootstrap(
        samples,
        lambda *xs, axis: statistic(np.concatenate(xs, axis=axis), axis=axis),
        n_resamples=BOOTSTRAP_RESAMPLES,
        vectorized=True,
        paired=False,
        method="percentile",
        rng=np.random.default_rng(seed),
    )
    interval = result.confidence_interval
    return value, float(interval.low), float(interval.high)


def probability_of_improvement(xs: list[np.ndarray], ys: list[np.ndarray]) -> float:
    """P(X > Y): the chance that a run of X scores above a run of Y on a task drawn from
    the tasks, ties counted half (the Mann-Whitney statistic over ``len(x) * len(y)``,
    averaged over the tasks; ``xs[i]`` and ``ys[i]`` are the per-seed scores on task ``i``).

    Examples:
        >>> probability_of_improvement([np.array([1.0, 3.0])], [np.array([2.0, 2.0])])
        0.5
        >>> probability_of_improvement([np.array([3.0])], [np.array([1.0, 3.0])])
        0.75
    """
    return float(_improvement(xs, ys))


def _improvement(xs, ys) -> np.ndarray:
    """:func:`probability_of_improvement` over the last axis of each array (any leading
    dims: the bootstrap's resamples)."""
    if len(xs) != len(ys) or not xs:
        raise ValueError(f"one array per task for each side, got {len(xs)} and {len(ys)}")
    per_task = []
    for x, y in zip(xs, ys, strict=True):
        x, y = np.asarray(x)[..., :, None], np.asarray(y)[..., None, :]
        per_task.append(((x > y) + 0.5 * (x == y)).mean((-2, -1)))
    return np.mean(per_task, axis=0)


def improvement_interval(
    xs: list[np.ndarray], ys: list[np.ndarray], *, seed: int = 0
) -> tuple[float, float, float]:
    """:func:`probability_of_improvement` and its 95 % percentile interval from a stratified
    bootstrap: each task's X runs and Y runs resampled separately, within the task
    (NaN where a side of a task has fewer than two seeds)."""
    from scipy.stats import bootstrap

    value = probability_of_improvement(xs, ys)
    samples = [np.ravel(s) for pair in zip(xs, ys, strict=True) for s in pair]
    if min(len(s) for s in samples) < 2:
        return value, float("nan"), float("nan")

    def statistic(*resampled, axis):  # resamples on the last axis
        return _improvement(list(resampled[0::2]), list(resampled[1::2]))

    result = bootstrap(samples, statistic, n_resamples=BOOTSTRAP_RESAMPLES, vectorized=True,
                       paired=False, method="percentile", rng=np.random.default_rng(seed))  # fmt: skip
    interval = result.confidence_interval
    return value, float(interval.low), float(interval.high)
