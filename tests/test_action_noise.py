"""envs.ActuatorNoise: the stochastic tasks' actuator noise, alone and through the recipe."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from test_recipe import make_cfg

from torchrl_rave.envs import ActuatorNoise
from torchrl_rave.recipe.agent import make_env


def rollout_obs(env: gym.Env, actions: np.ndarray, seed: int) -> np.ndarray:
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for a in actions:
        obs, *_ = env.step(a)
        out.append(obs)
    return np.stack(out)


class TestActuatorNoise:
    def test_zero_sigma_is_the_unwrapped_env_exactly(self):
        actions = np.random.default_rng(0).uniform(-1, 1, (60, 3)).astype(np.float32)
        plain = rollout_obs(gym.make("Hopper-v5"), actions, seed=3)
        wrapped = rollout_obs(ActuatorNoise(gym.make("Hopper-v5"), 0.0), actions, seed=3)
        np.testing.assert_array_equal(wrapped, plain)

    def test_noise_changes_the_transition_but_not_the_reset(self):
        actions = np.zeros((20, 3), dtype=np.float32)
        plain = rollout_obs(gym.make("Hopper-v5"), actions, seed=3)
        noisy = rollout_obs(ActuatorNoise(gym.make("Hopper-v5"), 0.3), actions, seed=3)
        np.testing.assert_array_equal(noisy[0], plain[0])  # same seeded reset state
        assert np.abs(noisy[1:] - plain[1:]).max() > 1e-3

    def test_same_seed_same_noise_other_seed_other_noise(self):
        actions = np.zeros((30, 3), dtype=np.float32)

        def applied(seed):
            env = ActuatorNoise(gym.make("Hopper-v5"), 0.3)
            env.reset(seed=seed)
            out = []
            for a in actions:
                env.step(a)
                out.append(env.applied_action)
            return np.stack(out)

        np.testing.assert_array_equal(applied(5), applied(5))
        assert not np.allclose(applied(5), applied(6))

    @pytest.mark.parametrize("sigma", [0.1, 0.3])
    def test_noise_std_is_sigma_half_ranges(self, sigma):
        # InvertedDoublePendulum's box is [-1, 1]; a made-up [0, 4] box has half range 2;
        # commanded at the centre with small sigma, clipping (beyond 1/sigma stds) is rare
        for env, centre, half in (
            (gym.make("InvertedDoublePendulum-v5"), 0.0, 1.0),
            (WideBox(gym.make("InvertedDoublePendulum-v5")), 2.0, 2.0),
        ):
            noisy = ActuatorNoise(env, sigma)
            noisy.reset(seed=0)
            diffs = []
            for _ in range(4000):
                a = np.full(noisy.action_space.shape, centre, dtype=np.float32)
                _, _, term, trunc, _ = noisy.step(a)
                diffs.append(noisy.applied_action - a)
                if term or trunc:
                    noisy.reset()
            diffs = np.concatenate(diffs)
            # 4000 draws: the std's standard error is about 1.1 %
            assert diffs.std() == pytest.approx(sigma * half, rel=0.05)
            assert abs(diffs.mean()) < 4 * sigma * half / np.sqrt(len(diffs))

    def test_clipped_at_the_bounds(self):
        env = ActuatorNoise(gym.make("Hopper-v5"), 0.5)
        env.reset(seed=0)
        high, low = env.action_space.high, env.action_space.low
        at_high = []
        for _ in range(200):
            env.step(high)
            a = env.applied_action
            assert (a <= high).all() and (a >= low).all()
            at_high.append(a == high)
            env.step(low)
            assert (env.applied_action >= low).all()
        # commanded at the bound, about half the draws push past it and are clipped to it
        assert 0.35 < np.mean(at_high) < 0.65

    def test_bad_arguments_are_named(self):
        with pytest.raises(ValueError, match="sigma"):
            ActuatorNoise(gym.make("Hopper-v5"), -0.1)
        with pytest.raises(ValueError, match="sigma"):
            ActuatorNoise(gym.make("Hopper-v5"), float("nan"))
        with pytest.raises(TypeError, match="Box"):
            ActuatorNoise(gym.make("CartPole-v1"), 0.1)


class WideBox(gym.ActionWrapper):
    """A [0, 4] action box mapped onto the env's [-1, 1] one."""

    def __init__(self, env):
        super().__init__(env)
        self.action_space = gym.spaces.Box(0.0, 4.0, env.action_space.shape, np.float32)

    def action(self, action):
        return (action - 2.0) / 2.0


class TestRecipeEnv:
    def test_zero_sigma_through_torchrl_is_gymenv_exactly(self):
        # the recipe builds GymEnv at sigma 0 and GymWrapper(ActuatorNoise(...)) above it:
        # the two constructions are the same env when the noise is off
        from torchrl.envs import GymEnv, GymWrapper

        plain = GymEnv("Hopper-v5")
        wrapped = GymWrapper(ActuatorNoise(gym.make("Hopper-v5"), 0.0))
        out = []
        for env in (plain, wrapped):
            env.set_seed(7)
            torch.manual_seed(0)
            out.append(env.rollout(300, break_when_any_done=False))
        assert out[0]["next", "done"].any()  # a reset inside the rollout is covered too
        for key in ("observation", "action", ("next", "reward"), ("next", "observation")):
            torch.testing.assert_close(out[0][key], out[1][key], rtol=0, atol=0)

    def test_noisy_env_stores_the_commanded_action(self):
        cfg = make_cfg("env.name=Hopper-v5", "env.action_noise=0.3")
        env = make_env(cfg, torch.device("cpu"))
        env.set_seed(7)
        td = env.rollout(5, break_when_any_done=False)
        inner = env.base_env._env
        while not isinstance(inner, ActuatorNoise):
            inner = inner.env
        # the rollout's last action is what the policy sent; the simulator got another
        assert not np.allclose(td["action"][-1].numpy(), inner.applied_action)
        assert inner.sigma == 0.3

    @pytest.mark.parametrize("bad", ["-0.1", "inf", "abc", "true"])
    def test_bad_noise_is_refused_by_name(self, bad):
        from torchrl_rave.recipe.config import check_config

        with pytest.raises(ValueError, match="env.action_noise"):
            check_config(make_cfg("env.name=Hopper-v5", f"env.action_noise={bad}"))
