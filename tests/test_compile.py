"""``compile.enabled=true``: the recipe's update steps under ``torch.compile`` give the same
parameters as the eager steps, and a compiled run trains end to end."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "recipes"))
import rave_mujoco  # noqa: E402
import update_throughput as bench  # noqa: E402
import utils as recipe_utils  # noqa: E402
from test_recipe import TINY, make_cfg  # noqa: E402

SMALL = [
    "replay_buffer.batch_size=32",
    "network.actor_cells=16",
    "network.critic_cells=16",
    "world_model.transition_cells=16",
    "world_model.reward_cells=16",
    "world_model.termination_cells=16",
]


@pytest.mark.parametrize("algorithm", ["ddpg", "rave"])
def test_compiled_updates_match_eager(algorithm):
    data = bench.batches(32, torch.device("cpu"), count=3)
    params = {}
    for compiled in (False, True):
        overrides = [*SMALL, f"compile.enabled={str(compiled).lower()}"]
        step, _, loss = bench.recipe_update(algorithm, overrides, torch.device("cpu"))
        torch.manual_seed(1)
        # compiled code draws RAVE's rollout noise from torch's own generator, as eager does
        with torch._inductor.config.patch(fallback_random=True):
            for batch in data:
                step(batch)
        params[compiled] = {k: v.detach().clone() for k, v in loss.named_parameters()}
        if algorithm == "rave":  # the estimator's diagnostics come out of the compiled step
            alpha = loss.value_estimator.diagnostics["rave_alpha"]
            assert torch.isfinite(alpha).all()
    assert params[False].keys() == params[True].keys()
    for name, eager in params[False].items():
        torch.testing.assert_close(params[True][name], eager, rtol=1e-4, atol=1e-5, msg=name)
    # three updates moved the parameters: the comparison is not between two initialisations
    _, _, fresh = bench.recipe_update(algorithm, SMALL, torch.device("cpu"))
    moved = [n for n, p in fresh.named_parameters() if not torch.equal(p, params[False][n])]
    assert moved


def test_compiled_run_trains(monkeypatch, tmp_path):
    """The recipe's ``train`` honours ``compile.enabled``: both update steps go through
    ``torch.compile`` (DDPG keeps this cheap; RAVE's compiled steps are checked above)."""
    compiled = []
    real = torch.compile

    def counting(fn, **kwargs):
        compiled.append((fn.__name__, kwargs))
        return real(fn, **kwargs)

    monkeypatch.setattr(torch, "compile", counting)
    cfg = make_cfg(*TINY, "algorithm=ddpg", "compile.enabled=true")
    result = rave_mujoco.train(cfg, str(tmp_path))
    assert compiled == [("world_model_step", {"mode": None}), ("agent_step", {"mode": None})]
    assert result["frames"] == 400
    assert result["updates"] == 30  # utd 0.1 x the 300 frames after init_random_frames


def test_bad_compile_settings_are_refused():
    with pytest.raises(ValueError, match="config key compile.mode='fastest'"):
        recipe_utils.check_config(make_cfg(*TINY, "compile.mode=fastest"))
    with pytest.raises(ValueError, match="config key compile.enabled"):
        recipe_utils.check_config(make_cfg(*TINY, "compile.enabled=maybe"))
