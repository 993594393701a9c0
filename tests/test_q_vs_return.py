"""q_vs_return.py: returns, ellipses, statistics, and a run from a real checkpoint."""

from __future__ import annotations

import re

import numpy as np
import pytest
import q_vs_return
from test_recipe import TINY, make_cfg


class TestPieces:
    def test_discounted_returns_by_hand(self):
        g = q_vs_return.discounted_returns(np.array([1.0, 2.0, 4.0]), gamma=0.5)
        np.testing.assert_allclose(g, [1 + 0.5 * 2 + 0.25 * 4, 2 + 0.5 * 4, 4.0])

    def test_perfect_prediction_collapses_onto_identity(self):
        x = np.random.default_rng(0).normal(size=500)
        e = q_vs_return.ellipse(x, x.copy(), n_sigma=2)
        np.testing.assert_allclose(e[:, 0], e[:, 1], atol=1e-6)
        # the 2-sigma segment spans mean +- 2 std along the identity
        assert e[:, 0].max() == pytest.approx(x.mean() + 2 * x.std(), rel=1e-3)

    def test_ellipse_of_independent_unit_normals_is_a_circle(self):
        rng = np.random.default_rng(1)
        x, y = rng.normal(size=200_000), rng.normal(size=200_000)
        radius = np.linalg.norm(q_vs_return.ellipse(x, y, n_sigma=1), axis=1)
        np.testing.assert_allclose(radius, 1.0, atol=0.01)

    def test_statistics(self):
        s = q_vs_return.statistics(np.array([1.0, 2.0, 3.0]), np.array([2.0, 3.0, 4.0]))
        assert s["bias"] == pytest.approx(1.0) and s["rmse"] == pytest.approx(1.0)
        assert s["correlation"] == pytest.approx(1.0) and s["states"] == 3


def test_from_checkpoints(tmp_path):
    import rave_mujoco

    for algo in ("ddpg", "rave"):
        rave_mujoco.train(make_cfg(*TINY, f"algorithm={algo}"), str(tmp_path / algo))
    out = tmp_path / "q.png"
    text = q_vs_return.main(
        [
            f"ddpg={tmp_path / 'ddpg'}",
            f"rave={tmp_path / 'rave'}",
            "--episodes",
            "3",
            "--out",
            str(out),
        ]
    )
    rows = [line for line in text.splitlines() if re.match(r"\| (ddpg|rave) \|", line)]
    assert len(rows) == 2
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert int(cells[1]) >= 3  # at least one state per episode
        assert all(np.isfinite(float(c)) for c in cells[2:])
    assert out.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        q_vs_return.main([f"x={tmp_path}", "--out", str(out)])


def test_bad_counts_are_named(capsys):
    # a negative --drop-tail would keep the truncated episodes' tails, not cut them
    for flag, value, problem in (("--episodes", "0", "--episodes must be >= 1"),
                                 ("--drop-tail", "-5", "--drop-tail must be >= 0")):  # fmt: skip
        with pytest.raises(SystemExit):
            q_vs_return.main(["x=/nonexistent", flag, value])
        assert problem in capsys.readouterr().err
