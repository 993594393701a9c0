"""A fast test env whose reward is a sum of named terms, as ``LearnToMove-v0``'s is:
InvertedPendulum-v5 with ``alive`` (its own reward, 1 per step) and ``effort`` (minus the
squared action), reported in ``info["reward_terms"]``. The recipe takes it as
``env.name=terms_env:TermsPendulum-v0``."""

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
