"""Stochastic versions of deterministic continuous-control tasks: actuator noise.

gymnasium's MuJoCo tasks are deterministic given ``(s, a)`` (only the reset is random),
which is where the paper's thesis says least: MVE and STEVE model only the mean of the
transition, RAVE its distribution. :class:`ActuatorNoise` makes the transition itself
random by perturbing the action the simulator applies, unseen by the agent, and keeps the
task's reward and termination as they are.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

__all__ = ["ActuatorNoise"]

# a fixed spawn key: the noise stream of seed s is not the env's own reset stream of seed s
_NOISE_STREAM = 0x5A7E


class ActuatorNoise(gym.Wrapper):
    """Applies ``clip(a + sigma * eps * half_range, low, high)`` instead of the commanded
    action ``a``, with ``eps ~ N(0, I)`` drawn afresh every step.

    ``half_range`` is ``(high - low) / 2`` of the action box, so ``sigma`` is in units of
    the action range, like the recipe's ``exploration.sigma``. The agent observes, and a
    TorchRL replay buffer stores, the commanded action: the noise is part of the
    environment's dynamics. The applied action of the last step is
    ``applied_action``, and ``info["applied_action"]``.

    The noise has its own generator, seeded by ``reset(seed=s)`` (which TorchRL's
    ``env.set_seed`` calls) from ``s`` and a fixed stream key: the same seed gives the same
    noise, and the reset states are those of the unwrapped env with that seed. Until the
    first seeded reset the generator is seeded from fresh entropy, as gymnasium's are.
    With ``sigma=0`` the wrapper is an exact pass-through and draws nothing.

    Args:
        env: an env with a bounded :class:`gymnasium.spaces.Box` action space.
        sigma: the noise's standard deviation in units of half the action range, ``>= 0``.

    Examples:
        >>> env = ActuatorNoise(gym.make("InvertedPendulum-v5"), sigma=0.3)
        >>> _ = env.reset(seed=0)
        >>> _, _, _, _, info = env.step(np.zeros(1, dtype=np.float32))
        >>> info["applied_action"]  # the simulator got this (half range 3), the agent sent 0
        array([-1.1432565], dtype=float32)
    """

    def __init__(self, env: gym.Env, sigma: float) -> None:
        super().__init__(env)
        space = env.action_space
        if not isinstance(space, gym.spaces.Box):
            raise TypeError(f"ActuatorNoise needs a continuous (Box) action space, got {space!r}")
        if not (np.isfinite(space.low).all() and np.isfinite(space.high).all()):
            raise ValueError(
                f"ActuatorNoise needs a bounded action box: its noise is scaled by half the "
                f"range, and {space!r} has an infinite bound"
            )
        sigma = float(sigma)
        if not (np.isfinite(sigma) and sigma >= 0):
            raise ValueError(f"ActuatorNoise: sigma={sigma!r} must be a finite number >= 0")
        self.sigma = sigma
        self._half_range = ((space.high - space.low) / 2).astype(space.dtype)
        self._rng = np.random.default_rng()
        self.applied_action: np.ndarray | None = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._rng = np.random.default_rng(
                np.random.SeedSequence(seed, spawn_key=(_NOISE_STREAM,))
            )
        self.applied_action = None
        return self.env.reset(seed=seed, options=options)

    def step(self, action):
        if self.sigma == 0:
            self.applied_action = action
            return self.env.step(action)
        space = self.action_space
        eps = self._rng.standard_normal(space.shape)
        noisy = np.asarray(action) + self.sigma * eps * self._half_range
        applied = np.clip(noisy, space.low, space.high).astype(space.dtype)
        self.applied_action = applied
        obs, reward, terminated, truncated, info = self.env.step(applied)
        return obs, reward, terminated, truncated, {**info, "applied_action": applied}
