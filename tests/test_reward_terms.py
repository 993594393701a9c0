"""Reward terms: the delayed weight value by value, the relabelling by hand, the replay
buffer that relabels with the weights of the moment, and the recipe's ``reward`` keys on a
fast env with two terms, resumed mid-ramp."""

from __future__ import annotations

import pytest
import rave_mujoco
import terms_env  # noqa: F401  registers TermsPendulum-v0
import torch
from tensordict import TensorDict
from test_recipe import TINY, make_cfg

from torchrl_rave.recipe.agent import make_env, make_replay_buffer
from torchrl_rave.recipe.config import ConfigError, check_config
from torchrl_rave.recipe.reward import make_reward_relabelling
from torchrl_rave.recipe.runs import read_scalar
from torchrl_rave.transforms import DelayedWeight, RewardTermsReader, ReweightRewardTerms

ENV = "env.name=terms_env:TermsPendulum-v0"


def test_the_delayed_weight_value_by_value():
    w = DelayedWeight(0.5, start_frames=1000, ramp_frames=400)
    got = [w.update(f) for f in (0, 999, 1000, 1100, 1300, 1400, 5000)]
    assert got == [0.0, 0.0, 0.0, 0.125, 0.375, 0.5, 0.5]
    assert w.started_at == 1000
    # a metric threshold starts it at the first update that sees the metric reach it
    w = DelayedWeight(1.0, metric="eval/return", threshold=200.0, ramp_frames=100)
    assert w.update(100, {}) == 0.0 and w.update(200, {"eval/return": 199.9}) == 0.0
    assert w.update(300, {"eval/return": 200.0}) == 0.0 and w.started_at == 300
    assert w.update(350, {"eval/return": -5.0}) == 0.5  # once started it stays started
    # both conditions: whichever comes first
    w = DelayedWeight(1.0, start_frames=500, metric="eval/return", threshold=10.0)
    assert w.update(400, {"eval/return": 11.0}) == 1.0 and w.started_at == 400
    w = DelayedWeight(1.0, start_frames=500, metric="eval/return", threshold=10.0)
    assert w.update(500, {"eval/return": 0.0}) == 1.0 and w.started_at == 500
    # its state is its start frame: set it, and it continues from there
    w = DelayedWeight(2.0, start_frames=10**9, ramp_frames=100)
    w.started_at = 50
    assert w.update(100) == 1.0
    with pytest.raises(ValueError, match="start_frames, or a metric"):
        DelayedWeight(1.0)
    with pytest.raises(ValueError, match="go together"):
        DelayedWeight(1.0, metric="eval/return")


def test_relabelling_by_hand():
    batch = TensorDict(
        {("next", "reward"): torch.zeros(3, 1),
         ("next", "reward_terms", "alive"): torch.tensor([1.0, 1.0, 0.0]),
         ("next", "reward_terms", "effort"): torch.tensor([-2.0, -0.5, -1.0])},
        [3],
    )  # fmt: skip
    relabel = ReweightRewardTerms(["alive", "effort"], scale=0.1)
    # weight 1 each, times the reward scale
    assert torch.allclose(relabel(batch.clone())["next", "reward"].squeeze(-1),
                          torch.tensor([-0.1, 0.05, -0.1]))  # fmt: skip
    relabel.set_weights({"effort": 0.0, "alive": 3.0})
    assert torch.allclose(relabel(batch.clone())["next", "reward"].squeeze(-1),
                          torch.tensor([0.3, 0.3, 0.0]))  # fmt: skip
    with pytest.raises(KeyError, match="no reward term \\['speed'\\]"):
        relabel.set_weights({"speed": 1.0})
    with pytest.raises(ValueError, match="finite"):
        relabel.set_weights({"alive": float("nan")})
    reader = RewardTermsReader(["alive", "effort"])
    td = reader({}, TensorDict())  # a reset's info: no terms, zeros
    assert td["reward_terms", "alive"] == 0 and td["reward_terms", "effort"].dtype == torch.float32
    # a misspelt name read 0 on every step; an unnamed term was dropped from the reward
    for names in (["alive", "efort"], ["alive"]):
        with pytest.raises(KeyError, match="has the terms \\['alive', 'effort'\\], but"):
            RewardTermsReader(names)({"reward_terms": {"alive": 1.0, "effort": -0.5}}, TensorDict())


def test_the_replay_buffer_relabels_every_sample_with_the_weights_of_the_moment():
    cfg = make_cfg(*TINY, ENV, "reward.weights={effort:0.0}")
    env = make_env(cfg, torch.device("cpu"))
    env.set_seed(0)
    data = env.rollout(50, break_when_any_done=False)
    terms = data["next", "reward_terms"]
    # the env's own reward is the sum of its terms
    assert torch.allclose(terms["alive"] + terms["effort"], data["next", "reward"].squeeze(-1))
    relabel, delayed = make_reward_relabelling(cfg, env)
    assert delayed is None and relabel.weights == {"alive": 1.0, "effort": 0.0}
    rb = make_replay_buffer(cfg, torch.device("cpu"))
    rb.append_transform(relabel)
    rb.extend(data)
    sample = rb.sample()
    assert torch.allclose(
        sample["next", "reward"].squeeze(-1), sample["next", "reward_terms", "alive"]
    )
    relabel.set_weights({"effort": 10.0})  # the stored data follow the new weight
    sample = rb.sample()
    t = sample["next", "reward_terms"]
    assert torch.allclose(sample["next", "reward"].squeeze(-1), t["alive"] + 10 * t["effort"])
    assert (t["effort"] < 0).any()
    # an env without terms, or a term the env lacks: named before anything is built
    with pytest.raises(ValueError, match="InvertedPendulum-v5 reports none"):
        plain = make_cfg(*TINY, "reward.weights={effort:1.0}")
        make_reward_relabelling(plain, make_env(plain, torch.device("cpu")))
    with pytest.raises(
        ValueError, match=r"no reward term \['speed'\]; its terms are \['alive', 'effort'\]"
    ):
        make_reward_relabelling(
            make_cfg(*TINY, ENV, "reward.delayed=speed", "reward.delay_frames=0"), env
        )


def test_bad_reward_keys_are_named():
    with pytest.raises(ConfigError) as err:
        check_config(
            make_cfg(*TINY, ENV, "reward.delayed=effort", "reward.delay_metric=eval/speed")
        )
    text = str(err.value)
    assert "reward.delay_metric" in text and "eval/return" in text  # unknown metric, and alone
    with pytest.raises(ConfigError, match="reward.delayed"):
        check_config(make_cfg(*TINY, ENV, "reward.delayed=effort"))  # no start condition
    with pytest.raises(ConfigError, match="an off-policy algorithm"):
        check_config(make_cfg(*TINY, ENV, "algorithm=ppo", "reward.weights={effort:0.5}"))
    with pytest.raises(ConfigError, match="reward.delay_frames"):
        check_config(make_cfg(*TINY, ENV, "reward.delay_frames=10"))  # nothing to delay


def test_a_delayed_term_is_logged_ramps_and_resumes_where_it_was(tmp_path):
    """Started by the first evaluation's return (any return passes the threshold), at the
    batch after it: frame 200. Ramp 400 frames to 2.0. Stopped at 300 and resumed to 500:
    the start frame comes back from the checkpoint, so the ramp goes on (a lost start
    would wait for the next evaluation and restart at 0)."""
    run = tmp_path / "run"
    args = [*TINY, ENV, "algorithm=ddpg", "eval.interval=100", "eval.episodes=1",
            "checkpoint.interval=100", "reward.delayed=effort", "reward.weights={effort:2.0}",
            "reward.delay_metric=eval/return", "reward.delay_threshold=-1e9",
            "reward.ramp_frames=400"]  # fmt: skip
    rave_mujoco.train(make_cfg(*args, "collector.total_frames=300"), str(run))
    rave_mujoco.train(make_cfg(*args, f"resume={run}", "collector.total_frames=500"), str(run))
    steps, weights = read_scalar(run, "train/reward_weight_effort")
    assert steps.tolist() == [100, 200, 300, 400, 500]
    assert weights.tolist() == pytest.approx([0.0, 0.0, 0.5, 1.0, 1.5])
