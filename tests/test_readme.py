"""The README's "Use RAVE in your own TorchRL loss" example runs as written."""

from __future__ import annotations

import re
import warnings
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


def run_example(code: str, path: Path) -> dict:
    """Runs an example as written; returns its names. Any warning it raises, other than a
    DeprecationWarning from an import, fails the test: a user who copies the example
    should see none (torchrl 0.14's collector warns when the env lacks the InitTracker
    every TorchRL policy asks for)."""
    scope: dict = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        exec(compile(code, str(path), "exec"), scope)
    raised = [f"{w.category.__name__}: {w.message}" for w in caught
              if not issubclass(w.category, DeprecationWarning)]  # fmt: skip
    assert not raised, raised
    return scope


def test_use_rave_in_your_own_loss(capsys):
    torch.manual_seed(0)
    scope = run_example(section_code("Use RAVE in your own TorchRL loss"), README)
    loss, wm_trainer = scope["loss"], scope["wm_trainer"]
    assert type(loss.value_estimator).__name__ == "RAVEValueEstimator"
    weights = loss.value_estimator.diagnostics["rave_horizon_weights"]
    assert weights.shape == (256, 4)
    torch.testing.assert_close(weights.sum(-1), torch.ones(256, device=weights.device))
    # 20 agent updates: 50 pretraining model steps once, then one per agent update
    assert (wm_trainer.calls, wm_trainer.updates) == (20, 70)
    assert int(scope["world_model"].obs_norm.count) == 750
    assert torch.isfinite(scope["loss_value"]) and torch.isfinite(scope["loss_actor"])
    printed = capsys.readouterr().out  # one scalar per horizon, alpha, the model's losses
    for key in ("rave_alpha", "rave_horizon_weights_h3", "rave_horizon_variance_h0",
                "wm/loss_transition"):  # fmt: skip
        assert f"'train/{key}': tensor(" in printed, key
    # the swap is short: the lines marked RAVE are all a DDPG script changes
    assert sum("# RAVE" in line for line in section_code_lines()) <= 10


def section_code_lines() -> list[str]:
    return section_code("Use RAVE in your own TorchRL loss").splitlines()


def test_ci_runs_exactly_the_readmes_test_command():
    text = README.read_text()
    start = text.index("## Two commands")
    blocks = re.findall(r"```bash\n(.*?)\n```", text[start : text.find("\n## ", start + 1)], re.S)
    main_job, tests = blocks[:2]
    assert main_job == "bash scripts/setup.sh && .venv/bin/python recipes/rave_mujoco.py"
    assert "sphinx -E -W" in tests  # the docs build, failing on any warning
    ci = (README.parent / ".ci" / "run").read_text().strip().splitlines()
    assert ci[-1] == tests


SWAP = README.parent / "docs" / "swap.md"


def sac_swap_code() -> str:
    text = SWAP.read_text()
    start, end = text.index("<!-- sac-swap-start -->"), text.index("<!-- sac-swap-end -->")
    (block,) = re.findall(r"```python\n(.*?)```", text[start:end], flags=re.S)
    return block


def test_rave_inside_sacloss_as_the_docs_show_it(capsys):
    """docs/swap.md's sota-shaped SAC loop with RAVE runs as written: SACLoss keeps its
    own actor and temperature losses, the estimator expands its soft target, and the
    diagnostics come out as scalars beside SAC's losses."""
    torch.manual_seed(0)
    scope = run_example(sac_swap_code(), SWAP)
    loss, wm_trainer = scope["loss_module"], scope["wm_trainer"]
    estimator = loss.value_estimator
    assert type(loss).__name__ == "SACLoss"
    assert type(estimator).__name__ == "RAVEValueEstimator"
    assert estimator.networks.stochastic
    torch.testing.assert_close(torch.as_tensor(estimator.networks.temperature()), loss._alpha)
    weights = estimator.diagnostics["rave_horizon_weights"]
    assert weights.shape == (256, 4)
    torch.testing.assert_close(weights.sum(-1), torch.ones(256, device=weights.device))
    assert (wm_trainer.calls, wm_trainer.updates) == (20, 70)
    assert float(loss.log_alpha.detach()) != 0.0  # alpha_init=1: the temperature moved
    printed = capsys.readouterr().out
    for key in ("loss_qvalue", "loss_alpha", "rave_alpha", "rave_horizon_weights_h0",
                "rave_horizon_variance_h3", "wm/loss_transition"):  # fmt: skip
        assert f"'train/{key}': tensor(" in printed, key
    assert sum("# RAVE" in line for line in sac_swap_code().splitlines()) <= 10
