"""DDPG on an ensemble of K critics: the base learner of STEVE and RAVE."""

from __future__ import annotations

import torch
from torchrl.objectives import TD3Loss
from torchrl.objectives.utils import distance_loss

from torchrl_rave.modules.tensor_call import TensorCall
from torchrl_rave.objectives.value_expansion import ValueExpansionEstimator


class EnsembleDDPGLoss(TD3Loss):
    """DDPG with ``K`` critics trained on one shared target; the actor ascends their mean.

    STEVE and RAVE build on DDPG with a critic ensemble (paper: ``K = 4``): every critic
    regresses onto the same value-expansion target, and the deterministic policy follows the
    ensemble's mean Q. This is :class:`~torchrl.objectives.TD3Loss` (which already holds K
    stacked critics, their targets and a vmapped forward) with two changes:

    - no target-policy smoothing noise (``policy_noise = noise_clip = 0``), and
    - the actor loss is ``-mean_k Q_k(s, pi(s))`` instead of TD3's ``-Q_0(s, pi(s))``.

    The target comes from the loss's value estimator: plug in
    :class:`~torchrl_rave.objectives.RAVEValueEstimator` (or STEVE / MVE). The default TD(0)
    estimator keeps TD3's minimum over the target critics, which for ``K = 1`` is plain DDPG.

    Args:
        actor_network: deterministic policy (e.g. :class:`~torchrl.modules.Actor`).
        qvalue_network: one critic; it is copied into ``num_qvalue_nets`` independent members.

    Keyword Args:
        num_qvalue_nets (int): ``K``. Defaults to 4 (paper).
        fast_calls (bool): evaluate the actor and the K critics through
            :class:`~torchrl_rave.modules.TensorCall` (direct matmuls, one batched matmul per
            layer for all critics) when their structure allows it, instead of TD3Loss's
            TensorDict + ``vmap`` path. Same numbers either way. With a value-expansion
            estimator the loss also skips TD3's next-state target, which that estimator
            does not read. Defaults to ``True``.
        **kwargs: the other keyword arguments of :class:`~torchrl.objectives.TD3Loss`
            (``action_spec``, ``loss_function``, ``delay_actor``, ``delay_qvalue`` ...).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> from torchrl.modules import MLP, Actor, ValueOperator
        >>> spec = Bounded(-1.0, 1.0, shape=(2,))
        >>> actor = Actor(torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Tanh()), spec=spec)
        >>> critic = ValueOperator(MLP(in_features=5, out_features=1, num_cells=[8]),
        ...                        in_keys=["observation", "action"])
        >>> loss = EnsembleDDPGLoss(actor, critic, action_spec=spec, num_qvalue_nets=4)
        >>> batch = TensorDict({"observation": torch.randn(6, 3), "action": torch.rand(6, 2),
        ...     ("next", "observation"): torch.randn(6, 3), ("next", "reward"): torch.randn(6, 1),
        ...     ("next", "done"): torch.zeros(6, 1, dtype=torch.bool),
        ...     ("next", "terminated"): torch.zeros(6, 1, dtype=torch.bool)}, [6])
        >>> out = loss(batch)
        >>> out["loss_actor"].shape, out["state_action_value_actor"].shape
        (torch.Size([]), torch.Size([4, 6]))
    """

    def __init__(
        self,
        actor_network,
        qvalue_network,
        *,
        num_qvalue_nets: int = 4,
        fast_calls: bool = True,
        **kwargs,
    ):
        for key in ("policy_noise", "noise_clip"):
            if key in kwargs:
                raise TypeError(f"EnsembleDDPGLoss takes no {key!r}: DDPG has no target smoothing")
        kwargs.setdefault("loss_function", "l2")
        super().__init__(
            actor_network,
            qvalue_network,
            num_qvalue_nets=num_qvalue_nets,
            policy_noise=0.0,
            noise_clip=0.0,
            **kwargs,
        )
        self.fast_calls = fast_calls
        self.__dict__["_tensor_calls"] = {}

    def _tensor_call(self, which: str) -> TensorCall | None:
        """Planned tensor-level calls of the actor and of the K stacked critics (cached)."""
        if which not in self._tensor_calls:
            if not self.fast_calls:
                call = None
            elif which == "actor":
                call = TensorCall.plan(self.actor_network)
            else:
                call = TensorCall.plan(self.qvalue_network, stacked=True)
            self._tensor_calls[which] = call
        return self._tensor_calls[which]

    def _fast(self) -> bool:
        return self._tensor_call("actor") is not None and self._tensor_call("critic") is not None

    def _actions(self, inputs, params) -> torch.Tensor:
        return self._tensor_call("actor")(params, inputs)[self.tensor_keys.action]

    def _q(self, inputs, params) -> torch.Tensor:
        """``[K, *B]`` values of the K critics with stacked ``params``."""
        out = self._tensor_call("critic")(params, inputs)[self.tensor_keys.state_action_value]
        return out.squeeze(-1)

    def _critic_inputs(self, source, action: torch.Tensor) -> dict:
        keys = self.tensor_keys
        return {k: action if k == keys.action else source(k) for k in self.qvalue_network.in_keys}

    def actor_loss(self, tensordict) -> tuple[torch.Tensor, dict]:
        if not self._fast():
            return self._actor_loss_tensordict(tensordict)
        weights = self._maybe_get_priority_weight(tensordict)
        actor_in = {k: tensordict.get(k) for k in self.actor_network.in_keys}
        action = self._actions(actor_in, self.actor_network_params)
        # the critics' weights are detached so this loss moves only the actor
        q = self._q(
            self._critic_inputs(tensordict.get, action), self._cached_detach_qvalue_network_params
        )
        loss = self._reduce_loss(-q.mean(0), tensordict=tensordict, weights=weights)
        return loss, {"state_action_value_actor": q.detach()}

    def value_loss(self, tensordict) -> tuple[torch.Tensor, dict]:
        if not self._fast():
            return super().value_loss(tensordict)
        weights = self._maybe_get_priority_weight(tensordict)
        tensordict = tensordict.clone(False)
        keys = self.tensor_keys
        next_value = None
        if not isinstance(self.value_estimator, ValueExpansionEstimator):
            # TD(0)/TD(lambda) read the next state's value from the batch: the minimum over
            # the target critics at the target policy's action (one critic: plain DDPG).
            with torch.no_grad():

                def next_entry(k):
                    return tensordict.get(("next", k))

                actor_in = {k: next_entry(k) for k in self.actor_network.in_keys}
                next_action = self._actions(actor_in, self.target_actor_network_params)
                next_q = self._q(
                    self._critic_inputs(next_entry, next_action),
                    self.target_qvalue_network_params,
                )
                next_value = next_q.min(0)[0]
            tensordict.set(("next", keys.state_action_value), next_value.unsqueeze(-1))
        current = self._q(
            self._critic_inputs(tensordict.get, tensordict.get(keys.action)),
            self.qvalue_network_params,
        )
        target = self.value_estimator.value_estimate(tensordict).squeeze(-1)
        loss = distance_loss(current, target.expand_as(current), loss_function=self.loss_function)
        loss = self._reduce_loss(loss.sum(0), tensordict=tensordict, weights=weights)
        metadata = {
            "td_error": (current - target).pow(2).detach(),
            "pred_value": current.detach(),
            "target_value": target.detach(),
        }
        if next_value is not None:
            metadata["next_state_value"] = next_value
        return loss, metadata

    def _actor_loss_tensordict(self, tensordict) -> tuple[torch.Tensor, dict]:
        weights = self._maybe_get_priority_weight(tensordict)
        actor_in = tensordict.select(*self.actor_network.in_keys, strict=False)
        with self.actor_network_params.to_module(self.actor_network, preserve_module_state=False):
            actor_out = self.actor_network(actor_in)
        # One (s, pi(s)) batch per critic; the critics' weights are detached so this loss
        # moves only the actor.
        critic_in = actor_out.select(*self.qvalue_network.in_keys, strict=False).expand(
            self.num_qvalue_nets, *actor_out.batch_size
        )
        q = self._vmap_qvalue_network00(critic_in, self._cached_detach_qvalue_network_params)
        q = q.get(self.tensor_keys.state_action_value).squeeze(-1)
        loss = self._reduce_loss(-q.mean(0), tensordict=tensordict, weights=weights)
        self._clear_weakrefs(
            tensordict,
            "actor_network_params",
            "qvalue_network_params",
            "target_actor_network_params",
            "target_qvalue_network_params",
        )
        return loss, {"state_action_value_actor": q.detach()}
