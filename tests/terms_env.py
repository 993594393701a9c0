"""Fast test envs for the recipe's ``reward`` and ``curriculum`` keys (``env.name=
terms_env:<id>``): ``TermsPendulum-v0``, InvertedPendulum-v5 whose reward is a sum of named
terms, as ``LearnToMove-v0``'s is (``alive``, its own reward, and ``effort``, minus the
squared action, in ``info["reward_terms"]``); ``LevelPendulum-v0``, whose reward is its
``level`` keyword at every step."""

from __future__ import annotations

import gymnasium as gym
import numpy as np


class _Terms(gym.Wrapper):
    reward_term_names = ("alive", "effort")

    def step(self, action):
        obs, alive, terminated, truncated, info = self.env.step(action)
        effort = -float(np.square(action).sum())
        info["reward_terms"] = {"alive": float(alive), "effort": effort}
        return obs, alive + effort, terminated, truncated, info


if "TermsPendulum-v0" not in gym.registry:
    gym.register(
        "TermsPendulum-v0",
        entry_point=lambda: _Terms(gym.make("InvertedPendulum-v5")),
        max_episode_steps=1000,
    )


class _Level(gym.Wrapper):
    """Reward ``level`` per step, whatever the action: an episode's return over its length
    says which ``level`` the env was built with (a curriculum's stage)."""

    def __init__(self, env, level: float):
        super().__init__(env)
        self.level = float(level)

    def step(self, action):
        obs, _, terminated, truncated, info = self.env.step(action)
        return obs, self.level, terminated, truncated, info


if "LevelPendulum-v0" not in gym.registry:
    gym.register(
        "LevelPendulum-v0",
        entry_point=lambda level=1.0: _Level(gym.make("InvertedPendulum-v5"), level),
        max_episode_steps=1000,
    )
