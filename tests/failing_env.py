"""A test env for collector-worker failures: InvertedPendulum that raises on its 150th step.

Importing this module registers ``FailingPendulum-v0``; the recipe's ``env.name`` takes it
as ``failing_env:FailingPendulum-v0`` (gymnasium's ``module:EnvId``), so worker processes
import the module, and with it the registration, themselves.
"""

from __future__ import annotations

import gymnasium as gym


class _RaiseAfter(gym.Wrapper):
    def __init__(self, env, steps: int = 150):
        super().__init__(env)
        self.steps, self.limit = 0, steps

    def step(self, action):
        self.steps += 1
        if self.steps >= self.limit:
            raise RuntimeError(f"simulated simulator crash at step {self.steps}")
        return self.env.step(action)


def _make():
    return _RaiseAfter(gym.make("InvertedPendulum-v5"))


if "FailingPendulum-v0" not in gym.registry:
    gym.register("FailingPendulum-v0", entry_point=_make, max_episode_steps=1000)
