"""The toy environment of the paper's section 4 and its exact Q-values."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs import GymEnv

import torchrl_rave  # noqa: F401  (registers RAVEToy-v0)
from torchrl_rave.envs import ENV_ID, ToyEnv, deterministic_q, ground_truth_q
from torchrl_rave.envs.toy import FINAL_REWARD, GAMMA, STEP_PENALTY


def monte_carlo_q(s0: float, a0: float, k: float, episodes: int, seed: int = 0):
    """Mean and standard error of the discounted return of (s0, a0) then 'move away from 0'."""
    rng = np.random.default_rng(seed)
    s = np.full(episodes, s0)
    alive = np.ones(episodes, dtype=bool)
    ret = np.zeros(episodes)
    a = np.full(episodes, np.sign(a0))
    for t in range(200):
        s = s + a + k * rng.standard_normal(episodes)
        done = alive & (np.abs(s) > 5)
        ret += alive * GAMMA**t * (-STEP_PENALTY + FINAL_REWARD * done)
        alive &= ~done
        a = np.where(s >= 0, 1.0, -1.0)
        if not alive.any():
            break
    return ret.mean(), ret.std() / np.sqrt(episodes)


class TestToyEnv:
    def test_deterministic_walk_and_rewards(self):
        env = ToyEnv(k=0.0)
        obs, _ = env.reset(seed=0)
        assert obs.tolist() == [0.0]
        path, rewards = [], []
        for a in [0.3, 0.7, -0.01, 1.0]:  # only the sign matters
            obs, r, term, trunc, _ = env.step(np.array([a], dtype=np.float32))
            path.append(obs.item())
            rewards.append(r)
            assert not term and not trunc
        assert path == [1.0, 2.0, 1.0, 2.0]
        assert rewards == [-STEP_PENALTY] * 4
        obs, r, term, _, _ = env.step(np.array([0.0], dtype=np.float32))  # a = 0 stays
        assert obs.item() == 2.0 and r == -STEP_PENALTY and not term
        for _ in range(3):
            obs, r, term, _, _ = env.step(np.array([1.0], dtype=np.float32))
        assert obs.item() == 5.0 and not term  # |s| > 5 is needed, 5 is not terminal
        obs, r, term, _, _ = env.step(np.array([1.0], dtype=np.float32))
        assert obs.item() == 6.0 and term and r == FINAL_REWARD - STEP_PENALTY

    def test_negative_side_terminates_too(self):
        env = ToyEnv(k=0.0)
        env.reset(seed=0)
        for _ in range(6):
            obs, r, term, _, _ = env.step(np.array([-1.0], dtype=np.float32))
        assert obs.item() == -6.0 and term
        # a step past the end paid the final reward again, and again
        with pytest.raises(RuntimeError, match=r"after the episode ended \(\|s\| = 6 > bound 5\)"):
            env.step(np.array([-1.0], dtype=np.float32))
        env.reset()
        assert env.step(np.array([1.0], dtype=np.float32))[0].item() == 1.0

    def test_stochastic_step_moments(self):
        env = ToyEnv(k=1.0)
        env.reset(seed=1)
        steps = []
        for _ in range(4000):
            env.reset()
            obs, *_ = env.step(np.array([1.0], dtype=np.float32))
            steps.append(obs.item())
        steps = np.array(steps)
        # s_1 ~ N(1, 1): mean within 4 standard errors, variance within ~10%
        assert abs(steps.mean() - 1.0) < 4 / np.sqrt(len(steps))
        assert 0.9 < steps.var() < 1.1

    def test_registered_id_and_torchrl_gymenv(self):
        env = gym.make(ENV_ID, k=0.0)
        assert env.spec.max_episode_steps == 100
        tenv = GymEnv(ENV_ID, k=0.0)
        rollout = tenv.rollout(10, lambda td: td.set("action", torch.ones(1)))
        assert rollout["next", "observation"].squeeze(-1).tolist() == [1, 2, 3, 4, 5, 6]
        assert rollout["next", "terminated"][-1].item()
        assert rollout["next", "reward"].sum().item() == FINAL_REWARD - 6 * STEP_PENALTY

    def test_bad_arguments(self):
        with pytest.raises(ValueError, match="k must be a finite number >= 0"):
            ToyEnv(k=-1.0)
        with pytest.raises(ValueError, match="bound must be a finite number > 0, got 0.0"):
            ToyEnv(bound=0)
        env = ToyEnv(k=0.0)
        env.reset(seed=0)
        with pytest.raises(ValueError, match="action must be finite"):
            env.step(np.array([np.nan], dtype=np.float32))
        # a second action value was silently dropped
        with pytest.raises(ValueError, match=r"action must hold one value, got shape \(2,\)"):
            env.step(np.array([1.0, -1.0], dtype=np.float32))


class TestGroundTruth:
    def test_deterministic_by_hand(self):
        # from 0 with a = +1: positions 1..6, five penalties then the goal step
        g = GAMMA
        by_hand = sum(-STEP_PENALTY * g**t for t in range(6)) + g**5 * FINAL_REWARD
        assert deterministic_q(0.0, 1.0) == pytest.approx(by_hand, rel=1e-12)
        assert deterministic_q(0.0, -1.0) == pytest.approx(by_hand, rel=1e-12)
        # one step from the edge: the goal right away
        assert deterministic_q(4.5, 1.0) == pytest.approx(FINAL_REWARD - STEP_PENALTY)
        # stepping toward the centre costs two extra steps
        assert deterministic_q(4.5, -1.0) == pytest.approx(
            -STEP_PENALTY + g * (-STEP_PENALTY) + g**2 * (FINAL_REWARD - STEP_PENALTY)
        )
        assert ground_truth_q(0.0, 1.0, k=0.0) == (deterministic_q(0.0, 1.0), 0.0)

    def test_undiscounted(self):
        # gamma = 1 divided by zero in the closed form: six penalties and the goal
        assert deterministic_q(0.0, 1.0, gamma=1.0) == 6 * -STEP_PENALTY + FINAL_REWARD
        assert ground_truth_q(0.0, 1.0, k=0.0, gamma=1.0)[0] == 6 * -STEP_PENALTY + FINAL_REWARD

    @pytest.mark.parametrize(
        "kw,match",
        [
            ({"gamma": 1.5}, "gamma must be in \\[0, 1\\], got 1.5"),  # ran 100,000 sweeps
            ({"k": float("nan")}, "k must be a finite number >= 0"),
            ({"cells": 1}, "cells must be an integer >= 2"),
            ({"s": float("nan")}, "s must be a finite number"),
            ({"s": 6.0}, "already terminal"),
            ({"a": float("inf")}, "a must be a finite number"),
        ],
    )
    def test_bad_arguments(self, kw, match):
        args = {"s": 0.0, "a": 1.0, "k": 1.0, **kw}
        with pytest.raises(ValueError, match=match):
            ground_truth_q(**args)

    def test_deterministic_against_monte_carlo(self):
        mc, se = monte_carlo_q(0.0, 1.0, k=0.0, episodes=10)
        assert se == 0.0 and mc == pytest.approx(deterministic_q(0.0, 1.0), rel=1e-12)

    @pytest.mark.parametrize("s0, a0", [(0.0, 1.0), (0.0, -1.0), (2.5, -1.0)])
    def test_stochastic_against_monte_carlo(self, s0, a0):
        q, err = ground_truth_q(s0, a0, k=1.0, cells=400)
        mc, se = monte_carlo_q(s0, a0, k=1.0, episodes=200_000, seed=3)
        assert err < 1e-3
        assert abs(q - mc) < 4 * se + err, (q, mc, se)

    def test_symmetry_and_noise_effect(self):
        plus, _ = ground_truth_q(0.0, 1.0, k=1.0, cells=400)
        minus, _ = ground_truth_q(0.0, -1.0, k=1.0, cells=400)
        assert plus == pytest.approx(minus, abs=1e-9)
        # noise shortens the way out on average, so the stochastic value is higher
        assert plus > deterministic_q(0.0, 1.0)
