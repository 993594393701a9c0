"""Training loss of the probabilistic world-model ensemble."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch.nn import functional as F
from torchrl.objectives import LossModule

from torchrl_rave._checks import check_finite_losses, check_not_empty, get_checked
from torchrl_rave.modules.world_model import WorldModelEnsemble

__all__ = ["WorldModelEnsembleLoss", "gaussian_nll", "world_model_loss_terms"]

_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


def gaussian_nll(mean: torch.Tensor, logvar: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Elementwise negative log likelihood of ``target`` under ``N(mean, exp(logvar))`` (paper eq. 3).

    Examples:
        >>> gaussian_nll(torch.zeros(1), torch.zeros(1), torch.zeros(1))  # -log N(0; 0, 1)
        tensor([0.9189])
    """
    return 0.5 * ((target - mean).pow(2) * torch.exp(-logvar) + logvar) + _HALF_LOG_2PI


def world_model_loss_terms(
    transition: tuple[torch.Tensor, torch.Tensor],
    transition_target: torch.Tensor,
    reward: tuple[torch.Tensor, torch.Tensor],
    reward_target: torch.Tensor,
    termination_logits: torch.Tensor,
    terminated: torch.Tensor,
    bound_penalties: tuple[torch.Tensor, torch.Tensor],
    *,
    reward_coeff: float = 1.0,
    termination_coeff: float = 1.0,
    logvar_bound_coeff: float = 0.01,
) -> dict[str, torch.Tensor]:
    """The world-model loss from the members' predictions: the functional core of
    :class:`WorldModelEnsembleLoss`, for one ensemble or many (a seed group's).

    Every tensor is ``[*S, N, B, F]``: any leading dimensions ``S`` (none for one
    ensemble, the seed for a group), the ``N`` members, each member's ``B`` (bootstrapped)
    transitions, the features. The members' losses are independent, so each is averaged
    over its batch and features and the members are summed: one backward gives each member
    exactly its own gradient.

    Args:
        transition: the transition head's ``(mean, logvar)`` of the normalised delta.
        transition_target: the normalised delta ``next_obs - obs``.
        reward: the reward head's ``(mean, logvar)``.
        reward_target: the normalised reward.
        termination_logits: the termination head's logits.
        terminated: ``1`` where the transition terminated (floating).
        bound_penalties: each model's ``sum(max_logvar) - sum(min_logvar)`` of the
            transition and reward heads, ``[*S]``.

    Keyword Args:
        reward_coeff (float): as :class:`WorldModelEnsembleLoss` takes it.
        termination_coeff (float): as :class:`WorldModelEnsembleLoss` takes it.
        logvar_bound_coeff (float): as :class:`WorldModelEnsembleLoss` takes it.

    Returns:
        ``loss_transition``, ``loss_reward``, ``loss_termination`` (``[*S]``, with
        gradients) and, detached, the members' mean ``transition_nll``,
        ``transition_mse``, ``reward_nll``, ``reward_mse``, ``termination_bce`` and the
        ``termination_accuracy`` of the logits' sign (``[*S]``).

    Examples:
        >>> z = torch.zeros(2, 3, 1)  # N = 2 members, B = 3 transitions, one feature
        >>> out = world_model_loss_terms((z, z), z, (z, z), z, z, z, (z.sum(), z.sum()))
        >>> out["loss_transition"]  # 2 members x -log N(0; 0, 1)
        tensor(1.8379)
    """
    mean, logvar = transition
    transition_nll = gaussian_nll(mean, logvar, transition_target).mean((-2, -1))  # [*S, N]
    transition_mse = (mean - transition_target).pow(2).mean((-2, -1))
    r_mean, r_logvar = reward
    reward_nll = gaussian_nll(r_mean, r_logvar, reward_target).mean((-2, -1))
    reward_mse = (r_mean - reward_target).pow(2).mean((-2, -1))
    termination_bce = F.binary_cross_entropy_with_logits(
        termination_logits, terminated, reduction="none"
    ).mean((-2, -1))
    c = logvar_bound_coeff
    transition_bound, reward_bound = bound_penalties
    with torch.no_grad():
        hit = (termination_logits > 0).to(terminated.dtype) == terminated
        accuracy = hit.to(mean.dtype).mean((-3, -2, -1))
    return {
        "loss_transition": transition_nll.sum(-1) + c * transition_bound,
        "loss_reward": reward_coeff * (reward_nll.sum(-1) + c * reward_bound),
        "loss_termination": termination_coeff * termination_bce.sum(-1),
        "transition_nll": transition_nll.detach().mean(-1),
        "transition_mse": transition_mse.detach().mean(-1),
        "reward_nll": reward_nll.detach().mean(-1),
        "reward_mse": reward_mse.detach().mean(-1),
        "termination_bce": termination_bce.detach().mean(-1),
        "termination_accuracy": accuracy,
    }


class WorldModelEnsembleLoss(LossModule):
    """Gaussian NLL for transition and reward, cross-entropy for termination.

    Each member trains on its own bootstrap resample of the batch: indices are drawn
    independently per member (``[N, B]``), so the ensemble does not collapse into copies.
    The learned log-variance bounds get the usual small penalty
    (``logvar_bound_coeff * (sum max - sum min)``).

    The output holds three losses to sum (``loss_transition``, ``loss_reward``,
    ``loss_termination``) and, for logging, per-head NLL/MSE (normalised units, averaged
    over members) and termination accuracy.

    Args:
        world_model (WorldModelEnsemble): the ensemble to train.

    Keyword Args:
        bootstrap (bool): resample the batch per member. Defaults to ``True``.
        logvar_bound_coeff (float): weight of the log-variance bound penalty. Defaults to 0.01.
        reward_coeff (float): weight of the reward loss. Defaults to 1.
        termination_coeff (float): weight of the termination loss. Defaults to 1.
        check_finite (bool): reject NaN/inf in the batch with an error naming the entry
            (one device sync per entry). Turn it off when the data were checked on the way
            into the buffer, as the recipe does. Shapes are always checked. Defaults to
            ``True``.

    Examples:
        >>> wm = WorldModelEnsemble(3, 1, num_models=2, transition_cells=8, reward_cells=8,
        ...                         termination_cells=8)
        >>> batch = TensorDict(
        ...     observation=torch.randn(16, 3), action=torch.rand(16, 1),
        ...     next=TensorDict(observation=torch.randn(16, 3), reward=torch.randn(16, 1),
        ...                     terminated=torch.zeros(16, 1, dtype=torch.bool), batch_size=[16]),
        ...     batch_size=[16])
        >>> wm.update_normalizers_from(batch)  # statistics of the data the model sees
        >>> loss = WorldModelEnsembleLoss(wm)
        >>> out = loss(batch)
        >>> sorted(out.keys())  # doctest: +NORMALIZE_WHITESPACE
        ['loss_reward', 'loss_termination', 'loss_transition', 'reward_mse', 'reward_nll',
         'termination_accuracy', 'termination_bce', 'transition_mse', 'transition_nll']
        >>> (out["loss_transition"] + out["loss_reward"] + out["loss_termination"]).backward()
    """

    @dataclass
    class _AcceptedKeys:
        """Keys read from the input tensordict.

        Attributes:
            observation (NestedKey): current observation. Defaults to ``"observation"``.
            action (NestedKey): action taken. Defaults to ``"action"``.
            next_observation (NestedKey): observation after the step.
                Defaults to ``("next", "observation")``.
            reward (NestedKey): reward of the step. Defaults to ``("next", "reward")``.
            terminated (NestedKey): termination flag. Defaults to ``("next", "terminated")``.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        next_observation: NestedKey = ("next", "observation")
        reward: NestedKey = ("next", "reward")
        terminated: NestedKey = ("next", "terminated")

    default_keys = _AcceptedKeys
    world_model: WorldModelEnsemble

    def __init__(
        self,
        world_model: WorldModelEnsemble,
        *,
        bootstrap: bool = True,
        logvar_bound_coeff: float = 0.01,
        reward_coeff: float = 1.0,
        termination_coeff: float = 1.0,
        check_finite: bool = True,
    ) -> None:
        super().__init__()
        self.check_finite = check_finite
        self.world_model = world_model
        self.bootstrap = bootstrap
        self.logvar_bound_coeff = logvar_bound_coeff
        self.reward_coeff = reward_coeff
        self.termination_coeff = termination_coeff

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        # no value estimator to forward keys to
        pass

    @property
    def in_keys(self):
        k = self.tensor_keys
        return [k.observation, k.action, k.next_observation, k.reward, k.terminated]

    @property
    def out_keys(self):
        return ["loss_transition", "loss_reward", "loss_termination"]

    def bootstrap_indices(
        self, batch_size: int, device: torch.device | None = None
    ) -> torch.Tensor:
        """Independent resample indices per member, ``[N, batch_size]``."""
        N = self.world_model.num_models
        if not self.bootstrap:
            return torch.arange(batch_size, device=device).expand(N, batch_size)
        return torch.randint(batch_size, (N, batch_size), device=device)

    def loss_terms(
        self,
        world_model: WorldModelEnsemble,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        reward: torch.Tensor,
        terminated: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """:func:`world_model_loss_terms` of ``world_model``'s predictions, with this
        loss's coefficients, on each member's own (resampled) transitions ``[N, B, F]``
        (``reward`` and ``terminated`` ``[N, B, 1]``, floating); with a seed group's
        stacked world model, ``[S, N, B, F]`` and per-seed outputs ``[S]``."""
        wm = world_model
        return world_model_loss_terms(
            wm.predict_transition(obs, action, per_member=True),
            wm.target_delta(obs, next_obs),
            wm.predict_reward(obs, action, next_obs, per_member=True),
            wm.reward_norm.normalize(reward),
            wm.termination_logits(next_obs, per_member=True),
            terminated,
            (wm.transition.bound_penalty(), wm.reward_model.bound_penalty()),
            reward_coeff=self.reward_coeff,
            termination_coeff=self.termination_coeff,
            logvar_bound_coeff=self.logvar_bound_coeff,
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        wm = self.world_model
        wm.check_normalizers()
        keys = self.tensor_keys
        S, A = wm.observation_dim, wm.action_dim
        check = self.check_finite
        check_not_empty(tensordict, type(self).__name__)
        read = functools.partial(get_checked, tensordict, check_finite=check, dtype=wm.dtype)
        obs = read(keys.observation, S).reshape(-1, S)
        action = read(keys.action, A).reshape(-1, A)
        next_obs = read(keys.next_observation, S).reshape(-1, S)
        reward = read(keys.reward, floating=True).reshape(-1, 1)
        terminated = (
            get_checked(tensordict, keys.terminated, check_finite=check)
            .reshape(-1, 1)
            .to(obs.dtype)
        )
        if not (obs.shape[0] == action.shape[0] == next_obs.shape[0] == reward.shape[0]):
            raise ValueError(
                "observation, action, next observation and reward hold different numbers of "
                f"transitions: {obs.shape[0]}, {action.shape[0]}, {next_obs.shape[0]}, {reward.shape[0]}"
            )

        idx = self.bootstrap_indices(obs.shape[0], obs.device)
        obs, action, next_obs = obs[idx], action[idx], next_obs[idx]  # [N, B, F]
        reward, terminated = reward[idx], terminated[idx]

        out = self.loss_terms(wm, obs, action, next_obs, reward, terminated)
        if check:
            check_finite_losses(
                type(self).__name__,
                {"loss_transition": out["loss_transition"], "loss_reward": out["loss_reward"]},
                tensordict, [keys.observation, keys.action, keys.next_observation, keys.reward],
            )  # fmt: skip
        return TensorDict(out)
