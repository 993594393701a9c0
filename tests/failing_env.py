"""Test envs for collector-worker failures: InvertedPendulum that, on its 150th step, raises
(``FailingPendulum-v0``) or kills its whole process (``DyingPendulum-v0``).

Importing this module registers both; the recipe's ``env.name`` takes them as
``failing_env:FailingPendulum-v0`` (gymnasium's ``module:EnvId``), so worker processes
import the module, and with it the registration, themselves.
"""

from __future__ import annotations

import os

import gymnasium as gym

LIMIT = 150


class _FailAfter(gym.Wrapper):
    def __init__(self, env, die: bool):
        super().__init__(env)
        self.steps, self.die = 0, die

    def step(self, action):
        self.steps += 1
        if self.steps >= LIMIT:
            if self.die:
                os._exit(3)  # no exception, no cleanup: the process is simply gone
            raise RuntimeError(f"simulated simulator crash at step {self.steps}")
        return self.env.step(action)


def _make(die: bool = False):
    return _FailAfter(gym.make("InvertedPendulum-v5"), die)


for _name, _die in (("FailingPendulum-v0", False), ("DyingPendulum-v0", True)):
    if _name not in gym.registry:
        gym.register(_name, entry_point=_make, kwargs={"die": _die}, max_episode_steps=1000)
