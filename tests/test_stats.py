"""recipe.stats: the few-seed statistics of the study reports, against naive loops."""

from __future__ import annotations

import itertools
import warnings

import numpy as np
import pytest

from torchrl_rave.recipe.stats import (
    improvement_interval,
    iqm,
    mean,
    probability_of_improvement,
    stratified_interval,
)


class TestFewSeedStatistics:
    @pytest.mark.parametrize("n", [4, 8, 12, 20])
    def test_iqm_is_the_mean_of_the_middle_half(self, n):
        x = np.random.default_rng(n).normal(size=n) * 100
        middle = np.sort(x)[n // 4 : n - n // 4]
        assert iqm(x) == pytest.approx(middle.mean(), rel=1e-12)
        assert iqm(x.reshape(1, n), axis=-1)[0] == pytest.approx(middle.mean(), rel=1e-12)

    def test_probability_of_improvement_against_a_loop_over_pairs(self):
        rng = np.random.default_rng(0)
        xs = [rng.integers(0, 4, size=5).astype(float), rng.normal(size=3)]
        ys = [rng.integers(0, 4, size=4).astype(float), rng.normal(size=6)]
        per_task = []
        for x, y in zip(xs, ys, strict=True):
            wins = [1.0 if a > b else 0.5 if a == b else 0.0 for a, b in itertools.product(x, y)]
            per_task.append(sum(wins) / len(wins))
        assert probability_of_improvement(xs, ys) == pytest.approx(np.mean(per_task), abs=1e-12)

    def test_the_bootstrap_resamples_within_each_task(self):
        """Task A scores 0 on every seed and task B 10: resampled within the tasks, the
        pooled mean is 5 in every resample; pooled across them it would not be."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # scipy warns of the degenerate distribution
            value, lo, hi = stratified_interval([np.zeros(3), np.full(3, 10.0)], mean)
        assert (value, lo, hi) == (5.0, 5.0, 5.0)

    def test_intervals_hold_the_estimate_and_are_reproduced_exactly(self):
        rng = np.random.default_rng(1)
        tasks = [rng.normal(1000, 300, size=5), rng.normal(400, 100, size=5)]
        others = [rng.normal(800, 300, size=5), rng.normal(500, 100, size=5)]
        for statistic in (iqm, mean):
            value, lo, hi = stratified_interval(tasks, statistic)
            assert lo < value < hi
            assert stratified_interval(tasks, statistic) == (value, lo, hi)
        p, lo, hi = improvement_interval(tasks, others)
        assert 0 <= lo < p < hi <= 1 and improvement_interval(tasks, others) == (p, lo, hi)

    def test_one_seed_gives_no_interval(self):
        value, lo, hi = stratified_interval([np.array([3.0]), np.array([1.0, 2.0])], mean)
        assert value == 2.0 and np.isnan(lo) and np.isnan(hi)
        p, lo, hi = improvement_interval([np.array([3.0])], [np.array([1.0, 2.0])])
        assert p == 1.0 and np.isnan(lo) and np.isnan(hi)
