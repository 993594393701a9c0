"""The target actor and target critics a value-expansion estimator evaluates."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torchrl_rave.modules.tensor_call import PlannedCalls

__all__ = ["TargetNetworks"]


class TargetNetworks:
    """Calls a deterministic actor and ``K`` critics on plain tensors with target parameters.

    The parameters are read at call time: from a loss (``TargetNetworks.of_loss``, which
    follows TorchRL's ``target_<name>_params`` so soft updates are seen without re-wiring),
    from explicit ``actor_params`` / ``value_params``, or, with neither, the modules' own.
    Critic parameters with a leading dimension are ``K`` stacked members (one batched
    matmul per layer through :class:`~torchrl_rave.modules.TensorCall`, or ``torch.vmap``
    when a module cannot be planned); plain parameters mean ``K = 1``.

    Args:
        actor_network (TensorDictModuleBase): ``observation -> action``.
        value_network (TensorDictModuleBase): ``(observation, action) -> value``.

    Keyword Args:
        actor_params, value_params (TensorDictBase, optional): fixed parameters to use.
        fast_calls (bool): plan the networks as tensor calls where possible. Defaults to ``True``.
    """

    def __init__(
        self,
        actor_network: TensorDictModuleBase,
        value_network: TensorDictModuleBase,
        *,
        actor_params: TensorDictBase | None = None,
        value_params: TensorDictBase | None = None,
        fast_calls: bool = True,
    ) -> None:
        self.actor_network = actor_network
        self.value_network = value_network
        self._fixed = (actor_params, value_params)
        self._loss = None
        self._loss_names: tuple[str, str] | None = None
        self.calls = PlannedCalls(fast_calls)

    @classmethod
    def of_loss(cls, loss_module, actor_network=None, fast_calls: bool = True) -> TargetNetworks:
        """The target actor and critics of a TorchRL loss: ``qvalue_network`` (stacked,
        ``TD3Loss``-style) or ``value_network`` (``DDPGLoss``, :class:`EnsembleDDPGLoss`).

        A loss with an entropy temperature (``log_alpha``: ``SACLoss``, ``REDQLoss``,
        ``CQLLoss``, ``CrossQLoss``) is refused: it bootstraps from
        ``Q(s', a') - alpha log pi(a' | s')`` with ``a'`` sampled from its policy, and the
        estimators' targets, ``Q(s', pi(s'))`` of a deterministic actor, would drop that term.
        So is a loss with both a ``qvalue_network`` and a ``value_network`` (``IQLLoss``),
        which bootstraps from the state-value network.
        """
        if hasattr(loss_module, "log_alpha"):
            name = type(loss_module).__name__
            raise ValueError(
                f"{name} bootstraps from Q(s', a') - alpha log pi(a'|s') with a' sampled from "
                "its stochastic policy (it has an entropy temperature, log_alpha). "
                "Value-expansion estimators bootstrap from Q(s', pi(s')) of a deterministic "
                f"actor, so installed in {name} they would drop its entropy term. Use them "
                "with torchrl_rave.EnsembleDDPGLoss or TD3Loss(num_qvalue_nets=K)."
            )
        if hasattr(loss_module, "qvalue_network_params") and hasattr(
            loss_module, "value_network_params"
        ):
            name = type(loss_module).__name__
            raise ValueError(
                f"{name} bootstraps from a separate state-value network V(s') (it has both a "
                "qvalue_network and a value_network); value-expansion estimators bootstrap from "
                f"Q(s', pi(s')) and would replace that target. Use them with "
                "torchrl_rave.EnsembleDDPGLoss or TD3Loss(num_qvalue_nets=K)."
            )
        actor = (
            actor_network
            if actor_network is not None
            else getattr(loss_module, "actor_network", None)
        )
        if actor is None:
            raise ValueError(
                f"{type(loss_module).__name__} has no actor_network; pass actor_network= explicitly"
            )
        if "qvalue_network" in loss_module._modules or hasattr(
            loss_module, "qvalue_network_params"
        ):
            critic = "qvalue_network"
        elif hasattr(loss_module, "value_network_params"):
            critic = "value_network"
        else:
            raise ValueError(
                f"{type(loss_module).__name__} has neither a qvalue_network nor a value_network"
            )
        nets = cls(actor, getattr(loss_module, critic), fast_calls=fast_calls)
        nets._loss = loss_module
        nets._loss_names = ("target_actor_network_params", f"target_{critic}_params")
        return nets

    def params(self, target_params: TensorDictBase | None = None):
        """``(actor_params, value_params)`` for this call."""
        if target_params is not None and ("module", "0") in target_params.keys(True):
            # DDPGLoss passes its actor-critic target parameters in this layout.
            return target_params["module", "0"], target_params["module", "1"]
        if self._loss is not None:
            return tuple(getattr(self._loss, name) for name in self._loss_names)
        return self._fixed

    def wired_num_critics(self) -> int:
        """``K`` of the wired critics, read from the loss's online parameters (reading its
        target parameters before a target updater exists makes TorchRL warn)."""
        if self._loss is not None:
            return self.num_critics(getattr(self._loss, self._loss_names[1][len("target_") :]))
        return self.num_critics(self._fixed[1])

    def num_critics(self, value_params: TensorDictBase | None) -> int:
        if value_params is None or value_params.batch_dims == 0:
            return 1
        return value_params.batch_size[0]

    def policy(self, obs: torch.Tensor, params, keys) -> torch.Tensor:
        """Actions ``[*B, A]`` for observations ``[*B, S]``."""
        return self.calls.actions(self.actor_network, params, {keys.observation: obs}, keys.action)

    def critic(self, obs: torch.Tensor, action: torch.Tensor, params, keys) -> torch.Tensor:
        """Critic values ``[K, *B]`` (``K = 1`` without stacked parameters)."""
        inputs = {keys.observation: obs, keys.action: action}
        return self.calls.values(self.value_network, params, inputs, keys.value)
