"""The toy study's quick mode: every method and noise level trains and lands in the table."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

RECIPES = Path(__file__).resolve().parents[1] / "recipes"


def test_quick_study_writes_table_and_figure(tmp_path):
    proc = subprocess.run(
        [sys.executable, str(RECIPES / "toy_q_bias.py"), "quick=true", f"out={tmp_path}",
         f"hydra.run.dir={tmp_path}"],
        capture_output=True,
        text=True,
        timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    table = (tmp_path / "toy_q_bias.md").read_text()
    rows = [line for line in table.splitlines() if re.match(r"\| [01] \| ", line)]
    assert len(rows) == 8  # 4 methods x k in {0, 1}
    assert {row.split("|")[2].strip() for row in rows} == {"ddpg", "mve", "steve", "rave"}
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        numbers = [float(x) for cell in cells[2:] for x in re.findall(r"[-+]?\d+\.\d+", cell)]
        assert len(numbers) == 6 and all(math.isfinite(x) for x in numbers), row
    # the ground truth column is the exact value, the same for every method at one k
    truths = {cells.split("|")[1].strip(): cells.split("|")[5].strip() for cells in rows}
    assert truths == {"0": "431.6", "1": "433.6"}
    png = (tmp_path / "toy_q_bias.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
