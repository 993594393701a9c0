"""Test envs for collector-worker failures: InvertedPendulum that, on its 150th step, raises
(``FailingPendulum-v0``), kills its whole process (``DyingPendulum-v0``) or hangs, sleeping
forever (``HangingPendulum-v0``).

Importing this module registers both; the recipe's ``env.name`` takes them as
``failing_env:FailingPendulum-v0`` (gymnasium's ``module:EnvId``), so worker processes
import the module, and with it the registration, themselves.
"""

from __future__ import annotations

import os
import time

import gymnasium as gym

LIMIT = 150


class _FailAfter(gym.Wrapper):
    def __init__(self, env, how: str):
        super().__init__(env)
        self.steps, self.how = 0, how

    def step(self, action):
        self.steps += 1
        if self.steps >= LIMIT:
            if self.how == "die":
                os._exit(3)  # no exception, no cleanup: the process is simply gone
            if self.how == "hang":
                while True:  # alive, silent, never returns
                    time.sleep(3600)
            raise RuntimeError(f"simulated simulator crash at step {self.steps}")
        return self.env.step(action)


def _make(how: str = "raise"):
    return _FailAfter(gym.make("InvertedPendulum-v5"), how)


for _name, _how in (
    ("FailingPendulum-v0", "raise"),
    ("DyingPendulum-v0", "die"),
    ("HangingPendulum-v0", "hang"),
):
    if _name not in gym.registry:
        gym.register(_name, entry_point=_make, kwargs={"how": _how}, max_episode_steps=1000)
