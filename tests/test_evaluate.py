"""training.evaluate: the value-error metric against hand-computed episodes."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs import GymWrapper, RewardScaling, RewardSum, StepCounter, TransformedEnv

from torchrl_rave.recipe.evaluate import (
    discounted_returns,
    evaluate,
    value_error,
    value_error_states,
)


class Countdown(gym.Env):
    """Observation ``[t]`` (the step index); reward ``t + 1`` at step ``t``; terminates
    after ``end`` steps unless a time limit cuts it first."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (1,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, end: int):
        self.end, self.t = end, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.array([0.0], np.float32), {}

    def step(self, action):
        reward = float(self.t + 1)
        self.t += 1
        return np.array([self.t], np.float32), reward, self.t >= self.end, False, {}


def torchrl_env(end: int, limit: int | None = None, scale: float = 1.0):
    env = Countdown(end)
    if limit is not None:
        env = gym.wrappers.TimeLimit(env, limit)
    env = TransformedEnv(GymWrapper(env), StepCounter())
    env.append_transform(RewardSum())
    if scale != 1.0:
        env.append_transform(RewardScaling(loc=0.0, scale=scale))
    return env


class ZeroActor(torch.nn.Module):
    def forward(self, td):
        return td.set("action", torch.zeros(*td.batch_size, 1))


class TestPieces:
    def test_discounted_returns_by_hand(self):
        g = discounted_returns(np.array([1.0, 2.0, 4.0]), gamma=0.5)
        np.testing.assert_allclose(g, [1 + 0.5 * 2 + 0.25 * 4, 2 + 0.5 * 4, 4.0])

    def test_kept_states(self):
        np.testing.assert_array_equal(value_error_states(5, True, 0.5), [0, 1, 2, 3, 4])
        # cut at 10 steps: 0.5 ** (10 - t) < 0.01 needs 10 - t >= 7
        np.testing.assert_array_equal(value_error_states(10, False, 0.5), [0, 1, 2, 3])
        # gamma 0.99: 0.99 ** 459 = 0.0099 < 0.01 < 0.99 ** 458 = 0.01002
        assert value_error_states(1000, False, 0.99)[-1] == 1000 - 459
        assert len(value_error_states(100, False, 0.99)) == 0

    def test_statistics_by_hand(self):
        s = value_error(np.array([2.5, 5.0, 4.0]), np.array([3.0, 4.0, 4.0]))
        assert s["eval/q_bias"] == pytest.approx((-0.5 + 1.0 + 0.0) / 3)
        assert s["eval/q_rmse"] == pytest.approx(np.sqrt((0.25 + 1.0) / 3))
        # Pearson by hand: x = (2.5, 5, 4) - 23/6, y = (3, 4, 4) - 11/3
        x, y = np.array([-8, 7, 1]) / 6, np.array([-2, 1, 1]) / 3
        assert s["eval/q_corr"] == pytest.approx((x @ y) / np.sqrt((x @ x) * (y @ y)))
        assert s["eval/q_states"] == 3

    def test_no_states_and_constant_predictions_give_nan(self):
        s = value_error(np.array([]), np.array([]))
        assert np.isnan(s["eval/q_bias"]) and s["eval/q_states"] == 0
        s = value_error(np.array([1.0, 1.0]), np.array([0.0, 2.0]))
        assert s["eval/q_bias"] == 0 and np.isnan(s["eval/q_corr"])


class TestEvaluate:
    def test_terminated_episode_by_hand(self):
        # rewards 1, 2, 3, gamma 0.5: G = (1 + 1 + 0.75, 2 + 1.5, 3) = (2.75, 3.5, 3);
        # the critic says 2 * t (t = 0, 1, 2): errors (-2.75, -1.5, 1)
        out = evaluate(
            torchrl_env(3),
            ZeroActor(),
            2,
            value=lambda td: 2 * td["observation"][..., 0],
            gamma=0.5,
        )
        errors = np.array([-2.75, -1.5, 1.0])
        assert out["eval/q_states"] == 6  # both episodes, every state
        assert out["eval/q_bias"] == pytest.approx(errors.mean())
        assert out["eval/q_rmse"] == pytest.approx(np.sqrt((errors**2).mean()))
        assert out["eval/q_corr"] == pytest.approx(np.corrcoef([0, 2, 4], [2.75, 3.5, 3])[0, 1])
        assert out["eval/falling_rate"] == 1.0

    def test_truncated_episode_keeps_only_the_early_states(self):
        # cut at 10 steps with gamma 0.5: states 0-3 count; the critic is exact there
        g = discounted_returns(np.arange(1.0, 11.0), 0.5)

        def exact(td):
            return torch.tensor(g[td["observation"][..., 0].long().numpy()])

        out = evaluate(torchrl_env(100, limit=10), ZeroActor(), 1, value=exact, gamma=0.5)
        assert out["eval/q_states"] == 4 and out["eval/falling_rate"] == 0.0
        assert out["eval/q_bias"] == pytest.approx(0.0, abs=1e-12)
        assert out["eval/q_rmse"] == pytest.approx(0.0, abs=1e-12)

    def test_reward_scale_is_undone_on_both_sides(self):
        # learning rewards x 4, and a critic of scaled returns: errors in env units
        g = discounted_returns(np.array([1.0, 2.0, 3.0]), 0.5)

        def scaled_plus_one(td):  # off by 1 env unit = 4 scaled units
            return 4 * torch.tensor(g[td["observation"][..., 0].long().numpy()]) + 4

        out = evaluate(torchrl_env(3, scale=4.0), ZeroActor(), 1, scaled_plus_one, 0.5, 4.0)
        assert out["eval/q_bias"] == pytest.approx(1.0)
        assert out["eval/return"] == 6.0  # returns stay in env units

    def test_without_a_critic_no_value_metrics(self):
        out = evaluate(torchrl_env(3), ZeroActor(), 1)
        assert not any(k.startswith("eval/q_") for k in out)


class TestBootstrapValue:
    """``bootstrap_value`` reads each loss's critics as that loss bootstraps from them:
    critics made constant (zero output weights, bias ``b_k``) give known values."""

    @pytest.mark.parametrize(
        "algorithm, biases, expected",
        [("rave", [1, 2, 3, 6], 3.0), ("ddpg", [5], 5.0), ("td3", [4, -2], -2.0),
         ("sac", [0.5, 3], 0.5), ("ppo", [7], 7.0)],
    )  # fmt: skip
    def test_constant_critics(self, algorithm, biases, expected):
        from test_recipe import make_cfg

        from torchrl_rave.recipe.agent import bootstrap_value, critic_params, make_agent
        from torchrl_rave.recipe.agent import make_env as make_recipe_env

        cfg = make_cfg(f"algorithm={algorithm}", "env.name=InvertedPendulum-v5")
        env = make_recipe_env(cfg, torch.device("cpu"))
        agent = make_agent(cfg, env)
        params, _ = critic_params(agent.loss)
        leaves = dict(params.items(True, True))
        # the output layer: the last of the MLP's (fewer than 10) layers
        weight = sorted(k for k in leaves if "weight" in str(k))[-1]
        bias = sorted(k for k in leaves if "bias" in str(k))[-1]
        with torch.no_grad():
            leaves[weight].zero_()
            leaves[bias].copy_(
                torch.tensor(biases, dtype=torch.float32).reshape(leaves[bias].shape)
            )
        td = env.rollout(5, break_when_any_done=False)
        torch.testing.assert_close(bootstrap_value(agent.loss, td), torch.full((5,), expected))
