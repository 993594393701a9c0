"""The README's "Use RAVE in your own TorchRL loss" example runs as written."""

from __future__ import annotations

import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"


def section_code(title: str) -> str:
    text = README.read_text()
    start = text.index(f"## {title}")
    end = text.find("\n## ", start + 1)
    blocks = re.findall(r"```python\n(.*?)```", text[start:end], flags=re.S)
    assert blocks, f"no python block under '## {title}'"
    return blocks[0]


def test_use_rave_in_your_own_loss(capsys):
    torch.manual_seed(0)
    scope: dict = {}
    exec(compile(section_code("Use RAVE in your own TorchRL loss"), str(README), "exec"), scope)
    loss, ddpg = scope["loss"], scope["ddpg"]
    assert type(loss.value_estimator).__name__ == "RAVEValueEstimator"
    assert type(ddpg.value_estimator).__name__ == "RAVEValueEstimator"
    weights = loss.value_estimator.diagnostics["rave_horizon_weights"]
    assert weights.shape == (256, 4)
    torch.testing.assert_close(weights.sum(-1), torch.ones(256))
    assert torch.isfinite(scope["out"]["loss_qvalue"])
    assert "tensor(" in capsys.readouterr().out
