"""Value-expansion estimators (MVE, STEVE, RAVE) as TorchRL value estimators."""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable
from dataclasses import field, make_dataclass
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.objectives.value import ValueEstimatorBase

from torchrl_rave._checks import (
    POSITIVE,
    UNIT_INTERVAL,
    check_not_empty,
    check_positive_int,
    first_param_dtype,
    get_checked,
)
from torchrl_rave.modules.world_model import WorldModelEnsemble
from torchrl_rave.objectives import functional as VF
from torchrl_rave.objectives.target_networks import TargetNetworks

__all__ = [
    "ValueExpansionEstimator",
    "MVEEstimator",
    "STEVEEstimator",
    "RAVEValueEstimator",
    "make_value_expansion_estimator",
]

RolloutMode = Literal["sample", "mean"]
MixMode = Literal["inverse_variance", "fixed"]
AlphaMode = Literal["constant", "adaptive", "tensordict"]


_ESTIMATOR_KEYS = {
    "advantage": "advantage",
    "value_target": "value_target",
    "value": "state_action_value",
    "reward": "reward",
    "done": "done",
    "terminated": "terminated",
    "observation": "observation",
    "action": "action",
}
_DIAGNOSTIC_KEYS = ("alpha", "horizon_variance", "horizon_weights")  # <prefix>_<name>


def _accepted_keys(prefix: str) -> type:
    """The estimators' configurable keys, with the diagnostics under ``<prefix>_*``.
    (TorchRL's ``set_keys`` looks the names up in the class's own ``__dict__``, where a
    dataclass keeps its defaults.)"""
    defaults = {**_ESTIMATOR_KEYS, **{name: f"{prefix}_{name}" for name in _DIAGNOSTIC_KEYS}}
    keys = make_dataclass(
        "_AcceptedKeys", [(name, NestedKey, field(default=v)) for name, v in defaults.items()]
    )
    keys.__doc__ = _ACCEPTED_KEYS_DOC
    return keys


_ACCEPTED_KEYS_DOC = """Configurable tensordict keys (``set_keys``).

Attributes:
    advantage (NestedKey): where ``forward`` writes ``target - value``. Defaults to ``"advantage"``.
    value_target (NestedKey): where ``forward`` writes the target. Defaults to ``"value_target"``.
    value (NestedKey): the critic's output. Defaults to ``"state_action_value"``.
    reward (NestedKey): reward, read under ``"next"``. Defaults to ``"reward"``.
    done (NestedKey): done flag, read under ``"next"``. Defaults to ``"done"``.
    terminated (NestedKey): termination flag, read under ``"next"``. Defaults to ``"terminated"``.
    observation (NestedKey): observation entry. Defaults to ``"observation"``.
    action (NestedKey): action entry. Defaults to ``"action"``.
    alpha (NestedKey): per-sample alpha used (written; read in ``"tensordict"`` mode).
        Defaults to ``"<prefix>_alpha"``: ``rave_alpha``, ``steve_alpha``,
        ``mve_alpha``, ``value_expansion_alpha`` for the base class.
    horizon_variance (NestedKey): ``V_H`` per sample, ``[*B, H_max + 1]``.
        Defaults to ``"<prefix>_horizon_variance"``.
    horizon_weights (NestedKey): normalised ``w_H`` per sample. Defaults to
        ``"<prefix>_horizon_weights"``.
"""


def world_model_calls(world_model: WorldModelEnsemble, sample: bool) -> dict[str, Callable]:
    """The world model's calls of :func:`~torchrl_rave.objectives.functional.value_expansion_target`
    (``step``, ``imagined_reward``, ``termination_prob``), for one model or a seed
    group's stacked one (every tensor then leads with the seed)."""

    def step(s, a, per_member):
        return world_model.step(s, a, sample=sample, per_member=per_member)

    def imagined_reward(s, a, s2):  # [Nj, Ni, M, H]: shared inputs, every reward member
        return world_model.reward(s, a, s2, sample=sample).squeeze(-1)

    def termination_prob(s2):  # [Ni, M, H]: each member's own
        return world_model.termination_prob(s2, per_member=True).squeeze(-1)

    return {"step": step, "imagined_reward": imagined_reward, "termination_prob": termination_prob}


class ValueExpansionEstimator(ValueEstimatorBase):
    """Model-based value-expansion target for a Q-function: the MVE / STEVE / RAVE family.

    From every real transition ``(s_t, a_t, r_t, s_{t+1}, d_{t+1})`` it rolls each of the
    ``N`` transition members ``H_max`` steps with the target policy, scores the imagined
    steps with the ``N`` reward members and the last state of each horizon with the ``K``
    target critics, and forms the ``N * N * K * (H_max + 1)`` candidate targets ``T_H(i,j,k)``
    (paper eq. 9). Their per-horizon mean ``E_H`` and variance ``V_H`` give the target:

    ==============  ==============  ========================  ==========================
    algorithm       ``rollout``     ``mix``                   ``alpha``
    ==============  ==============  ========================  ==========================
    MVE (eq. 5)     ``"mean"``      ``"fixed"``               0
    STEVE (eq. 6)   ``"mean"``      ``"inverse_variance"``    0
    RAVE (eq. 11)   ``"sample"``    ``"inverse_variance"``    ``alpha`` or ``alpha(s,a)``
                                                              (eq. 12)
    ==============  ==============  ========================  ==========================

    Network evaluations per batch of ``M`` samples: ``N M H_max`` transition rows,
    ``N^2 M H_max`` reward rows, ``K M (1 + N H_max)`` critic rows and
    ``M (1 + N H_max)`` actor rows, combined by broadcasting (never ``N^3`` calls).
    The target carries no gradient: neither the critics, the actor nor the world model
    receive any through it.

    The estimator reads the loss's *target* actor and critic parameters at call time
    (:meth:`for_loss` wires them), so soft updates are seen without re-wiring. A critic
    with stacked parameters (leading dim ``K``, as in ``TD3Loss``) is evaluated as a
    ``K``-member ensemble through ``torch.vmap``; plain parameters mean ``K = 1``.

    The world model and the networks are held by reference, not registered as
    submodules, so they do not appear twice in the loss's ``parameters()``.

    Diagnostics (per-sample alpha, ``V_H`` and the horizon weights) are written into the
    input tensordict under the ``alpha``/``horizon_variance``/``horizon_weights`` keys and
    kept as ``diagnostics`` (a TensorDict) for losses that work on a copy of the batch.

    STEVE and RAVE need ``K >= 2`` critics: with one, every ``H = 0`` candidate is the
    same number, ``V_0 = 0`` and the inverse-variance mix returns TD(0) after paying for
    every rollout, so a single critic is refused (use
    :class:`~torchrl_rave.objectives.EnsembleDDPGLoss`, the paper's ``K = 4``).

    Diagnostics are keyed by the estimator that wrote them (``rave_*``, ``steve_*``,
    ``mve_*``; renameable with ``set_keys``).

    Keyword Args:
        world_model (WorldModelEnsemble): the probabilistic ensemble (any object with the
            same ``num_models``/``step``/``reward``/``termination_prob`` methods works).
        actor_network (TensorDictModuleBase): deterministic policy ``observation -> action``.
        value_network (TensorDictModuleBase): critic ``(observation, action) -> value``.
        gamma (float): discount.
        horizon (int): ``H_max`` for the inverse-variance mix; the fixed ``H`` for MVE.
        rollout (str): ``"sample"`` (draw from each member's Gaussian) or ``"mean"``.
        mix (str): ``"inverse_variance"`` or ``"fixed"``.
        alpha (float): confidence factor ``alpha`` (>= 0).
        alpha_mode (str): ``"constant"`` uses ``alpha``; ``"adaptive"`` uses
            ``max(0, alpha (1 - err(s,a) / Z))`` from the world model's one-step error on
            the real transition (eq. 12); ``"tensordict"`` reads a per-sample alpha
            written by :class:`~torchrl_rave.transforms.AdaptiveAlpha` under the ``alpha`` key.
        alpha_error_scale (float): ``Z`` of eq. 12.
        actor_params (TensorDictBase, optional): parameters to run the actor with
            (typically target parameters). Defaults to the module's own.
        value_params (TensorDictBase, optional): critic parameters, optionally stacked
            with a leading ensemble dimension ``K``. Defaults to the module's own.
        variance_eps (float): ``eps`` in ``w_H = 1 / (V_H + eps)``, > 0: on a row that
            terminates, every candidate's variance is 0, and ``eps = 0`` would divide by 0.
        check_inputs (bool): validate shapes and reject NaN/inf in the batch (one
            device sync per call). Defaults to ``True``.
        fast_calls (bool): evaluate the actor and critics through
            :class:`~torchrl_rave.modules.TensorCall` (direct matmuls on the target
            parameters, one batched matmul per layer for ``K`` critics) when their structure
            allows it; ``False`` always goes through the TensorDict modules (and ``vmap``).
            Both give the same numbers. Defaults to ``True``.
        networks (TargetNetworks, optional): the actor and critics to call, already wired
            (:meth:`for_loss` passes a loss's, whose target parameters it reads at call
            time); when given, ``actor_params``, ``value_params``, ``fast_calls`` and the
            temperature are its own. Defaults to ``None``: built from the arguments above.
        temperature (float, optional): with a probabilistic ``actor_network`` (SAC's), the
            entropy temperature of the soft target (see
            :func:`~torchrl_rave.objectives.functional.value_expansion_target`);
            :meth:`for_loss` reads a ``SACLoss``'s at
            call time instead. Defaults to ``None``: a deterministic actor.
        device (torch.device, optional): where the buffers live.

    Examples:
        >>> from torchrl.modules import MLP, Actor, ValueOperator
        >>> from torchrl_rave.objectives import EnsembleDDPGLoss
        >>> wm = WorldModelEnsemble(3, 1, num_models=2, transition_cells=8, reward_cells=8,
        ...                         termination_cells=8)
        >>> actor = Actor(MLP(in_features=3, out_features=1, num_cells=[8]))
        >>> qvalue = ValueOperator(MLP(in_features=4, out_features=1, num_cells=[8]),
        ...                        in_keys=["observation", "action"])
        >>> loss = EnsembleDDPGLoss(actor, qvalue, num_value_nets=4)
        >>> _ = loss.make_value_estimator(RAVEValueEstimator.for_loss(
        ...     loss, world_model=wm, gamma=0.99, horizon=3, alpha=1.5))
        >>> batch = TensorDict(
        ...     observation=torch.randn(8, 3), action=torch.rand(8, 1),
        ...     next=TensorDict(observation=torch.randn(8, 3), reward=torch.randn(8, 1),
        ...                     done=torch.zeros(8, 1, dtype=torch.bool),
        ...                     terminated=torch.zeros(8, 1, dtype=torch.bool), batch_size=[8]),
        ...     batch_size=[8])
        >>> loss.value_estimator.value_estimate(batch).shape
        torch.Size([8, 1])
        >>> batch["rave_horizon_weights"].shape, batch["rave_alpha"].shape
        (torch.Size([8, 4]), torch.Size([8, 1]))
    """

    _AcceptedKeys = _accepted_keys("value_expansion")
    default_keys = _AcceptedKeys

    def __init__(
        self,
        *,
        world_model: WorldModelEnsemble,
        actor_network: TensorDictModuleBase,
        value_network: TensorDictModuleBase,
        gamma: float,
        horizon: int = 3,
        rollout: RolloutMode = "sample",
        mix: MixMode = "inverse_variance",
        alpha: float = 0.0,
        alpha_mode: AlphaMode = "constant",
        alpha_error_scale: float = 1.0,
        actor_params: TensorDictBase | None = None,
        value_params: TensorDictBase | None = None,
        variance_eps: float = 1e-8,
        check_inputs: bool = True,
        fast_calls: bool = True,
        networks: TargetNetworks | None = None,
        temperature: float | None = None,
        device: torch.device | None = None,
    ) -> None:
        super().__init__(value_network=value_network, differentiable=False, device=device)
        check_positive_int("horizon", horizon, minimum=0)
        alpha, alpha_error_scale = VF.check_alpha_parameters(alpha, alpha_error_scale)
        UNIT_INTERVAL.check("gamma", float(gamma))
        if rollout not in ("sample", "mean"):
            raise ValueError(f"rollout must be 'sample' or 'mean', got {rollout!r}")
        if mix not in ("inverse_variance", "fixed"):
            raise ValueError(f"mix must be 'inverse_variance' or 'fixed', got {mix!r}")
        if alpha_mode not in ("constant", "adaptive", "tensordict"):
            raise ValueError(
                f"alpha_mode must be 'constant', 'adaptive' or 'tensordict', got {alpha_mode!r}"
            )
        check_positive_int("world_model.num_models", getattr(world_model, "num_models", None))
        self.horizon = horizon
        self.rollout = rollout
        self.mix = mix
        self.alpha_mode = alpha_mode
        self.variance_eps = float(POSITIVE.check("variance_eps", variance_eps))
        self.check_inputs = check_inputs
        # in the world model's precision: a float32 gamma would cost a float64 model 3e-8
        dtype = first_param_dtype(world_model) or torch.get_default_dtype()
        for name, value in (("gamma", gamma), ("alpha", alpha),
                            ("alpha_error_scale", alpha_error_scale)):  # fmt: skip
            self.register_buffer(name, torch.tensor(float(value), dtype=dtype, device=self._device))
        # Held by reference: the loss (or the user) owns and trains these.
        self.__dict__["world_model"] = world_model
        if networks is None:
            networks = TargetNetworks(
                actor_network,
                value_network,
                actor_params=actor_params,
                value_params=value_params,
                fast_calls=fast_calls,
                stochastic=temperature is not None,
                temperature=temperature,
            )
        elif temperature is not None:
            raise ValueError("temperature= comes with the networks= given (their temperature())")
        self.__dict__["networks"] = networks
        self.__dict__["diagnostics"] = None

    @property
    def actor_network(self) -> TensorDictModuleBase:
        return self.networks.actor_network

    @property
    def fast_calls(self) -> bool:
        return self.networks.calls.enabled

    @fast_calls.setter
    def fast_calls(self, value: bool) -> None:
        self.networks.calls.enabled = value

    # ----------------------------------------------------------------- wiring
    @classmethod
    def for_loss(cls, loss_module, **hyperparams) -> ValueExpansionEstimator:
        """Builds an estimator on ``loss_module``'s actor and critic (target parameters).

        Works with :class:`~torchrl_rave.objectives.EnsembleDDPGLoss` (``K`` =
        ``num_value_nets``), ``TD3Loss`` and other losses exposing ``qvalue_network`` with
        stacked parameters (``K`` = their number), and copies the loss's key names (value,
        reward, done, terminated, action). A single-critic loss (``DDPGLoss``) is refused
        for STEVE and RAVE (with one critic, ``V_0 = 0`` and the mix reduces to TD(0)).

        Keyword Args:
            world_model (WorldModelEnsemble): required.
            **hyperparams: the constructor's other keyword arguments.
        """
        if "world_model" not in hyperparams:
            raise ValueError(f"{cls.__name__}.for_loss needs world_model=")
        networks = TargetNetworks.of_loss(
            loss_module,
            hyperparams.pop("actor_network", None),
            fast_calls=hyperparams.get("fast_calls", True),
        )
        estimator = cls(
            actor_network=networks.actor_network,
            value_network=networks.value_network,
            networks=networks,
            **hyperparams,
        )
        estimator._check_num_critics(networks.wired_num_critics())
        loss_keys = loss_module.tensor_keys
        forwarded = {
            "value": getattr(loss_keys, "state_action_value", None),
            "reward": getattr(loss_keys, "reward", None),
            "done": getattr(loss_keys, "done", None),
            "terminated": getattr(loss_keys, "terminated", None),
            "action": getattr(loss_keys, "action", None),
        }
        estimator.set_keys(**{k: v for k, v in forwarded.items() if v is not None})
        return estimator

    @property
    def in_keys(self):
        k = self.tensor_keys
        return [
            k.observation,
            k.action,
            ("next", k.observation),
            ("next", k.reward),
            ("next", k.done),
            ("next", k.terminated),
        ]

    @property
    def out_keys(self):
        k = self.tensor_keys
        return [k.value_target, k.alpha, k.horizon_variance, k.horizon_weights]

    def _alpha(self, obs, action, next_obs, tensordict, batch_shape) -> torch.Tensor:
        if self.alpha_mode == "constant":
            return self.alpha
        if self.alpha_mode == "tensordict":
            key = self.tensor_keys.alpha
            alpha = tensordict.get(key, None)
            if alpha is None:
                raise ValueError(
                    f"alpha_mode='tensordict' but the batch has no {key!r} entry; apply the "
                    "AdaptiveAlpha transform to sampled batches first"
                )
            return alpha.reshape(-1)
        err = self.world_model.mean_prediction_error(obs, action, next_obs)
        return VF.adaptive_alpha(err, self.alpha, self.alpha_error_scale)

    # ------------------------------------------------------------------ target
    def _warn_if_untrained(self, wm) -> None:
        """Warns once when the world model's normalisers never saw data: its rollouts then
        come from a model that was never trained (``WorldModelTrainer.extend`` and ``step``
        were not called). Checked until the first call that finds them fitted."""
        if self.__dict__.get("_model_seen_data") or not hasattr(wm, "normalizers_fitted"):
            return
        if wm.normalizers_fitted:
            self.__dict__["_model_seen_data"] = True
        elif not self.__dict__.get("_warned_untrained"):
            self.__dict__["_warned_untrained"] = True
            warnings.warn(
                f"{type(self).__name__} is expanding with a world model that never saw data "
                "(its normalisers are empty): its targets come from an untrained model. "
                "Call WorldModelTrainer.extend(batch) on every collected batch and "
                "WorldModelTrainer.step(replay_buffer) before each agent update",
                UserWarning,
                stacklevel=3,
            )

    def check_batch(self, tensordict: TensorDictBase) -> None:
        """Names a missing entry, a wrong width or dtype, or an empty batch before any
        network sees the batch (a loss calls it first); NaN is checked by the target."""
        if self.check_inputs:
            self._read_batch(tensordict, check_finite=False)

    def _read_batch(self, tensordict: TensorDictBase, check_finite: bool | None = None):
        k = self.tensor_keys
        wm = self.world_model
        check = self.check_inputs
        finite = check if check_finite is None else check_finite
        S = getattr(wm, "observation_dim", None) if check else None
        A = getattr(wm, "action_dim", None) if check else None
        dtype = first_param_dtype(wm) if check else None
        if check:
            check_not_empty(tensordict, type(self).__name__)
        checked = functools.partial(get_checked, check_finite=finite, dtype=dtype, floating=True)
        obs = checked(tensordict, k.observation, S)
        action = checked(tensordict, k.action, A)
        next_obs = checked(tensordict, ("next", k.observation), S)
        reward = checked(tensordict, ("next", k.reward))
        terminated = tensordict.get(("next", k.terminated), None)
        if terminated is None:
            terminated = get_checked(tensordict, ("next", k.done), check_finite=False)
        batch_shape = reward.shape[:-1] if reward.shape[-1:] == (1,) else reward.shape
        if check and obs.shape[:-1] != batch_shape:
            raise ValueError(
                f"reward has batch shape {tuple(batch_shape)} but observation has shape "
                f"{tuple(obs.shape)}; expected [*B, 1] rewards for [*B, S] observations"
            )
        return obs, action, next_obs, reward, terminated, batch_shape

    def _check_num_critics(self, num_critics: int) -> None:
        """Refuses one critic where the inverse-variance mix needs several.

        With ``K = 1`` every ``H = 0`` candidate is the same number, so ``V_0 = 0``; with
        ``N > 1`` model members the longer horizons have ``V_H > 0`` and the mix puts all
        its weight on ``H = 0``: STEVE and RAVE would pay for every rollout and return
        TD(0).
        """
        if (
            num_critics == 1
            and self.world_model.num_models > 1
            and self.horizon > 0
            and self.mix == "inverse_variance"
        ):
            raise ValueError(
                f"{type(self).__name__} needs K >= 2 critics: with a single critic V_0 = 0 "
                "and the inverse-variance mix reduces to TD(0) after paying for every "
                "rollout. Use torchrl_rave.EnsembleDDPGLoss(actor, critic, num_value_nets=4) "
                "(the paper's K = 4), TD3Loss(num_qvalue_nets=K), or stacked value_params."
            )

    @torch.no_grad()
    def value_estimate(
        self,
        tensordict: TensorDictBase,
        target_params: TensorDictBase | None = None,
        next_value: torch.Tensor | None = None,
        **kwargs,
    ) -> torch.Tensor:
        """Computes the target ``[*B, 1]`` and writes the diagnostics into ``tensordict``.

        Args:
            tensordict (TensorDictBase): a batch of transitions with batch shape ``[*B]``.
            target_params (TensorDictBase, optional): ``DDPGLoss``-style actor-critic
                parameters (``("module", "0")`` actor, ``("module", "1")`` critic); when
                absent the wired target parameters are used.
        """
        if next_value is not None:
            raise ValueError(
                f"{type(self).__name__} computes its own values; next_value is not supported"
            )
        wm = self.world_model
        if not torch.compiler.is_compiling():
            self._warn_if_untrained(wm)
        N, H = wm.num_models, self.horizon
        obs, action, next_obs, reward, terminated, batch_shape = self._read_batch(tensordict)
        S, A = obs.shape[-1], action.shape[-1]
        obs, action, next_obs = obs.reshape(-1, S), action.reshape(-1, A), next_obs.reshape(-1, S)
        reward, terminated = reward.reshape(-1), terminated.reshape(-1)
        M = reward.shape[0]
        sample = self.rollout == "sample"
        alpha = self._alpha(obs, action, next_obs, tensordict, batch_shape)
        nets, keys = self.networks, self.tensor_keys
        actor_params, value_params = nets.params(target_params)
        self._check_num_critics(nets.num_critics(value_params))

        def policy(s):  # a stochastic actor's (action, log_prob)
            if nets.stochastic:
                return nets.sample(s, actor_params, keys)
            return nets.policy(s, actor_params, keys)

        def critic(s, a):  # [K, R]
            return nets.critic(s, a, value_params, keys)

        target, var, weights = VF.value_expansion_target(
            next_obs, reward, terminated, policy=policy, critic=critic,
            **world_model_calls(wm, sample), num_members=N, horizon=H, gamma=self.gamma,
            mix=self.mix, alpha=alpha, eps=self.variance_eps, temperature=nets.temperature() if nets.stochastic else None,
        )  # fmt: skip

        diagnostics = TensorDict(
            {
                keys.alpha: alpha.expand(M).reshape(*batch_shape, 1),
                keys.horizon_variance: var.reshape(*batch_shape, H + 1),
                keys.horizon_weights: weights.reshape(*batch_shape, H + 1),
            },
            batch_size=batch_shape,
        )
        tensordict.update(diagnostics)
        # Losses that pass a shallow copy (TD3Loss) drop what we write; keep the last ones here.
        self.__dict__["diagnostics"] = diagnostics
        return target.reshape(*batch_shape, 1)

    def diagnostic_scalars(self) -> dict[str, torch.Tensor]:
        """The last target's diagnostics as scalars (batch means) a script can log as it
        logs a loss's outputs: ``<prefix>_alpha``, and one entry per horizon for the
        weights and the candidate variances (``<prefix>_horizon_weights_h<H>``,
        ``<prefix>_horizon_variance_h<H>``). Empty before the first target.

        Examples:
            >>> from torchrl.modules import MLP, Actor, ValueOperator
            >>> wm = WorldModelEnsemble(3, 1, num_models=2, transition_cells=8,
            ...                         reward_cells=8, termination_cells=8)
            >>> est = STEVEEstimator(
            ...     world_model=wm, actor_network=Actor(MLP(in_features=3, out_features=1)),
            ...     value_network=ValueOperator(MLP(in_features=4, out_features=1),
            ...                                 in_keys=["observation", "action"]),
            ...     gamma=0.9, horizon=1)
            >>> est.diagnostic_scalars()
            {}
        """
        scalars = {}
        if self.diagnostics is None:
            return scalars
        for key, value in self.diagnostics.items():
            mean = value.detach().reshape(-1, value.shape[-1]).mean(0)
            if mean.numel() == 1:
                scalars[key] = mean.squeeze(-1)
            else:
                for H, entry in enumerate(mean.unbind(0)):
                    scalars[f"{key}_h{H}"] = entry
        return scalars

    def forward(
        self,
        tensordict: TensorDictBase,
        *,
        params: TensorDictBase | None = None,
        target_params: TensorDictBase | None = None,
    ) -> TensorDictBase:
        """Writes the target under ``value_target`` (and ``advantage = target - value``
        when the batch already holds the critic's ``value``)."""
        target = self.value_estimate(tensordict, target_params=target_params)
        k = self.tensor_keys
        tensordict.set(k.value_target, target)
        value = tensordict.get(k.value, None)
        if value is not None:
            tensordict.set(k.advantage, target - value)
        return tensordict

    def extra_repr(self) -> str:
        return (
            f"horizon={self.horizon}, rollout={self.rollout!r}, mix={self.mix!r}, "
            f"alpha={float(self.alpha)}, alpha_mode={self.alpha_mode!r}"
        )


class MVEEstimator(ValueExpansionEstimator):
    """MVE (paper eq. 5): the ensemble-mean ``H``-step expansion of deterministic (mean) rollouts.

    ``horizon`` is the fixed expansion length ``H``. Same keyword arguments as
    :class:`ValueExpansionEstimator` (``world_model``, ``actor_network``,
    ``value_network`` and ``gamma`` required) except ``rollout``, ``mix`` and ``alpha``.
    """

    _AcceptedKeys = _accepted_keys("mve")
    default_keys = _AcceptedKeys

    def __init__(
        self,
        *,
        world_model: WorldModelEnsemble,
        actor_network: TensorDictModuleBase,
        value_network: TensorDictModuleBase,
        gamma: float,
        horizon: int = 3,
        **kwargs,
    ) -> None:
        super().__init__(
            world_model=world_model, actor_network=actor_network, value_network=value_network,
            gamma=gamma, horizon=horizon, rollout="mean", mix="fixed", alpha=0.0, **kwargs,
        )  # fmt: skip


class STEVEEstimator(ValueExpansionEstimator):
    """STEVE (paper eq. 6): inverse-variance mix of ``H = 0..H_max`` over mean rollouts.

    Same keyword arguments as :class:`ValueExpansionEstimator` (``world_model``,
    ``actor_network``, ``value_network`` and ``gamma`` required) except ``rollout``,
    ``mix`` and ``alpha``.
    """

    _AcceptedKeys = _accepted_keys("steve")
    default_keys = _AcceptedKeys

    def __init__(
        self,
        *,
        world_model: WorldModelEnsemble,
        actor_network: TensorDictModuleBase,
        value_network: TensorDictModuleBase,
        gamma: float,
        horizon: int = 3,
        **kwargs,
    ) -> None:
        super().__init__(
            world_model=world_model, actor_network=actor_network, value_network=value_network,
            gamma=gamma, horizon=horizon, rollout="mean", mix="inverse_variance", alpha=0.0,
            **kwargs,
        )  # fmt: skip


class RAVEValueEstimator(ValueExpansionEstimator):
    """RAVE (paper eq. 11-12): inverse-variance mix of ``alpha``-confidence lower bounds
    over sampled (DVE) rollouts of the probabilistic ensemble.

    By default ``alpha`` is adaptive (eq. 12: ``alpha(s, a) = max(0, alpha (1 - err / Z))``,
    paper values ``alpha = 1.5``, ``Z = 1``); ``alpha_mode="constant"`` keeps it constant
    (the paper's ablation uses 0, 0.5 and 2.0). ``alpha = 0`` is "STEVE on a probabilistic
    ensemble".

    Keyword Args:
        world_model (WorldModelEnsemble): as for :class:`ValueExpansionEstimator`.
        actor_network (TensorDictModuleBase): as for :class:`ValueExpansionEstimator`
            (:meth:`~ValueExpansionEstimator.for_loss` takes the networks from a loss).
        value_network (TensorDictModuleBase): as for :class:`ValueExpansionEstimator`.
        gamma (float): the discount.
        horizon (int): ``H_max``. Defaults to 3.
        alpha (float): the constant ``alpha``. Defaults to 1.5.
        alpha_mode (str): ``"adaptive"`` (eq. 12, the default), ``"constant"``, or
            ``"tensordict"`` (read the :class:`~torchrl_rave.transforms.AdaptiveAlpha`
            transform's output from the batch).
        **kwargs: see :class:`ValueExpansionEstimator`.
    """

    _AcceptedKeys = _accepted_keys("rave")
    default_keys = _AcceptedKeys

    def __init__(
        self,
        *,
        world_model: WorldModelEnsemble,
        actor_network: TensorDictModuleBase,
        value_network: TensorDictModuleBase,
        gamma: float,
        horizon: int = 3,
        alpha: float = 1.5,
        alpha_mode: AlphaMode = "adaptive",
        **kwargs,
    ) -> None:
        super().__init__(
            world_model=world_model,
            actor_network=actor_network,
            value_network=value_network,
            gamma=gamma,
            horizon=horizon,
            rollout="sample",
            mix="inverse_variance",
            alpha=alpha,
            alpha_mode=alpha_mode,
            **kwargs,
        )


_BY_NAME = {
    "mve": MVEEstimator,
    "steve": STEVEEstimator,
    "rave": RAVEValueEstimator,
}


def make_value_expansion_estimator(name: str, loss_module, **kwargs) -> ValueExpansionEstimator:
    """Picks an estimator by name (``"mve"``, ``"steve"``, ``"rave"``) and wires it to a loss.

    Examples:
        >>> make_value_expansion_estimator("dqn", None)
        Traceback (most recent call last):
        ...
        ValueError: unknown value-expansion estimator 'dqn'; choose one of ['mve', 'steve', 'rave']
    """
    cls = _BY_NAME.get(str(name).lower())
    if cls is None:
        raise ValueError(
            f"unknown value-expansion estimator {name!r}; choose one of {list(_BY_NAME)}"
        )
    return cls.for_loss(loss_module, **kwargs)
