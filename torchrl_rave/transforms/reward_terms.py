"""An env's reward as separately weighted terms: read them into the tensordict, relabel
the reward from them at every replay-buffer sample, and start one of them late.

An env whose reward is a sum of named terms (``LearnToMove-v0``: ``alive``, ``footstep``,
``velocity``, ``effort``, ``success``, ``target``) reports each step's terms in
``info["reward_terms"]``. :class:`RewardTermsReader` puts them in the tensordict (under
``("next", "reward_terms", name)`` once TorchRL steps the env), the replay buffer stores
them, and :class:`ReweightRewardTerms`, a replay-buffer transform, rewrites
``("next", "reward")`` from them with the weights it holds *now*: changing a weight
relabels every stored transition, so the learner's critics and world model always train
on the current objective, and an off-policy learner needs no new data to follow it.
:class:`DelayedWeight` is the schedule of the supplement's low-energy stage: a term's
weight is 0 until a frame count or an evaluation metric's threshold, then ramps up.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.gym_like import BaseInfoDictReader
from torchrl.envs.transforms import Transform

__all__ = ["DelayedWeight", "RewardTermsReader", "ReweightRewardTerms"]

TERMS_KEY = "reward_terms"


class RewardTermsReader(BaseInfoDictReader):
    """TorchRL info reader (``GymWrapper.set_info_dict_reader``) of ``info["reward_terms"]``,
    a dict of the step's reward terms by name: each becomes a float32 scalar entry
    ``("reward_terms", name)``. An info without terms (a reset's) reads as zeros; a step's
    terms must be exactly ``names`` (``KeyError`` otherwise: a misspelt name would read 0
    on every step, and an unnamed term would be missing from every relabelled reward).

    Args:
        names (Sequence[str]): the terms, in a fixed order.

    Examples:
        >>> from tensordict import TensorDict
        >>> reader = RewardTermsReader(["alive", "effort"])
        >>> td = reader({"reward_terms": {"alive": 0.1, "effort": -0.5}}, TensorDict())
        >>> td["reward_terms", "effort"]
        tensor(-0.5000)
    """

    def __init__(self, names: Sequence[str]) -> None:
        if not names or len(set(names)) != len(names):
            raise ValueError(f"reward term names must be distinct and not empty, got {names}")
        self.names = tuple(names)

    def __call__(self, info_dict: dict, tensordict: TensorDictBase) -> TensorDictBase:
        terms = info_dict.get(TERMS_KEY) or {}  # none at a reset: every term is 0
        if terms and set(terms) != set(self.names):
            # a name the env lacks would read 0 on every step, and a term not named would
            # be missing from every relabelled reward
            raise KeyError(
                f"info[{TERMS_KEY!r}] has the terms {sorted(terms)}, but the reader was given "
                f"{sorted(self.names)}: name exactly the env's terms"
            )
        for name in self.names:
            value = torch.tensor(float(terms.get(name, 0.0)), dtype=torch.float32)
            tensordict.set((TERMS_KEY, name), value)
        return tensordict

    @property
    def info_spec(self) -> dict:
        terms = Composite({n: Unbounded((), dtype=torch.float32) for n in self.names}, shape=())
        return {TERMS_KEY: terms}


class ReweightRewardTerms(Transform):
    """Replay-buffer transform: ``("next", "reward") = scale * sum_k w_k term_k`` from the
    stored ``("next", "reward_terms", k)``, with the weights ``weights`` holds when
    the batch is sampled (a term not in it has weight 1).

    Args:
        names (Sequence[str]): the env's terms.
        weights (Mapping[str, float]): initial weights by name; others are 1.
        scale (float): the reward scale the learner sees (the recipe's
            ``env.reward_scale``; TorchRL's ``RewardScaling`` scaled the stored reward alike).

    Examples:
        >>> from tensordict import TensorDict
        >>> batch = TensorDict({("next", "reward"): torch.zeros(2, 1),
        ...     ("next", "reward_terms", "alive"): torch.tensor([0.1, 0.1]),
        ...     ("next", "reward_terms", "effort"): torch.tensor([-1.0, -3.0])}, [2])
        >>> relabel = ReweightRewardTerms(["alive", "effort"], {"effort": 0.5})
        >>> relabel(batch)["next", "reward"].squeeze(-1)
        tensor([-0.4000, -1.4000])
    """

    def __init__(
        self, names: Sequence[str], weights: Mapping[str, float] | None = None, scale: float = 1.0
    ) -> None:
        super().__init__()
        self.names = tuple(names)
        self.weights: dict[str, float] = dict.fromkeys(self.names, 1.0)
        self.set_weights(weights or {})
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"scale must be a finite number > 0, got {scale}")
        self.scale = float(scale)

    def set_weights(self, weights: Mapping[str, float]) -> None:
        """Updates the weights of the named terms (from the next sample on)."""
        unknown = set(weights) - set(self.names)
        if unknown:
            raise KeyError(f"no reward term {sorted(unknown)}; the env's terms are {self.names}")
        for name, value in weights.items():
            if not math.isfinite(value):
                raise ValueError(f"the weight of {name!r} must be finite, got {value}")
            self.weights[name] = float(value)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        terms = tensordict.get(("next", TERMS_KEY))
        reward = sum(self.weights[n] * terms.get(n) for n in self.names) * self.scale
        shape = tensordict.get(("next", "reward")).shape
        tensordict.set(("next", "reward"), reward.reshape(shape))
        return tensordict

    _call = forward


class DelayedWeight:
    """A weight that is 0 until a start condition, then ramps linearly to ``weight`` over
    ``ramp_frames`` frames (at once with 0). It starts at the first :meth:`update` whose
    frame count reaches ``start_frames``, or whose ``metrics[metric]`` reaches
    ``threshold``, whichever comes first; ``started_at`` (the frame count then, or
    ``None``) is all its state.

    Args:
        weight (float): the weight once ramped up.
        start_frames (int, optional): start at this many frames.
        metric (str, optional): start once this metric (e.g. ``"eval/return"``) reaches
            ``threshold``.
        threshold (float, optional): see ``metric``.
        ramp_frames (int): frames from 0 to ``weight``.

    Examples:
        >>> w = DelayedWeight(1.0, start_frames=100, ramp_frames=50)
        >>> [w.update(f) for f in (0, 99, 100, 125, 150, 400)]
        [0.0, 0.0, 0.0, 0.5, 1.0, 1.0]
        >>> w = DelayedWeight(2.0, metric="eval/return", threshold=300.0)
        >>> [w.update(f, {"eval/return": r}) for f, r in ((10, 100.0), (20, 310.0), (30, 0.0))]
        [0.0, 2.0, 2.0]
    """

    def __init__(
        self,
        weight: float,
        start_frames: int | None = None,
        metric: str | None = None,
        threshold: float | None = None,
        ramp_frames: int = 0,
    ) -> None:
        if start_frames is None and metric is None:
            raise ValueError("a delayed weight needs start_frames, or a metric and a threshold")
        if (metric is None) != (threshold is None):
            raise ValueError(f"metric and threshold go together, got {metric!r} and {threshold!r}")
        if start_frames is not None and not (isinstance(start_frames, int) and start_frames >= 0):
            raise ValueError(f"start_frames must be an integer >= 0, got {start_frames!r}")
        if not (isinstance(ramp_frames, int) and ramp_frames >= 0):
            raise ValueError(f"ramp_frames must be an integer >= 0, got {ramp_frames!r}")
        self.weight, self.ramp_frames = float(weight), ramp_frames
        self.start_frames, self.metric, self.threshold = start_frames, metric, threshold
        self.started_at: int | None = None

    def update(self, frames: int, metrics: Mapping[str, float] | None = None) -> float:
        """The weight at ``frames``, given the latest ``metrics``; starts it if due."""
        if self.started_at is None:
            due = self.start_frames is not None and frames >= self.start_frames
            value = (metrics or {}).get(self.metric) if self.metric else None
            if due or (value is not None and value >= self.threshold):
                self.started_at = frames
        if self.started_at is None:
            return 0.0
        if self.ramp_frames == 0:
            return self.weight
        return self.weight * min(1.0, (frames - self.started_at) / self.ramp_frames)
