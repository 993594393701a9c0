"""The episode in progress, kept so that another process can rebuild it exactly.

A checkpoint taken in the middle of an episode holds the learner but not the simulator. A
gymnasium env's state is whatever its simulator holds (MuJoCo's ``mjData``, a PyBullet
world, an OpenSim model), its wrappers' counters and its random generators, and most of
it cannot be written down portably. What can be written down is how the episode came
about: the state of the env's random generators just before its reset, the reset's
arguments, and the actions taken since. Deterministic given those, as MuJoCo and the
other simulators here are on one machine, the env rebuilds the episode by replaying them,
down to the time limit's step count and the derived quantities the simulator keeps.
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import gymnasium as gym
import numpy as np

__all__ = ["EpisodeReplay", "EpisodeReplayError"]


class EpisodeReplayError(RuntimeError):
    """A recorded episode could not be rebuilt: the env is not the one that recorded it,
    or replaying it did not end where the recording did."""


def _generators(env: gym.Env) -> Iterator[tuple[str, np.random.Generator]]:
    """Every numpy generator held by ``env`` and the envs it wraps, by a stable name
    (``<depth>.<attribute>``): gymnasium's ``np_random`` of the base env, and a wrapper's
    own (e.g. :class:`~torchrl_rave.envs.ActuatorNoise`'s noise)."""
    layer, depth = env, 0
    while True:
        for name, value in sorted(vars(layer).items()):
            if isinstance(value, np.random.Generator):
                yield f"{depth}.{name}", value
        if not isinstance(layer, gym.Wrapper):
            return
        layer, depth = layer.env, depth + 1


def _json_state(value) -> bool:
    try:
        json.dumps(value)
    except (TypeError, ValueError):
        return False
    return True


class EpisodeReplay(gym.Wrapper):
    """Records the episode in progress so that :meth:`replay` can rebuild it in a new
    process: what a checkpoint needs to resume an interrupted run mid-episode, exactly.

    At every reset it keeps the reset's ``seed`` and ``options`` and the state of every
    numpy generator of the wrapped env (gymnasium's ``np_random``, and a wrapper's own,
    e.g. :class:`~torchrl_rave.envs.ActuatorNoise`'s noise stream); at every step, a copy
    of the action. :meth:`episode_state` returns them as plain data (JSON values and one
    array); :meth:`replay` restores the generators, resets with the same arguments and
    steps the same actions, which rebuilds the episode when the env is deterministic
    given its generators (MuJoCo on one machine is). The wrapper itself changes nothing
    the env returns.

    An episode longer than ``max_steps`` steps, or one whose generators or reset options
    cannot be written as plain data, is not kept (:meth:`episode_state` returns ``None``).

    Args:
        env: the env to record.
        max_steps: the longest episode kept. Defaults to 100,000 steps.

    Examples:
        >>> env = EpisodeReplay(gym.make("InvertedPendulum-v5"))
        >>> _ = env.reset(seed=3)
        >>> for a in (0.5, -0.2):
        ...     obs, *_ = env.step(np.array([a], dtype=np.float32))
        >>> twin = EpisodeReplay(gym.make("InvertedPendulum-v5"))
        >>> bool((twin.replay(env.episode_state()) == obs).all())
        True
    """

    def __init__(self, env: gym.Env, max_steps: int = 100_000) -> None:
        super().__init__(env)
        if int(max_steps) < 0:
            raise ValueError(f"EpisodeReplay: max_steps={max_steps!r} must be >= 0")
        self.max_steps = int(max_steps)
        self._reset: dict | None = None
        self._actions: list[np.ndarray] = []
        #: why :meth:`episode_state` returns ``None``, when it does
        self.why_not = "no reset yet"

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        generators = {name: g.bit_generator.state for name, g in _generators(self.env)}
        record = {"seed": seed, "options": options, "generators": generators}
        self._reset = record if _json_state(record) else None
        self.why_not = "its reset's options or generator states are not plain data"
        self._actions = []
        return self.env.reset(seed=seed, options=options)

    def step(self, action):
        if self._reset is not None:
            if len(self._actions) < self.max_steps:
                self._actions.append(np.array(action, copy=True))
            else:  # too long to keep
                self._reset, self._actions = None, []
                self.why_not = f"longer than max_steps={self.max_steps}"
        return self.env.step(action)

    def episode_state(self) -> dict | None:
        """The episode in progress as plain data: ``reset`` (the reset's ``seed``,
        ``options`` and generator states, JSON values), ``actions`` (a float64 array, one
        row per step taken since) and ``dtype`` (the actions' own), or ``None`` when it
        is not kept (no reset yet, too long, or not writable as plain data;
        :attr:`why_not` says which)."""
        if self._reset is None:
            return None
        shape = self.action_space.shape or ()
        actions = np.stack(self._actions) if self._actions else np.zeros((0, *shape))
        reset = json.loads(json.dumps(self._reset))  # a copy
        return {"reset": reset, "actions": actions.astype(np.float64), "dtype": actions.dtype.str}

    @staticmethod
    def _other_generators(generators: dict, saved: dict) -> EpisodeReplayError:
        return EpisodeReplayError(
            f"the env's random generators {sorted(generators)} are not those of the "
            f"recorded episode {sorted(saved)}: another env recorded it, or it began with "
            "an unseeded first reset (fresh entropy)"
        )

    def replay(self, state: dict):
        """Rebuilds the episode of ``state`` (from :meth:`episode_state`, possibly of
        another process): restores the generators, resets and steps the recorded
        actions. Returns the last observation. Raises :class:`EpisodeReplayError` when
        the actions or the env's generators are not the recording's, or the episode
        ended before its last recorded action."""
        try:
            reset, seed, saved = (
                state["reset"],
                state["reset"]["seed"],
                state["reset"]["generators"],
            )
            dtype = np.dtype(state["dtype"])
            actions = np.asarray(state["actions"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as err:
            raise EpisodeReplayError(
                f"not a recorded episode ({type(err).__name__}: {err})"
            ) from None
        if (
            dtype.kind != "f"
            or not (seed is None or type(seed) is int)
            or not isinstance(saved, dict)
        ):
            raise EpisodeReplayError(
                f"not a recorded episode: actions of dtype {dtype}, seed {seed!r}, generators "
                f"of type {type(saved).__name__}"
            )
        if len(actions) > self.max_steps:
            raise EpisodeReplayError(
                f"the recorded episode has {len(actions)} steps, more than max_steps="
                f"{self.max_steps} (no recording keeps more)"
            )
        actions = actions.astype(dtype)
        shape = self.action_space.shape or ()
        if actions.shape[1:] != shape:
            raise EpisodeReplayError(
                f"the recorded actions have shape {actions.shape[1:]}, this env's "
                f"{shape}: another env recorded them"
            )
        generators = dict(_generators(self.env))
        if not set(saved) <= set(generators):  # created by its first reset
            self.env.reset()
            generators = dict(_generators(self.env))
        if not set(saved) <= set(generators):
            raise self._other_generators(generators, saved)
        for name, value in saved.items():
            kind = type(generators[name].bit_generator).__name__
            recorded = value.get("bit_generator") if isinstance(value, dict) else value
            if recorded != kind:
                raise EpisodeReplayError(
                    f"generator {name} is a {kind}, the recorded episode's a {recorded!r}"
                )
            try:
                generators[name].bit_generator.state = value
            except (KeyError, TypeError, ValueError) as err:
                raise EpisodeReplayError(
                    f"generator {name}: unusable recorded state ({err})"
                ) from None
        obs, _ = self.reset(seed=seed, options=reset.get("options"))
        # a generator the recording did not have is made by the reset: from its seed, or,
        # unseeded, from fresh entropy, and then the episode cannot be rebuilt
        generators = dict(_generators(self.env))
        if seed is None and set(generators) != set(saved):
            raise self._other_generators(generators, saved)
        for i, action in enumerate(actions):
            obs, _, terminated, truncated, _ = self.step(action)
            if (terminated or truncated) and i < len(actions) - 1:
                raise EpisodeReplayError(
                    f"the replayed episode ended at step {i + 1} of {len(actions)}: the env "
                    "is not deterministic given its generators"
                )
        return obs
