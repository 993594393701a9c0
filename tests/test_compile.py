"""``compile.enabled=true``: the recipe's update steps under ``torch.compile`` give the same
parameters as the eager steps, and a compiled run trains end to end."""

from __future__ import annotations

from pathlib import Path

import pytest
import rave_mujoco
import torch
import update_throughput as bench
from test_recipe import TINY, make_cfg

from torchrl_rave.recipe.agent import make_agent, make_env
from torchrl_rave.recipe.config import check_config

ROOT = Path(__file__).resolve().parents[1]

SMALL = [
    "replay_buffer.batch_size=32",
    "network.actor_cells=16",
    "network.critic_cells=16",
    "world_model.transition_cells=16",
    "world_model.reward_cells=16",
    "world_model.termination_cells=16",
]


@pytest.mark.parametrize(
    "algorithm, critic_first", [("ddpg", False), ("rave", False), ("rave", True)]
)
def test_compiled_updates_match_eager(algorithm, critic_first):
    data = bench.batches(32, torch.device("cpu"), count=3)
    params = {}
    for compiled in (False, True):
        overrides = [*SMALL, f"compile.enabled={str(compiled).lower()}",
                     f"optim.critic_first={str(critic_first).lower()}"]  # fmt: skip
        step, _, loss = bench.recipe_update(algorithm, overrides, torch.device("cpu"))
        torch.manual_seed(1)
        # compile_loss has the compiled code draw RAVE's rollout noise from torch's own
        # generator, as eager code does: the same seed gives the same updates
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
    """The recipe's ``train`` honours ``compile.enabled``: the agent's loss forward goes
    through ``torch.compile`` (DDPG keeps this cheap), and so does the world-model
    trainer's for model-based algorithms (RAVE's compiled steps are checked above)."""
    compiled = []
    real = torch.compile

    def counting(fn, **kwargs):
        compiled.append((fn.__name__, kwargs))
        return real(fn, **kwargs)

    monkeypatch.setattr(torch, "compile", counting)
    cfg = make_cfg(*TINY, "algorithm=ddpg", "compile.enabled=true")
    result = rave_mujoco.train(cfg, str(tmp_path))
    assert compiled == [("loss_and_total", {"options": {"fallback_random": True}})]
    assert result["frames"] == 400
    assert result["updates"] == 30  # utd 0.1 x the 300 frames after init_random_frames
    compiled.clear()
    rave = make_cfg(*TINY, "algorithm=rave", "compile.enabled=true", "compile.mode=max-autotune")
    env = make_env(rave, torch.device("cpu"))
    make_agent(rave, env)  # compiling happens at the first call: nothing runs here
    # compile.mode's own inductor options, plus fallback_random
    mode_options = {
        "max_autotune": True,
        "triton.cudagraphs": True,
        "coordinate_descent_tuning": True,
    }
    assert compiled == [
        ("_loss_total_eager", {"options": {**mode_options, "fallback_random": True}})
    ]


def test_bad_compile_settings_are_refused():
    with pytest.raises(ValueError, match="config key compile.mode='fastest'"):
        check_config(make_cfg(*TINY, "compile.mode=fastest"))
    with pytest.raises(ValueError, match="config key compile.enabled"):
        check_config(make_cfg(*TINY, "compile.enabled=maybe"))


def test_finite_checks_compile_without_a_graph_break():
    """The library's NaN checks assert on device under torch.compile (a host read-back
    would break the graph); the error still names the entry."""
    from torchrl_rave._checks import get_checked

    double = torch.compile(lambda d: get_checked(d, "x", 3) * 2, fullgraph=True)
    torch.testing.assert_close(double({"x": torch.ones(2, 3)}), torch.full((2, 3), 2.0))
    with pytest.raises(RuntimeError, match="entry 'x' holds NaN"):
        double({"x": torch.tensor([[1.0, float("nan"), 0.0]])})
