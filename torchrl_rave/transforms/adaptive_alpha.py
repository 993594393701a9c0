"""Adaptive confidence factor alpha(s, a) of RAVE (paper eq. 12) as a TorchRL transform."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.envs.transforms import Transform

from torchrl_rave._checks import get_checked
from torchrl_rave.modules.world_model import WorldModelEnsemble
from torchrl_rave.objectives.functional import adaptive_alpha, check_alpha_parameters

__all__ = ["AdaptiveAlpha"]


class AdaptiveAlpha(Transform):
    """Writes ``alpha(s_t, a_t) = max(0, alpha (1 - ||mean_i f_s,i(s_t, a_t) - s_{t+1}||^2 / Z))``.

    The error is the ensemble-mean one-step prediction error on the *real* transition, in
    the normalised state-change units the world model is trained in. Early on the model
    is poor, the error is large and alpha is near 0 (exploration); as the model learns,
    alpha grows towards ``alpha`` (risk aversion).

    Use it as a replay-buffer transform, so every sampled batch carries the per-sample
    alpha, and build the estimator with ``alpha_mode="tensordict"``; or call it on any
    batch. :class:`~torchrl_rave.objectives.RAVEValueEstimator` with its default
    ``alpha_mode="adaptive"`` computes the same quantity itself (through
    :func:`~torchrl_rave.objectives.functional.adaptive_alpha`).

    The world model is held by reference (not registered), so a replay buffer's
    ``state_dict`` does not duplicate its weights.

    Args:
        world_model (WorldModelEnsemble): the trained ensemble.

    Keyword Args:
        alpha (float): the constant ``alpha`` of eq. 12. Defaults to 1.5 (paper).
        alpha_error_scale (float): ``Z``. Defaults to 1 (paper).
        observation_key (NestedKey): observation entry (``("next", key)`` is read too).
        action_key (NestedKey): action entry.
        out_key (NestedKey): where alpha is written, ``[*B, 1]``. Defaults to ``"rave_alpha"``.

    Examples:
        >>> from tensordict import TensorDict
        >>> wm = WorldModelEnsemble(2, 1, num_models=2, transition_cells=8, reward_cells=8,
        ...                         termination_cells=8)
        >>> batch = TensorDict(observation=torch.zeros(4, 2), action=torch.zeros(4, 1),
        ...                    next=TensorDict(observation=torch.zeros(4, 2), batch_size=[4]),
        ...                    batch_size=[4])
        >>> out = AdaptiveAlpha(wm, alpha=1.5)(batch)
        >>> out["rave_alpha"].shape, bool((out["rave_alpha"] <= 1.5).all())
        (torch.Size([4, 1]), True)
    """

    def __init__(
        self,
        world_model: WorldModelEnsemble,
        *,
        alpha: float = 1.5,
        alpha_error_scale: float = 1.0,
        observation_key: NestedKey = "observation",
        action_key: NestedKey = "action",
        out_key: NestedKey = "rave_alpha",
    ) -> None:
        alpha, alpha_error_scale = check_alpha_parameters(alpha, alpha_error_scale)
        super().__init__(
            in_keys=[observation_key, action_key, ("next", observation_key)],
            out_keys=[out_key],
        )
        self.__dict__["world_model"] = world_model
        self.register_buffer("alpha", torch.tensor(float(alpha)))
        self.register_buffer("alpha_error_scale", torch.tensor(float(alpha_error_scale)))

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs_key, action_key, next_key = self.in_keys
        S, A = self.world_model.observation_dim, self.world_model.action_dim
        dtype = self.world_model.dtype
        # names a missing entry or a wrong width; no NaN scan (a device sync) per sample
        obs, action, next_obs = (
            get_checked(tensordict, key, size, check_finite=False, dtype=dtype, floating=True)
            for key, size in ((obs_key, S), (action_key, A), (next_key, S))
        )
        err = self.world_model.mean_prediction_error(obs, action, next_obs)
        alpha = adaptive_alpha(err, self.alpha, self.alpha_error_scale)
        tensordict.set(self.out_keys[0], alpha.unsqueeze(-1))
        return tensordict

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        raise RuntimeError(
            "AdaptiveAlpha works on batches of transitions (replay-buffer samples), not inside an env"
        )
