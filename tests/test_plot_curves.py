"""plot_curves.py on synthetic run directories."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import plot_curves
import pytest

from torchrl_rave.recipe.runs import curves, parse_groups, read_scalar


def fake_run(root: Path, exp: str, rows: list[tuple[int, float]]) -> Path:
    path = root / exp / "scalars" / "eval"
    path.mkdir(parents=True)
    (path / "return.csv").write_text("".join(f"{s},{v}\n" for s, v in rows))
    return root


class TestPlotCurves:
    def test_table_mean_std_and_last_value_before(self, tmp_path):
        fake_run(tmp_path / "a" / "seed0", "rave", [(100, 1.0), (200, 3.0), (300, 5.0)])
        fake_run(tmp_path / "a" / "seed1", "rave", [(100, 3.0), (200, 5.0), (300, 9.0)])
        fake_run(tmp_path / "b" / "seed0", "ddpg", [(100, 0.0), (200, 2.0)])
        out = tmp_path / "c.png"
        text = plot_curves.main(
            [
                f"rave={tmp_path}/a/seed*",
                f"ddpg={tmp_path}/b/seed*",
                "--at",
                "200",
                "250",
                "300",
                "--out",
                str(out),
            ]
        )
        # at 200 and 250 the last values are 3 and 5 (mean 4, std 1); at 300: 5 and 9
        assert "| rave | 2 | 4.0 ± 1.0 | 4.0 ± 1.0 | 7.0 ± 2.0 |" in text
        # ddpg's log ends at 200: nothing shows it ran to 250 or 300, so no value there
        # (before, both cells silently repeated its value at 200)
        assert "| ddpg | 1 | 2.0 ± 0.0 | n/a (ends at 200) | n/a (ends at 200) |" in text
        assert out.read_bytes()[:4] == b"\x89PNG"

    def test_max_frames_cuts_longer_runs(self, tmp_path, capsys):
        fake_run(tmp_path / "long", "rave", [(100, 1.0), (200, 3.0), (300, 50.0)])
        fake_run(tmp_path / "short", "ppo", [(100, 0.0), (200, 2.0)])
        groups = [
            f"rave={tmp_path}/long",
            f"ppo={tmp_path}/short",
            "--out",
            str(tmp_path / "c.png"),
        ]
        # without --at the table is at the last step logged, which the cut makes 200
        text = plot_curves.main([*groups, "--max-frames", "250"])
        assert "at 200 |" in text and "| rave | 1 | 3.0 ± 0.0 |" in text
        with pytest.raises(ValueError, match="--max-frames 50: no step"):
            plot_curves.main([*groups, "--max-frames", "50"])

    def test_curves_use_shared_steps_and_resumed_duplicates(self, tmp_path):
        fake_run(tmp_path / "s0", "x", [(100, 1.0), (200, 2.0), (300, 3.0)])
        # a resumed run logged step 200 twice; the later value counts; step 300 missing
        fake_run(tmp_path / "s1", "x", [(100, 5.0), (200, 6.0), (200, 7.0)])
        data = curves({"x": [tmp_path / "s0", tmp_path / "s1"]}, "eval/return")
        steps, values = data["x"]
        assert steps.tolist() == [100, 200]
        np.testing.assert_array_equal(values, [[1.0, 2.0], [5.0, 7.0]])
        assert np.isnan(plot_curves.value_at(steps, values, 50)).all()

    def test_clear_errors(self, tmp_path):
        with pytest.raises(ValueError, match="LABEL=PATTERN"):
            parse_groups(["nolabel"])
        with pytest.raises(FileNotFoundError, match="no run directory matches"):
            parse_groups([f"x={tmp_path}/missing*"])
        # a damaged line is named with its file and line number
        fake_run(tmp_path / "bad", "x", [(100, 1.0)])
        with open(tmp_path / "bad" / "x" / "scalars" / "eval" / "return.csv", "a") as f:
            f.write("60\n")
        with pytest.raises(
            ValueError, match=r"return.csv:2: expected a line 'step,value', got '60'"
        ):
            read_scalar(tmp_path / "bad", "eval/return")
        (tmp_path / "empty").mkdir()
        with pytest.raises(FileNotFoundError, match=r"no 'eval/return' logged \(no CSV or Tens"):
            read_scalar(tmp_path / "empty", "eval/return")


def test_legends_count_seeds_in_words():
    assert [plot_curves.seeds(n) for n in (1, 2, 3)] == ["1 seed", "2 seeds", "3 seeds"]
