"""falling_rate.py: the Wilson interval by hand, pooled logged rates, and real checkpoints."""

from __future__ import annotations

import re
from pathlib import Path

import falling_rate
import pytest
from test_recipe import TINY, make_cfg


class TestWilson:
    def test_three_of_ten(self):
        # p = 0.3, z^2/n = 0.38415: centre 0.35552, half-width 0.24771
        lo, hi = falling_rate.wilson_interval(3, 10)
        assert lo == pytest.approx(0.10779, abs=1e-4)
        assert hi == pytest.approx(0.60322, abs=1e-4)

    def test_no_falls_has_a_zero_lower_bound(self):
        lo, hi = falling_rate.wilson_interval(0, 10)
        assert lo == 0.0
        # upper bound z^2/n / (1 + z^2/n) when p = 0
        assert hi == pytest.approx(0.38415 / 1.38415, abs=1e-4)

    def test_symmetry(self):
        lo, hi = falling_rate.wilson_interval(2, 25)
        lo2, hi2 = falling_rate.wilson_interval(23, 25)
        assert (lo, hi) == pytest.approx((1 - hi2, 1 - lo2))

    @pytest.mark.parametrize("k,n", [(-1, 10), (11, 10), (0, 0)])
    def test_bad_counts(self, k, n):
        with pytest.raises(ValueError):
            falling_rate.wilson_interval(k, n)


def write_run(root: Path, name: str, rates: dict[int, float]) -> None:
    scalars = root / name / "rave" / "scalars" / "eval"
    scalars.mkdir(parents=True)
    (scalars / "falling_rate.csv").write_text("".join(f"{s},{r}\n" for s, r in rates.items()))


def test_logged_rates_are_pooled_over_seeds(tmp_path):
    write_run(tmp_path, "seed0", {1000: 0.3, 2000: 0.1})
    write_run(tmp_path, "seed1", {1000: 0.5, 2000: 0.0, 3000: 0.0})  # 3000: seed0 lacks it
    out = tmp_path / "fall.png"
    text = falling_rate.main(
        [f"rave={tmp_path}/seed*", "--episodes", "0", "--eval-episodes", "10", "--out", str(out)]
    )
    steps, falls, episodes = falling_rate.logged_falls([tmp_path / "seed0", tmp_path / "seed1"], 10)
    assert steps.tolist() == [1000, 2000]
    assert falls.tolist() == [8, 1] and episodes.tolist() == [20, 20]
    lo, hi = falling_rate.wilson_interval(1, 20)
    assert f"step 2000, 1 / 20 fell (0.050, 95% [{lo:.3f}, {hi:.3f}])" in text
    assert out.stat().st_size > 10_000


def test_from_checkpoints(tmp_path):
    import rave_mujoco

    for seed in (0, 1):
        rave_mujoco.train(
            make_cfg(*TINY, "algorithm=ddpg", f"env.seed={seed}"), str(tmp_path / f"s{seed}")
        )
    text = falling_rate.main(
        [f"ddpg={tmp_path}/s*", "--episodes", "3", "--out", str(tmp_path / "f.png")]
    )
    row = re.search(r"\| ddpg \| 2 \| (\d+) / 6 \| ([\d.]+) \| \[([\d.]+), ([\d.]+)\] \|", text)
    assert row, text
    k = int(row.group(1))
    assert 0 <= k <= 6 and float(row.group(2)) == pytest.approx(k / 6, abs=1e-3)
    lo, hi = falling_rate.wilson_interval(k, 6)
    assert (float(row.group(3)), float(row.group(4))) == pytest.approx((lo, hi), abs=1e-3)
    # one episode at a time (for the progress bar) plays the episodes one call plays
    at_once = 0
    for seed in (0, 1):
        _, env, actor, _ = falling_rate.load_run(tmp_path / f"s{seed}")
        env.set_seed(2024)
        at_once += round(falling_rate.evaluate(env, actor, 3)["eval/falling_rate"] * 3)
    assert k == at_once


def test_help_and_bad_pattern(capsys):
    with pytest.raises(SystemExit) as e:
        falling_rate.main(["--help"])
    assert e.value.code == 0
    with pytest.raises(SystemExit):
        falling_rate.main(["rave=/nonexistent/run*", "--episodes", "0"])
    assert "no run directory matches" in capsys.readouterr().err
    # a count behind the logged rates below 1 would make negative falls, not an error
    for bad in ("0", "-5"):
        with pytest.raises(SystemExit):
            falling_rate.main(["rave=/nonexistent/run*", "--eval-episodes", bad])
        assert "--eval-episodes must be >= 1" in capsys.readouterr().err
