"""The paper's 1-D toy environment (section 4) and its exact optimal Q-values.

``s_0 = 0``, ``a in [-1, 1]``, ``s' = s + sign(a) + k N(0, 1)``; the episode terminates once
``|s'| > 5``. Every step costs ``step_penalty``; the terminating step also pays
``final_reward``. ``k = 0`` is deterministic, ``k = 1`` stochastic.

Choices the paper leaves open (documented in the README):

- ``a = 0``: ``sign(0) = 0``, the agent stays put (and still pays the penalty, and with
  ``k > 0`` still moves by the noise).
- constants: ``step_penalty = 1``, ``final_reward = 460``, ``gamma = 0.99``; then the
  optimal ``Q(s_0, +-1)`` is about 432 for ``k = 0`` (six steps to the boundary).
- episodes are truncated after ``max_episode_steps = 100`` steps, far beyond the six an
  optimal policy needs, so the truncation does not change the optimal values.
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from torchrl_rave._checks import FINITE, NON_NEGATIVE, POSITIVE, UNIT_INTERVAL, Rule

BOUND = 5.0
STEP_PENALTY = 1.0
FINAL_REWARD = 460.0
GAMMA = 0.99
ENV_ID = "RAVEToy-v0"


class ToyEnv(gym.Env):
    """The 1-D toy environment of the paper's section 4 as a gymnasium env.

    Args:
        k (float): noise scale of the transition (0: deterministic, 1: the paper's
            stochastic case).
        step_penalty (float): cost paid on every step.
        final_reward (float): reward paid on the terminating step (on top of the penalty).
        bound (float): the episode terminates once ``|s| > bound``.

    Examples:
        >>> env = ToyEnv(k=0.0)
        >>> obs, _ = env.reset(seed=0)
        >>> [env.step(np.array([1.0], dtype=np.float32))[1:3] for _ in range(6)]
        [(-1.0, False), (-1.0, False), (-1.0, False), (-1.0, False), (-1.0, False), (459.0, True)]
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        k: float = 1.0,
        step_penalty: float = STEP_PENALTY,
        final_reward: float = FINAL_REWARD,
        bound: float = BOUND,
    ) -> None:
        self.k = NON_NEGATIVE.check("k", _number(k))
        self.step_penalty, self.final_reward, self.bound = _check_constants(
            step_penalty, final_reward, bound
        )
        self.action_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(1,), dtype=np.float32)
        self._s = 0.0
        self._ended = False

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self._s = 0.0
        self._ended = False
        return np.array([self._s], dtype=np.float32), {}

    def step(self, action):
        flat = np.asarray(action, dtype=np.float64).reshape(-1)
        if flat.size != 1:
            raise ValueError(f"action must hold one value, got shape {np.shape(action)}")
        a = float(flat[0])
        if not math.isfinite(a):
            raise ValueError(f"action must be finite, got {a!r}")
        if self._ended:  # it would pay the final reward again on every step
            raise RuntimeError(
                f"ToyEnv.step after the episode ended (|s| = {abs(self._s):g} > bound "
                f"{self.bound:g}): call reset() first"
            )
        noise = self.k * self.np_random.standard_normal() if self.k > 0 else 0.0
        self._s = self._s + float(np.sign(a)) + noise
        terminated = abs(self._s) > self.bound
        self._ended = terminated
        reward = -self.step_penalty + (self.final_reward if terminated else 0.0)
        return np.array([self._s], dtype=np.float32), reward, terminated, False, {}


def _check_constants(step_penalty, final_reward, bound) -> tuple[float, float, float]:
    return (
        FINITE.check("step_penalty", _number(step_penalty)),
        FINITE.check("final_reward", _number(final_reward)),
        POSITIVE.check("bound", _number(bound)),
    )


def _number(value):
    """``value`` as a Python float where it is a real scalar (numpy and torch scalars
    included); anything else as it is, for the check to name."""
    try:
        return float(value) if not isinstance(value, (bool, str)) else value
    except (TypeError, ValueError):
        return value


def _check_state_action(s, a, bound: float) -> tuple[float, float]:
    s = FINITE.check("s", _number(s))
    a = FINITE.check("a", _number(a))
    if abs(s) > bound:
        raise ValueError(f"s={s} is already terminal (|s| > {bound})")
    return s, a


def deterministic_q(
    s: float,
    a: float,
    gamma: float = GAMMA,
    step_penalty: float = STEP_PENALTY,
    final_reward: float = FINAL_REWARD,
    bound: float = BOUND,
) -> float:
    """Closed-form optimal ``Q(s, a)`` for ``k = 0`` (then move away from 0 every step).

    Examples:
        >>> round(deterministic_q(0.0, 1.0), 3)  # six steps: five penalties, then the goal
        431.603
    """
    step_penalty, final_reward, bound = _check_constants(step_penalty, final_reward, bound)
    s, a = _check_state_action(s, a, bound)
    gamma = UNIT_INTERVAL.check("gamma", _number(gamma))

    def steps_out(x: float) -> int:  # moves away from 0 until |x| > bound
        return math.floor(bound - abs(x)) + 1

    x = s + float(np.sign(a))
    if abs(x) > bound:
        return -step_penalty + final_reward
    n = steps_out(x)
    penalties = n if gamma == 1 else (1 - gamma**n) / (1 - gamma)  # sum of gamma^i, i < n
    tail = -step_penalty * penalties + gamma ** (n - 1) * final_reward
    return -step_penalty + gamma * tail


def ground_truth_q(
    s: float,
    a: float,
    k: float,
    gamma: float = GAMMA,
    *,
    step_penalty: float = STEP_PENALTY,
    final_reward: float = FINAL_REWARD,
    bound: float = BOUND,
    cells: int = 1000,
    tol: float = 1e-10,
) -> tuple[float, float]:
    """Optimal ``Q(s, a)`` of the toy environment and a bound on its discretisation error.

    ``k = 0`` uses :func:`deterministic_q` (exact, error 0). For ``k > 0``, value iteration
    runs on ``cells`` equal cells of ``[-bound, bound]``: the Gaussian transition is
    integrated exactly over each cell (normal CDF differences) and the value is taken at
    the cell centre; the terminal mass is ``P(|s'| > bound)``. Only the signs of actions
    matter, so the maximisation is over ``{-1, 0, +1}``. The returned error is
    ``|Q_cells - Q_{cells/2}|``, the change from halving the grid (midpoint rule:
    the error shrinks about fourfold per halving, so this over-bounds the finer grid's).

    Examples:
        >>> q, err = ground_truth_q(0.0, 1.0, k=1.0)
        >>> err < 0.01
        True
    """
    k = NON_NEGATIVE.check("k", _number(k))
    step_penalty, final_reward, bound = _check_constants(step_penalty, final_reward, bound)
    s, a = _check_state_action(s, a, bound)
    # gamma > 1 would run value iteration for its 100,000 sweeps, then fail
    gamma = UNIT_INTERVAL.check("gamma", _number(gamma))
    Rule(lambda v: isinstance(v, int) and v >= 2, "an integer >= 2").check("cells", cells)
    POSITIVE.check("tol", _number(tol))
    if k == 0:
        return deterministic_q(s, a, gamma, step_penalty, final_reward, bound), 0.0
    fine = _value_iteration_q(s, a, k, gamma, step_penalty, final_reward, bound, cells, tol)
    coarse = _value_iteration_q(s, a, k, gamma, step_penalty, final_reward, bound, cells // 2, tol)
    return fine, abs(fine - coarse)


def _normal_cdf(x: np.ndarray) -> np.ndarray:
    return torch.special.ndtr(torch.from_numpy(np.asarray(x, dtype=np.float64))).numpy()


def _transition(means: np.ndarray, edges: np.ndarray, k: float, bound: float):
    """Cell probabilities ``[M, cells]`` and terminal probabilities ``[M]`` of
    ``N(mean, k^2)`` for each mean."""
    cdf = _normal_cdf((edges[None, :] - means[:, None]) / k)
    inside = np.diff(cdf, axis=1)
    terminal = _normal_cdf((-bound - means) / k) + (1.0 - _normal_cdf((bound - means) / k))
    return inside, terminal


def _value_iteration_q(s, a, k, gamma, step_penalty, final_reward, bound, cells, tol) -> float:
    edges = np.linspace(-bound, bound, cells + 1)
    centres = (edges[:-1] + edges[1:]) / 2
    moves = (-1.0, 0.0, 1.0)
    trans = [_transition(centres + m, edges, k, bound) for m in moves]
    reward = [-step_penalty + final_reward * term for _, term in trans]
    v = np.zeros(cells)
    for _ in range(100_000):
        q = np.stack([r + gamma * p @ v for (p, _), r in zip(trans, reward, strict=True)])
        v_new = q.max(0)
        if np.max(np.abs(v_new - v)) < tol:
            v = v_new
            break
        v = v_new
    else:
        raise RuntimeError("value iteration did not converge")
    p, term = _transition(np.array([s + float(np.sign(a))]), edges, k, bound)
    return float(-step_penalty + final_reward * term[0] + gamma * p[0] @ v)


gym.register(ENV_ID, entry_point=ToyEnv, max_episode_steps=100)
