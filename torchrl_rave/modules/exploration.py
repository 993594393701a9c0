"""Gaussian action noise applied with a probability (the paper's epsilon exploration)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import Bounded, TensorSpec
from torchrl.envs.utils import ExplorationType, exploration_type

from torchrl_rave._checks import check_non_negative


class EpsilonGaussianModule(TensorDictModuleBase):
    """Adds Gaussian noise to the action with probability ``epsilon`` per step.

    The paper's DDPG explores by "adding a Gaussian noise to the action with probability
    epsilon = 0.05" (hyper-parameter table); ``epsilon = 1`` is the usual always-on
    Gaussian exploration. The noise standard deviation is ``sigma`` times half the width of
    the action box, so one ``sigma`` means the same thing on every MuJoCo task, and the noisy
    action is clipped back into the box. Noise is only added when the exploration type is
    ``RANDOM`` (what collectors use); deterministic evaluation sees the bare policy.

    Args:
        spec (Bounded): the action spec (its ``low``/``high`` scale and clip the noise).
        sigma (float): noise std in units of half the action range.
        epsilon (float): probability, per environment step, of adding noise. Defaults to 1.

    Keyword Args:
        action_key (NestedKey): where the action lives. Defaults to ``"action"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> spec = Bounded(-3.0, 3.0, shape=(1,))
        >>> noise = EpsilonGaussianModule(spec, sigma=0.1, epsilon=0.5)
        >>> td = noise(TensorDict({"action": torch.zeros(1000, 1)}, [1000]))
        >>> 0.4 < (td["action"] != 0).float().mean().item() < 0.6
        True
    """

    def __init__(
        self,
        spec: TensorSpec,
        sigma: float,
        epsilon: float = 1.0,
        *,
        action_key: NestedKey = "action",
    ) -> None:
        super().__init__()
        if not isinstance(spec, Bounded):
            raise TypeError(f"spec must be a Bounded action spec, got {type(spec).__name__}")
        check_non_negative("sigma", sigma)
        if not 0.0 <= float(epsilon) <= 1.0:
            raise ValueError(f"epsilon must lie in [0, 1], got {epsilon!r}")
        self.in_keys = [action_key]
        self.out_keys = [action_key]
        self.action_key = action_key
        self.register_buffer("low", spec.space.low.clone())
        self.register_buffer("high", spec.space.high.clone())
        self.register_buffer("sigma", torch.tensor(float(sigma)))
        self.register_buffer("epsilon", torch.tensor(float(epsilon)))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if exploration_type() not in (ExplorationType.RANDOM, None):
            return tensordict
        action = tensordict.get(self.action_key)
        scale = (self.high - self.low) / 2
        noise = torch.randn_like(action) * self.sigma * scale
        # one coin per environment step, shared by all action dimensions
        coin = torch.rand(action.shape[:-1], device=action.device) < self.epsilon
        noisy = action + noise * coin.unsqueeze(-1).to(action.dtype)
        tensordict.set(self.action_key, torch.maximum(torch.minimum(noisy, self.high), self.low))
        return tensordict
