"""The target actor and target critics a value-expansion estimator evaluates."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import CQLLoss, CrossQLoss, DiscreteSACLoss, REDQLoss, SACLoss
from torchrl.objectives.sac import compute_rsample_log_prob

from torchrl_rave.modules.tensor_call import PlannedCalls, TensorCall

__all__ = ["TargetNetworks"]


#: why a loss with an entropy temperature cannot take a value-expansion target
_SOFT_REFUSALS = (
    (DiscreteSACLoss, "acts on a discrete action set: its target is an expectation over every "
     "action, and the world model takes continuous action vectors"),
    (CrossQLoss, "has no target critics: its target comes from the current critics in one "
     "batch-normalised call together with the batch itself, which separate calls on imagined "
     "states would change"),
    (CQLLoss, "is an offline loss: its conservative penalty and its max-Q and deterministic "
     "backups are not the soft target the estimators expand, and imagined rollouts would leave "
     "the dataset's support that the penalty guards"),
)  # fmt: skip

#: the losses whose soft TD(0) target the estimators expand: their policy's and temperature's
#: attributes (SACLoss samples the next action with its current actor, REDQLoss with its
#: target actor, the current one's detached copy unless ``delay_actor``)
_SOFT_LOSSES = ((SACLoss, "actor_network_params", "_alpha"),
                (REDQLoss, "target_actor_network_params", "alpha"))  # fmt: skip


class TargetNetworks:
    """Calls an actor and ``K`` critics on plain tensors with target parameters.

    The parameters are read at call time: from a loss (``TargetNetworks.of_loss``, which
    follows TorchRL's ``target_<name>_params`` so soft updates are seen without re-wiring),
    from explicit ``actor_params`` / ``value_params``, or, with neither, the modules' own.
    Critic parameters with a leading dimension are ``K`` stacked members (one batched
    matmul per layer through :class:`~torchrl_rave.modules.TensorCall`, or ``torch.vmap``
    when a module cannot be planned); plain parameters mean ``K = 1``.

    The actor is deterministic (``observation -> action``), or, with ``stochastic=True``,
    a TorchRL probabilistic actor (``get_dist``) such as SAC's: :meth:`sample` then draws a
    reparameterised action and its log-probability as ``SACLoss`` draws its next action,
    and :meth:`temperature` gives the entropy temperature.

    Args:
        actor_network (TensorDictModuleBase): ``observation -> action``, or a probabilistic
            actor with ``stochastic=True``.
        value_network (TensorDictModuleBase): ``(observation, action) -> value``.

    Keyword Args:
        actor_params (TensorDictBase, optional): fixed actor parameters to use.
        value_params (TensorDictBase, optional): fixed critic parameters to use, optionally
            stacked with a leading ensemble dimension ``K``.
        fast_calls (bool): plan the networks as tensor calls where possible. Defaults to ``True``.
        stochastic (bool): the actor is a probabilistic one. Defaults to ``False``.
        temperature (float or Tensor, optional): the entropy temperature of a stochastic
            actor built without a loss (``of_loss`` reads the loss's at call time).
    """

    def __init__(
        self,
        actor_network: TensorDictModuleBase,
        value_network: TensorDictModuleBase,
        *,
        actor_params: TensorDictBase | None = None,
        value_params: TensorDictBase | None = None,
        fast_calls: bool = True,
        stochastic: bool = False,
        temperature: float | torch.Tensor | None = None,
    ) -> None:
        if stochastic and not hasattr(actor_network, "get_dist"):
            raise ValueError(
                f"stochastic=True needs a probabilistic actor (with get_dist), got "
                f"{type(actor_network).__name__}"
            )
        if stochastic != (temperature is not None):
            raise ValueError("a stochastic actor needs temperature=, a deterministic one none")
        self.actor_network = actor_network
        self.value_network = value_network
        self.stochastic = stochastic
        self._fixed = (actor_params, value_params)
        self._temperature = temperature
        self._temperature_name: str | None = None
        self._loss = None
        self._loss_names: tuple[str, str] | None = None
        self.calls = PlannedCalls(fast_calls)

    @classmethod
    def of_loss(cls, loss_module, actor_network=None, fast_calls: bool = True) -> TargetNetworks:
        """The target actor and critics of a TorchRL loss: ``qvalue_network`` (stacked,
        ``TD3Loss``-style) or ``value_network`` (``DDPGLoss``, :class:`EnsembleDDPGLoss`).

        A loss with an entropy temperature bootstraps from the soft value
        ``Q'(s', a') - temperature * log pi(a' | s')`` with ``a'`` drawn from its policy:
        ``SACLoss`` (version 2, without a state-value network; the next action from its
        current actor, as it draws it) and ``REDQLoss`` (from its target actor) give a
        stochastic actor and their temperature, read at call time. ``DiscreteSACLoss``,
        ``CrossQLoss``, ``CQLLoss`` and a loss with both a ``qvalue_network`` and a
        ``value_network`` (``IQLLoss``, SAC version 1: they bootstrap from a state-value
        network) are refused, each with its reason.
        """
        name = type(loss_module).__name__
        for kind, reason in _SOFT_REFUSALS:
            if isinstance(loss_module, kind):
                raise ValueError(f"value-expansion estimators cannot expand {name}: it {reason}")

        def has(params: str) -> bool:  # SACLoss (v2) keeps value_network_params = None
            return getattr(loss_module, params, None) is not None

        if has("qvalue_network_params") and has("value_network_params"):
            raise ValueError(
                f"{name} bootstraps from a separate state-value network V(s') (it has both a "
                "qvalue_network and a value_network); value-expansion estimators bootstrap from "
                f"Q(s', a') and would replace that target. Use them with SACLoss (no "
                "value_network), torchrl_rave.EnsembleDDPGLoss or TD3Loss(num_qvalue_nets=K)."
            )
        soft = [(a, t) for kind, a, t in _SOFT_LOSSES if isinstance(loss_module, kind)]
        if hasattr(loss_module, "log_alpha") and not soft:
            raise ValueError(
                f"{name} has an entropy temperature (log_alpha) but is not a loss whose soft "
                "target the value-expansion estimators reproduce (SACLoss, REDQLoss)"
            )
        if getattr(loss_module, "gSDE", False):
            raise ValueError(f"{name} with gSDE: its actor draws with state-dependent noise "
                             "that imagined states do not carry; build it with gSDE=False")  # fmt: skip
        actor = (
            actor_network
            if actor_network is not None
            else getattr(loss_module, "actor_network", None)
        )
        if actor is None:
            raise ValueError(f"{name} has no actor_network; pass actor_network= explicitly")
        if "qvalue_network" in loss_module._modules or has("qvalue_network_params"):
            critic = "qvalue_network"
        elif has("value_network_params"):
            critic = "value_network"
        else:
            raise ValueError(f"{name} has neither a qvalue_network nor a value_network")
        actor_name, temperature = soft[0] if soft else ("target_actor_network_params", None)
        nets = cls(actor, getattr(loss_module, critic), fast_calls=fast_calls)
        nets.stochastic = bool(soft)
        nets._loss = loss_module
        nets._loss_names = (actor_name, f"target_{critic}_params")
        nets._temperature_name = temperature
        return nets

    def temperature(self) -> torch.Tensor | float:
        """A stochastic actor's entropy temperature now (a loss's, read at call time)."""
        if self._loss is not None:
            return getattr(self._loss, self._temperature_name)
        return self._temperature

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

    def sample(self, obs: torch.Tensor, params, keys) -> tuple[torch.Tensor, torch.Tensor]:
        """A stochastic actor's reparameterised actions ``[*B, A]`` and their
        log-probabilities ``[*B]`` for observations ``[*B, S]``, drawn as ``SACLoss`` draws
        its next action (``get_dist`` under random exploration, one ``rsample`` scored with
        its own log-probability)."""
        actor = self.actor_network
        planned = self.calls.gaussian_actor(actor)
        with set_exploration_type(ExplorationType.RANDOM):
            if planned is not None:  # the MLP as tensor calls, the distribution as built
                flat = obs.reshape(-1, obs.shape[-1])
                inputs = {keys.observation: flat}
                dist = TensorCall.gaussian_dist(planned, actor, params, inputs)
                action, log_prob = compute_rsample_log_prob(dist)
                return action.reshape(*obs.shape[:-1], -1), log_prob.reshape(obs.shape[:-1])
            td = TensorDict({keys.observation: obs}, batch_size=obs.shape[:-1])
            if params is None:
                return compute_rsample_log_prob(actor.get_dist(td))
            with params.to_module(actor, preserve_module_state=False):
                return compute_rsample_log_prob(actor.get_dist(td))

    def critic(self, obs: torch.Tensor, action: torch.Tensor, params, keys) -> torch.Tensor:
        """Critic values ``[K, *B]`` (``K = 1`` without stacked parameters)."""
        inputs = {keys.observation: obs, keys.action: action}
        return self.calls.values(self.value_network, params, inputs, keys.value)
