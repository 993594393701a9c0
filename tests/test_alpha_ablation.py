"""alpha_ablation.py: launches the variants as real runs and plots their curves."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import alpha_ablation
import pytest
from test_recipe import TINY


def logged(path: Path, metric: str) -> list[float]:
    with open(path / f"{metric}.csv") as f:
        return [float(v) for _, v in csv.reader(f)]


def test_two_variants_end_to_end(tmp_path):
    tiny = [o for o in TINY if not o.startswith("collector.total_frames")]
    text = alpha_ablation.main(
        [
            "--seeds", "0",
            "--frames", "400",
            "--jobs", "2",
            "--variants", "rave_alpha0", "rave",
            "--out", str(tmp_path),
            "--", *tiny,
        ]
    )  # fmt: skip
    rows = re.findall(r"\| (.+?) \| 1 \| (-?[\d.]+) ± 0.0 \|", text)
    assert [label for label, _ in rows] == [
        "alpha = 0 (constant)",
        "dynamic alpha (eq. 12, alpha = 1.5)",
    ]
    base = tmp_path / "Hopper-v5"
    constant = logged(
        base / "rave_alpha0" / "seed0" / "rave_alpha0" / "scalars" / "train", "rave_alpha"
    )
    dynamic = logged(base / "rave" / "seed0" / "rave" / "scalars" / "train", "rave_alpha")
    assert constant and all(a == 0.0 for a in constant)
    assert dynamic and all(0.0 <= a <= 1.5 for a in dynamic)
    assert (base / "alpha_ablation.png").stat().st_size > 10_000
    # a second call finds every run finished and only plots
    again = alpha_ablation.main(
        ["--seeds", "0", "--frames", "400", "--variants", "rave_alpha0", "rave",
         "--out", str(tmp_path), "--plot-only"]
    )  # fmt: skip
    assert again == text


def test_help_lists_the_variants(capsys):
    with pytest.raises(SystemExit) as e:
        alpha_ablation.main(["--help"])
    assert e.value.code == 0
    with pytest.raises(SystemExit):
        alpha_ablation.main(["--variants", "rave_alpha7"])
    assert "invalid choice" in capsys.readouterr().err
