"""DDPG on an ensemble of K critics: the base learner of STEVE and RAVE."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictParams, dispatch
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule, ValueEstimators
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value import TD0Estimator, TD1Estimator, TDLambdaEstimator

from torchrl_rave._checks import (
    check_finite_losses,
    check_not_empty,
    check_positive_int,
    check_transition_layout,
    first_param_dtype,
    get_checked,
)
from torchrl_rave.modules.tensor_call import PlannedCalls
from torchrl_rave.objectives.value_expansion import ValueExpansionEstimator

__all__ = ["EnsembleDDPGLoss"]

_TORCHRL_TD = (TD0Estimator, TD1Estimator, TDLambdaEstimator)

_PARAMS = (
    "actor_network_params",
    "value_network_params",
    "target_actor_network_params",
    "target_value_network_params",
)


class EnsembleDDPGLoss(LossModule):
    """DDPG with ``K`` critics trained on one shared target; the actor ascends their mean.

    STEVE and RAVE build on DDPG with a critic ensemble (paper: ``K = 4``): every critic
    regresses onto the same target and the deterministic policy follows the ensemble's
    mean Q. The constructor, attributes and outputs are :class:`~torchrl.objectives.DDPGLoss`'s
    (``value_network``, ``delay_value``, ``value_network_params``, ``loss_value``,
    ``loss_actor``, ``loss_value(td)`` / ``loss_actor(td)``), so a DDPG script swaps the
    class name and adds ``num_value_nets``. The ``K`` critics are one module's parameters
    stacked along a leading dimension, each member initialised independently.

    The target comes from the loss's value estimator: install
    :class:`~torchrl_rave.objectives.RAVEValueEstimator` (or STEVE / MVE) with
    ``loss.make_value_estimator(RAVEValueEstimator.for_loss(loss, world_model=wm, gamma=g))``.
    The default TD(0) estimator bootstraps from the minimum over the target critics at the
    target policy's action, which for ``K = 1`` is plain DDPG.

    Args:
        actor_network (TensorDictModule): deterministic policy (e.g. :class:`~torchrl.modules.Actor`).
        value_network (TensorDictModule): one critic ``(observation, action) -> state_action_value``;
            it is copied into ``num_value_nets`` independently initialised members.

    Keyword Args:
        num_value_nets (int): ``K``. Defaults to 4 (paper).
        loss_function (str): distance of the critic regression. Defaults to ``"l2"``.
        delay_actor (bool): keep target actor parameters. Defaults to ``True``, unlike
            ``DDPGLoss``: STEVE and RAVE roll out the *target* policy (paper eq. 8).
        delay_value (bool): keep target critic parameters. Defaults to ``True``.
        fast_calls (bool): evaluate the actor and the K critics through
            :class:`~torchrl_rave.modules.TensorCall` (direct matmuls, one batched matmul per
            layer for all critics) when their structure allows it, instead of TensorDict
            calls through ``torch.vmap``. Same numbers either way. Defaults to ``True``.
        check_inputs (bool): with a TD estimator, refuse NaN/inf in the batch and input
            widths the actor or critics cannot take, naming the entries (one device sync
            per call; a value-expansion estimator checks its inputs itself, under its own
            ``check_inputs``). Defaults to ``True``.
        reduction (str, optional): ``"mean"`` (default), ``"sum"`` or ``"none"``.
        use_prioritized_weights (str or bool): as in TorchRL's losses. Defaults to ``"auto"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> from torchrl.modules import MLP, Actor, ValueOperator
        >>> spec = Bounded(-1.0, 1.0, shape=(2,))
        >>> actor = Actor(torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Tanh()), spec=spec)
        >>> critic = ValueOperator(MLP(in_features=5, out_features=1, num_cells=[8]),
        ...                        in_keys=["observation", "action"])
        >>> loss = EnsembleDDPGLoss(actor, critic, num_value_nets=4)
        >>> batch = TensorDict({"observation": torch.randn(6, 3), "action": torch.rand(6, 2),
        ...     ("next", "observation"): torch.randn(6, 3), ("next", "reward"): torch.randn(6, 1),
        ...     ("next", "done"): torch.zeros(6, 1, dtype=torch.bool),
        ...     ("next", "terminated"): torch.zeros(6, 1, dtype=torch.bool)}, [6])
        >>> out = loss(batch)
        >>> out["loss_value"].shape, out["pred_value"].shape, out["state_action_value_actor"].shape
        (torch.Size([]), torch.Size([4, 6]), torch.Size([4, 6]))
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (``set_keys``), as in ``DDPGLoss`` plus ``action``.

        Attributes:
            state_action_value (NestedKey): the critics' output. Defaults to ``"state_action_value"``.
            action (NestedKey): the action entry. Defaults to ``"action"``.
            priority (NestedKey): where the TD error is written. Defaults to ``"td_error"``.
            reward (NestedKey): reward, under ``"next"``. Defaults to ``"reward"``.
            done (NestedKey): done flag, under ``"next"``. Defaults to ``"done"``.
            terminated (NestedKey): termination flag, under ``"next"``. Defaults to ``"terminated"``.
            priority_weight (NestedKey): importance weights. Defaults to ``"priority_weight"``.
        """

        state_action_value: NestedKey = "state_action_value"
        action: NestedKey = "action"
        priority: NestedKey = "td_error"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        priority_weight: NestedKey = "priority_weight"

    default_keys = _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0
    out_keys = [
        "loss_actor",
        "loss_value",
        "pred_value",
        "target_value",
        "pred_value_max",
        "target_value_max",
        "state_action_value_actor",
    ]

    actor_network: TensorDictModule
    value_network: TensorDictModule
    actor_network_params: TensorDictParams
    value_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    target_value_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: TensorDictModule,
        value_network: TensorDictModule,
        *,
        num_value_nets: int = 4,
        loss_function: str = "l2",
        delay_actor: bool = True,
        delay_value: bool = True,
        fast_calls: bool = True,
        check_inputs: bool = True,
        reduction: str | None = None,
        use_prioritized_weights: str | bool = "auto",
    ) -> None:
        check_positive_int("num_value_nets", num_value_nets)
        super().__init__()
        self.use_prioritized_weights = use_prioritized_weights
        self.delay_actor = delay_actor
        self.delay_value = delay_value
        self.convert_to_functional(actor_network, "actor_network", create_target_params=delay_actor)
        self.convert_to_functional(
            value_network, "value_network", num_value_nets, create_target_params=delay_value
        )
        self.num_value_nets = num_value_nets
        self.loss_function = loss_function
        self.reduction = reduction or "mean"
        self.__dict__["_calls"] = PlannedCalls(fast_calls)
        self.check_inputs = check_inputs
        self._in_keys = None

    # --------------------------------------------------------------------- keys
    def _forward_value_estimator_keys(self, **kwargs) -> None:
        if self._value_estimator is not None:
            self._value_estimator.set_keys(
                value=self.tensor_keys.state_action_value,
                reward=self.tensor_keys.reward,
                done=self.tensor_keys.done,
                terminated=self.tensor_keys.terminated,
            )
        self._in_keys = None

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            k = self.tensor_keys
            keys = {
                k.action,
                ("next", k.reward),
                ("next", k.done),
                ("next", k.terminated),
                *self.actor_network.in_keys,
                *[("next", key) for key in self.actor_network.in_keys],
                *self.value_network.in_keys,
            }
            self._in_keys = sorted(keys, key=str)
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values) -> None:
        self._in_keys = values

    # ----------------------------------------------------------- network calls
    @property
    def fast_calls(self) -> bool:
        return self._calls.enabled

    @fast_calls.setter
    def fast_calls(self, value: bool) -> None:
        self._calls.enabled = value

    def _actions(self, source, params) -> torch.Tensor:
        """The actor's action ``[*B, A]`` for the inputs ``source(key)`` under ``params``."""
        inputs = {k: source(k) for k in self.actor_network.in_keys}
        return self._calls.actions(self.actor_network, params, inputs, self.tensor_keys.action)

    def _values(self, source, action: torch.Tensor, params, detach: bool = False) -> torch.Tensor:
        """``[K, *B]`` values of the K critics (stacked ``params``, detached with
        ``detach``) at ``action``."""
        keys = self.tensor_keys
        inputs = {k: action if k == keys.action else source(k) for k in self.value_network.in_keys}
        return self._calls.values(self.value_network, params, inputs, keys.state_action_value,
                                  detach=detach, randomness=self.vmap_randomness)  # fmt: skip

    def _value_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        return [
            *self.value_network.in_keys,
            ("next", keys.reward),
            ("next", keys.done),
            *[("next", k) for k in self.actor_network.in_keys],
        ]

    def _check_batch(self, tensordict: TensorDictBase, keys) -> None:
        """Names an empty batch, or a missing entry or wrong dtype among ``keys``, before
        any network runs. A value-expansion estimator checks the widths (and, computing
        its target, the values); otherwise, with ``check_inputs``, so does this."""
        check_not_empty(tensordict, type(self).__name__)
        dtype = first_param_dtype(self.actor_network_params)
        expanding = isinstance(self.value_estimator, ValueExpansionEstimator)
        finite = self.check_inputs and not expanding
        flags = {("next", self.tensor_keys.done), ("next", self.tensor_keys.terminated)}
        for key in keys:  # observations, actions and rewards: never integers
            floating = key not in flags
            get_checked(tensordict, key, check_finite=finite, dtype=dtype, floating=floating)
        if expanding:
            self.value_estimator.check_batch(tensordict)
        elif self.check_inputs:
            self._check_widths(tensordict, keys)
            check_transition_layout(tensordict, ("next", self.tensor_keys.reward), list(flags))

    def _check_widths(self, tensordict: TensorDictBase, keys) -> None:
        """The actor's inputs among ``keys`` (now and ``next``) and the critics' add up
        to the width of each network's first linear layer."""
        actor_in = list(self.actor_network.in_keys)
        checks = [
            ("actor", self.actor_network, actor_in),
            ("actor", self.actor_network, [_under_next(k) for k in actor_in]),
            ("critic", self.value_network, list(self.value_network.in_keys)),
        ]
        for name, net, inputs in checks:
            width = _input_width(net)
            if width is None or not all(k in keys for k in inputs):
                continue
            widths = {k: tensordict.get(k).shape[-1] for k in inputs}
            if sum(widths.values()) != width:
                given = ", ".join(f"{k!r} of width {w}" for k, w in widths.items())
                raise ValueError(
                    f"the {name} takes {width} input features, but the batch gives {given}"
                )

    # ------------------------------------------------------------------ losses
    def loss_actor(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """``-mean_k Q_k(s, pi(s))``; the critics' weights are detached, so only the actor moves."""
        self._check_batch(tensordict, self.actor_network.in_keys)
        return self._loss_actor(tensordict)

    def _loss_actor(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        weights = self._maybe_get_priority_weight(tensordict)
        action = self._actions(tensordict.get, self.actor_network_params)
        q = self._values(tensordict.get, action, self.value_network_params, detach=True)
        loss = self._reduce_loss(-q.mean(0), tensordict=tensordict, weights=weights)
        return loss, {"state_action_value_actor": q.detach()}

    def loss_value(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """Every critic regresses onto the estimator's target; the sum over critics is reduced."""
        self._check_batch(tensordict, self._value_keys())
        return self._loss_value(tensordict)

    def _loss_value(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        keys = self.tensor_keys
        weights = self._maybe_get_priority_weight(tensordict)
        estimator = self.value_estimator
        if isinstance(estimator, ValueExpansionEstimator):
            # it writes its diagnostics into the batch it gets: a shallow copy keeps the
            # caller's batch as it was
            tensordict = tensordict.clone(False)
            target = estimator.value_estimate(tensordict)
        else:
            # TD(0)/TD(lambda) bootstrap from the next state's value: the minimum over the
            # target critics at the target policy's action (one critic: plain DDPG).
            with torch.no_grad():

                def next_entry(k):
                    return tensordict.get(("next", k))

                next_action = self._actions(next_entry, self.target_actor_network_params)
                next_q = self._values(next_entry, next_action, self.target_value_network_params)
                next_value = next_q.min(0)[0].unsqueeze(-1)
            if isinstance(estimator, _TORCHRL_TD) and not estimator.average_rewards:
                # TorchRL's estimators take the next value directly (and then leave the
                # batch alone)
                target = estimator.value_estimate(tensordict, next_value=next_value)
            else:
                # any other estimator reads it from (a shallow copy of) the batch
                tensordict = tensordict.clone(False)
                tensordict.set(("next", keys.state_action_value), next_value)
                target = estimator.value_estimate(tensordict)
        target = target.squeeze(-1)
        current = self._values(
            tensordict.get, tensordict.get(keys.action), self.value_network_params
        )
        loss = distance_loss(current, target.expand_as(current), loss_function=self.loss_function)
        loss = self._reduce_loss(loss.sum(0), tensordict=tensordict, weights=weights)
        with torch.no_grad():
            td_error = (current - target).pow(2)
            metadata = {
                "td_error": td_error,
                "pred_value": current.detach(),
                "target_value": target,
                "pred_value_max": current.max(),
                "target_value_max": target.max(),
            }
        if isinstance(estimator, ValueExpansionEstimator):
            # the target's diagnostics as scalars (batch means), so that a script logging
            # the mean of every loss output logs each
            metadata.update(estimator.diagnostic_scalars())
        return loss, metadata

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Critic and actor losses; writes the critics' largest squared TD error under
        ``priority`` for prioritised replay."""
        self._check_batch(tensordict, [*self._value_keys(), *self.actor_network.in_keys])
        loss_value, metadata = self._loss_value(tensordict)
        loss_actor, metadata_actor = self._loss_actor(tensordict)
        if self.check_inputs:
            check_finite_losses(
                type(self).__name__, {"loss_value": loss_value, "loss_actor": loss_actor},
                tensordict, [*self._value_keys(), *self.actor_network.in_keys],
            )  # fmt: skip
        tensordict.set(self.tensor_keys.priority, metadata.pop("td_error").max(0)[0])
        out = TensorDict(
            {"loss_actor": loss_actor, "loss_value": loss_value, **metadata, **metadata_actor}
        )
        self._clear_weakrefs(tensordict, out, *_PARAMS)
        return out

    def make_value_estimator(self, value_type: ValueEstimators = None, **hyperparams):
        """TD(0), TD(1) or TD(lambda) on the batch's ``("next", state_action_value)``
        (see :meth:`loss_value`), or an estimator instance such as
        :class:`~torchrl_rave.objectives.RAVEValueEstimator`."""
        from torchrl.objectives.utils import dispatch_value_estimator

        value_type, hp = self._prepare_value_estimator_kwargs(value_type, **hyperparams)
        if value_type is None:
            return self
        dispatch_value_estimator(
            self,
            value_type,
            supported=(ValueEstimators.TD0, ValueEstimators.TD1, ValueEstimators.TDLambda),
            tensor_keys={
                "value": self.tensor_keys.state_action_value,
                "reward": self.tensor_keys.reward,
                "done": self.tensor_keys.done,
                "terminated": self.tensor_keys.terminated,
            },
            value_network=None,
            **hp,
        )
        return self


def _under_next(key: NestedKey) -> tuple[str, ...]:
    return ("next", *key) if isinstance(key, tuple) else ("next", key)


def _input_width(module: torch.nn.Module) -> int | None:
    """``in_features`` of a module's first linear layer (``None`` without one)."""
    for layer in module.modules():
        if isinstance(layer, torch.nn.Linear):
            return layer.in_features
        if isinstance(layer, torch.nn.LazyLinear):
            return None
    return None
