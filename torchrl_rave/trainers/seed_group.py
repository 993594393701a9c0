"""Many independent learners updated as one: the seed as a batch dimension of every call.

:class:`SeedGroup` takes ``S`` fully built learners and moves every parameter, target
parameter and normaliser statistic of all of them into one tensor per leaf, with the seed
as a dimension of its own. The learners are of one kind:

- ``ddpg``, ``mve``, ``steve``, ``rave`` and ``rave_constant``: an
  :class:`~torchrl_rave.objectives.EnsembleDDPGLoss` with its target estimator and, for
  the model-based ones, a :class:`~torchrl_rave.objectives.WorldModelEnsembleLoss`;
- ``td3``: TorchRL's ``TD3Loss``;
- ``sac``: TorchRL's ``SACLoss`` (v2, no value network).

The fused leaves are laid out as follows:

==================  ================================  ===================================
network             one learner's leaf                the group's leaf
==================  ================================  ===================================
actor               ``[out, in]``                     ``[S, out, in]``
K critics           ``[K, out, in]``                  ``[S, K, out, in]``
world model         ``[N, in, out]``                  ``[S, N, in, out]``
normalisers         ``[F]``                           ``[S, F]``
==================  ================================  ===================================

Each learner's own leaves become views of its slice, so its modules (the policy a collector
runs, the evaluation actor, ``state_dict`` and checkpoints) keep working on the group's
current weights, unchanged. An update then evaluates each network once for all seeds: the
seed leads the weights and every activation (``[S, *members, rows, features]``), and the
``S x members`` pairs are the batch of one ``baddbmm`` per layer, so seed ``s``'s rows only
meet seed ``s``'s weights and the number of kernel calls does not depend on ``S``. Losses are summed over seeds after their per-seed reductions, so one
backward gives each seed exactly its own gradient, and Adam and the soft target update act
element-wise.

Random draws. With :class:`SeedStreams` (``streams=``, as the recipe builds every group),
each seed draws from its own stream: every random draw of an update (the world model's
bootstrap indices and sampled rollouts, TD3's target smoothing, SAC's actions) is made seed
by seed, each under its seed's generator state, with the shape and in the order its single
learner draws it. A seed's draws then do not depend on which other seeds share the group,
and a seed of any group draws exactly what a single run of that seed draws. These draws are
the one part of an update whose kernel calls grow with ``S`` (one per seed per draw, a few
per update); the network evaluations stay one call each. Without ``streams`` each draw is
one call for the whole group from the process's generator: a group of one still draws what
its single learner draws, seeds of a larger group draw independently of each other, but
not what they would draw alone.

This is the hand-folded form of ``torch.func.vmap`` over the update: ``vmap`` over TorchRL's
loss does not carry gradients through ``TensorDictParams`` and was slower than separate
updates on this workload (``benchmarks/README.md``, the seed-group section). TorchRL's
``TD3Loss`` run unchanged on networks whose layers hold every seed's weights gives each
seed its own losses, at 1.28x this group's time per update at S = 1 and 1.11x at S = 5 at
``preset=mujoco`` sizes (``benchmarks/seed_group.py --library-losses``); ``SACLoss``
cannot take a temperature per seed.
"""

from __future__ import annotations

import copy
import functools
import types
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch.distributions.utils import _sum_rightmost
from torchrl.objectives import SACLoss, TD3Loss
from torchrl.objectives.value import TD0Estimator

from torchrl_rave.modules.tensor_call import TensorCall, _leaf
from torchrl_rave.objectives import functional as VF
from torchrl_rave.objectives.ensemble_ddpg import EnsembleDDPGLoss
from torchrl_rave.objectives.value_expansion import ValueExpansionEstimator, world_model_calls
from torchrl_rave.objectives.world_model_loss import WorldModelEnsembleLoss
from torchrl_rave.trainers.agent_update import agent_update, critic_first_update, total_loss
from torchrl_rave.trainers.seed_streams import SeedStreams, _randn_like

__all__ = ["SeedGroup", "SeedStreams"]

Tensor = torch.Tensor


# (group parameter, the learners' leaves it holds) for every fused parameter, so that
# optimiser states can move between the group and the learners
_Members = list[tuple[torch.nn.Parameter, list[Tensor]]]


def _fuse(
    leaves: Sequence[Tensor], dim: int, parameter: bool, members: _Members | None = None
) -> Tensor:
    """One tensor holding ``leaves`` stacked along ``dim``; each leaf's storage is then
    replaced by a view of its slice (``leaf.data = group.select(dim, s)``), so whatever
    holds the leaf reads (and writes) the group's numbers. A parameter is listed in
    ``members`` with its learners' leaves."""
    group = torch.stack([leaf.detach() for leaf in leaves], dim).contiguous()
    if parameter:
        group = torch.nn.Parameter(group)
        if members is not None:
            members.append((group, list(leaves)))
    for s, leaf in enumerate(leaves):
        leaf.data = group.detach().select(dim, s)
    return group


def _same(name: str, values: Sequence) -> object:
    first = values[0]
    for v in values[1:]:
        if v != first:
            raise ValueError(f"the learners of a seed group must share {name}; got {list(values)}")
    return first


def _stacked_params(plan: TensorCall, params: Sequence[TensorDictBase], members: _Members) -> dict:
    """The leaves of a planned TorchRL MLP (one ``"mlp"`` step, optionally followed by a
    ``"tanh"`` step), each learner's ``params`` fused along the seed, by dotted key: what
    :class:`~torchrl_rave.modules.TensorCall` runs with ``seeds=True``."""
    kinds = [step[0] for step in plan.steps]
    if kinds not in (["mlp"], ["mlp", "tanh"]):
        raise ValueError(f"a seed group runs plain MLP networks, got the planned steps {kinds}")
    out = {}
    for is_linear, _, *keys in plan.steps[0][3]:
        for key in keys if is_linear else ():
            if key is not None:
                leaves = [_leaf(p, *key) for p in params]
                out[key[1]] = _fuse(leaves, 0, isinstance(leaves[0], torch.nn.Parameter), members)
    return out


def _sac_actor_plan(loss) -> tuple:
    """The SAC actor planned (:meth:`~torchrl_rave.modules.TensorCall.plan_gaussian_actor`):
    its MLP as tensor calls keyed as in the loss's ``actor_network_params``, its extractor
    and its distribution module, which the group applies itself."""
    planned = TensorCall.plan_gaussian_actor(loss.actor_network)
    if planned is None:
        raise ValueError(
            "a seed group's SAC actor is a ProbabilisticActor over "
            "TensorDictModule(Sequential(<MLP>, NormalParamExtractor)), as the recipe builds it"
        )
    return planned


def _stacked(modules: Sequence[torch.nn.Module], members: _Members) -> torch.nn.Module:
    """A copy of ``modules[0]`` whose every parameter and buffer is the modules' leaves
    fused along a new leading seed dimension (:func:`_fuse`: each module's own leaves
    become views of their slice). The ensemble modules evaluate such stacked parameters
    for all seeds at once (``modules.ensemble``, stacked seeds)."""
    _same(
        "world-model shapes", [[tuple(t.shape) for t in m.state_dict().values()] for m in modules]
    )
    stacked = copy.deepcopy(modules[0])
    for name, _ in list(stacked.named_parameters()):
        owner, _, leaf = name.rpartition(".")
        fused = _fuse([m.get_parameter(name) for m in modules], 0, True, members)
        setattr(stacked.get_submodule(owner), leaf, fused)
    for name, _ in list(stacked.named_buffers()):
        owner, _, leaf = name.rpartition(".")
        fused = _fuse([m.get_buffer(name) for m in modules], 0, False)
        stacked.get_submodule(owner)._buffers[leaf] = fused
    return stacked


def _gaussian_draw(streams: SeedStreams | None) -> Callable[[Tensor, Tensor, bool], Tensor]:
    """The world model's draw (``modules.world_model._draw``) for outputs with the seed
    leading."""

    def draw(mean: Tensor, logvar: Tensor, sample: bool) -> Tensor:
        if not sample:
            return mean
        return mean + _randn_like(mean, streams) * (0.5 * logvar).exp()

    return draw


class SeedGroup:
    """``S`` independent DDPG-family learners, each network call batched across seeds.

    Args:
        losses (Sequence[LossModule]): one loss per seed, all ``EnsembleDDPGLoss``, all
            ``TD3Loss`` or all ``SACLoss``, with the same networks' shapes, the same value
            estimator type and hyperparameters (TD(0), or MVE, STEVE or RAVE wired with
            ``for_loss``), and plain TorchRL MLP actors and critics (the deterministic actor
            ending in a ``TanhModule``, SAC's the recipe's tanh-Gaussian).

    Keyword Args:
        lr_actor (float): the actor's Adam learning rate.
        lr_critic (float): the critics' Adam learning rate.
        tau (float): the soft target update's ``tau`` (targets move ``tau`` of the way).
        world_model_losses (Sequence[WorldModelEnsembleLoss], optional): one per seed, for
            a value-expansion estimator (each on its loss's world model).
        lr_world_model (float, optional): the world models' Adam learning rate.
        streams (SeedStreams, optional): each seed's random stream; every default draw
            below is then made seed by seed under it (see the module's docstring).
            Without it each draw is one call for the group from the process's generator.
        draw (Callable, optional): ``(mean, logvar, sample) -> tensor``, the world model's
            Gaussian draw (tests pass one that replays known noise). Defaults to
            ``randn`` noise.
        bootstrap_indices (Callable, optional): ``(B, S) -> [N, S, B]`` resample indices of
            the world-model step. Defaults to ``randint`` draws.
        policy_noise_draw (Callable, optional): ``action -> noise``, the policy's standard
            normal draw shaped as ``action``: TD3's target smoothing before scaling and
            clipping, SAC's pre-tanh ``eps``. Defaults to ``randn`` noise.
        lr_alpha (float, optional): SAC's temperature learning rate (required for SAC).
        critic_first (bool, optional): step the critics before the actor's (and SAC
            temperature's) loss is computed, as
            :func:`~torchrl_rave.trainers.agent_update.critic_first_update` does for one learner.
            Defaults to ``False``: one backward pass over the summed losses.

    After construction every learner's parameters, target parameters and world-model
    statistics are views of the group's tensors (see the module's docstring); train with
    :meth:`update_world_model` and :meth:`update` only, not with the learners' own
    optimisers.

    Examples:
        >>> from torchrl.data import Bounded
        >>> from torchrl.modules import MLP, Actor, TanhModule, ValueOperator
        >>> from tensordict.nn import TensorDictModule, TensorDictSequential
        >>> spec = Bounded(-1.0, 1.0, shape=(2,))
        >>> def learner(seed):
        ...     torch.manual_seed(seed)
        ...     actor = TensorDictSequential(
        ...         TensorDictModule(MLP(in_features=3, out_features=2, num_cells=[8]),
        ...                          in_keys=["observation"], out_keys=["param"]),
        ...         TanhModule(in_keys=["param"], out_keys=["action"], spec=spec))
        ...     critic = ValueOperator(MLP(in_features=5, out_features=1, num_cells=[8]),
        ...                            in_keys=["observation", "action"])
        ...     loss = EnsembleDDPGLoss(actor, critic, num_value_nets=1)
        ...     return loss.make_value_estimator(gamma=0.99)
        >>> group = SeedGroup([learner(0), learner(1), learner(2)],
        ...                   lr_actor=1e-3, lr_critic=1e-3, tau=0.005)
        >>> batch = TensorDict({"observation": torch.randn(3, 6, 3),
        ...     "action": torch.rand(3, 6, 2),
        ...     ("next", "observation"): torch.randn(3, 6, 3),
        ...     ("next", "reward"): torch.randn(3, 6, 1),
        ...     ("next", "done"): torch.zeros(3, 6, 1, dtype=torch.bool),
        ...     ("next", "terminated"): torch.zeros(3, 6, 1, dtype=torch.bool)}, [3, 6])
        >>> out = group.update(batch)
        >>> out["loss_value"].shape, out["target_value"].shape
        (torch.Size([3]), torch.Size([3, 6]))
    """

    def __init__(
        self,
        losses: Sequence[EnsembleDDPGLoss],
        *,
        lr_actor: float,
        lr_critic: float,
        tau: float,
        world_model_losses: Sequence[WorldModelEnsembleLoss] | None = None,
        lr_world_model: float | None = None,
        streams: SeedStreams | None = None,
        draw: Callable[[Tensor, Tensor, bool], Tensor] | None = None,
        bootstrap_indices: Callable[[int, int], Tensor] | None = None,
        policy_noise_draw: Callable[[Tensor], Tensor] | None = None,
        lr_alpha: float | None = None,
        critic_first: bool = False,
    ) -> None:
        losses = list(losses)
        self.critic_first = bool(critic_first)
        if not losses:
            raise ValueError("a seed group needs at least one learner")
        if streams is not None and streams.num_seeds != len(losses):
            raise ValueError(
                f"streams hold {streams.num_seeds} seeds' random streams, the group has "
                f"{len(losses)} learners"
            )
        self.streams = streams
        kinds = {type(loss) for loss in losses}
        if len(kinds) != 1 or not issubclass(kinds.pop(), (EnsembleDDPGLoss, TD3Loss, SACLoss)):
            raise TypeError(
                "a seed group runs EnsembleDDPGLoss learners (ddpg, mve, steve, rave), TD3Loss "
                f"or SACLoss ones, all of one kind; got {sorted(type(x).__name__ for x in losses)}"
            )
        self.num_seeds = S = len(losses)
        self.losses = losses
        self.td3 = isinstance(losses[0], TD3Loss)
        self.sac = isinstance(losses[0], SACLoss)
        if self.sac:
            for loss in losses:
                if loss._version != 2 or loss.skip_done_states or loss.delay_actor:
                    raise ValueError("a seed group runs SACLoss without a value network, "
                                     "skip_done_states or a target actor (the recipe's)")  # fmt: skip
                if loss.min_log_alpha is not None or loss.max_log_alpha is not None:
                    raise ValueError("a seed group's SACLoss has no log-alpha bounds")
            self.target_entropy = float(
                _same("target_entropy", [float(x.target_entropy) for x in losses])
            )
        self._critic = "qvalue_network" if (self.td3 or self.sac) else "value_network"
        count = "num_qvalue_nets" if (self.td3 or self.sac) else "num_value_nets"
        self.num_critics = _same(count, [getattr(loss, count) for loss in losses])
        if self.td3:
            for name in ("policy_noise", "noise_clip"):
                setattr(self, name, _same(name, [float(getattr(x, name)) for x in losses]))
            _same("action bounds", [(x.min_action.tolist(), x.max_action.tolist()) for x in losses])
            self.min_action, self.max_action = losses[0].min_action, losses[0].max_action
        self._noise = policy_noise_draw or (lambda x: _randn_like(x, self.streams))
        _same("loss_function", [loss.loss_function for loss in losses])
        if losses[0].loss_function != "l2":
            raise ValueError("a seed group's critics regress with loss_function='l2'")
        self.keys = losses[0].tensor_keys
        self._estimator_setup(losses)
        self._members: _Members = []
        self._networks_setup(losses)
        self.world_model = None
        self._bootstrap = bootstrap_indices
        if self.expanding:
            if world_model_losses is None or len(world_model_losses) != S:
                raise ValueError(
                    f"a value-expansion group needs one world_model_losses entry per seed ({S})"
                )
            for loss, wm_loss in zip(losses, world_model_losses, strict=True):
                if wm_loss.world_model is not loss.value_estimator.world_model:
                    raise ValueError("each world-model loss must train its learner's own model")
            self.wm_losses = list(world_model_losses)
            models = [w.world_model for w in world_model_losses]
            _same("normaliser min_std", [[n.min_std for n in (m.obs_norm, m.action_norm,
                  m.delta_norm, m.reward_norm)] for m in models])  # fmt: skip
            self.world_model = _stacked(models, self._members)
            self.world_model.draw = draw or _gaussian_draw(streams)
            for name in ("bootstrap", "logvar_bound_coeff", "reward_coeff", "termination_coeff"):
                _same(f"world-model loss {name}", [getattr(w, name) for w in world_model_losses])
            if lr_world_model is None:
                raise ValueError("a value-expansion group needs lr_world_model")
            self.wm_optimizer = torch.optim.Adam(
                self.world_model.parameters(), lr=lr_world_model, fused=True
            )
        # the weight ForeachSoftUpdate lerps with: 1 - eps, eps = 1 - tau (the same float)
        self.tau = 1.0 - (1.0 - float(tau))
        self.actor_optimizer = torch.optim.Adam(self.actor_leaves, lr=lr_actor, fused=True)
        self.critic_optimizer = torch.optim.Adam(self.critic_leaves, lr=lr_critic, fused=True)
        # every seed's soft target update, one _foreach_lerp_ as ForeachSoftUpdate's
        targets = [*self.target_actor.values(), *self.target_critic.values()]
        sources = [t.detach() for t in ([] if self.sac else self.actor_leaves) + self.critic_leaves]
        lerp = functools.partial(torch._foreach_lerp_, targets, sources, self.tau)
        self.target_updater = types.SimpleNamespace(step=torch.no_grad()(lerp))
        if self.sac:
            if lr_alpha is None:
                raise ValueError("a SAC seed group needs lr_alpha")
            self.log_alpha = _fuse([x.log_alpha for x in losses], 0, True, self._members)
            self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=lr_alpha, fused=True)
        self._agent_optimizers = self.optimizers()  # built once, not at every update

    # ----------------------------------------------------------------- set-up
    def _estimator_setup(self, losses) -> None:
        estimators = [loss.value_estimator for loss in losses]
        kinds = _same("value estimator", [type(e) for e in estimators])
        self.expanding = issubclass(kinds, ValueExpansionEstimator)
        e = estimators[0]
        _same("gamma", [float(x.gamma) for x in estimators])
        self.gamma = e.gamma.detach().clone()  # the estimator's own float32 number
        if not self.expanding:
            if not isinstance(e, TD0Estimator) or e.average_rewards:
                raise ValueError(
                    f"a seed group computes TD(0) or value-expansion targets, got {kinds.__name__}"
                )
            return
        for name in ("horizon", "rollout", "mix", "alpha_mode", "variance_eps"):
            setattr(self, name, _same(name, [getattr(x, name) for x in estimators]))
        if self.alpha_mode == "tensordict":
            raise ValueError("a seed group computes alpha itself: use 'constant' or 'adaptive'")
        _same("alpha", [float(x.alpha) for x in estimators])
        _same("alpha_error_scale", [float(x.alpha_error_scale) for x in estimators])
        self.alpha = e.alpha.detach().clone()
        self.alpha_error_scale = e.alpha_error_scale.detach().clone()
        self.diagnostic_keys = e.tensor_keys

    def _networks_setup(self, losses) -> None:
        actor_plan = TensorCall.plan(losses[0].actor_network)
        critic_plan = TensorCall.plan(getattr(losses[0], self._critic), stacked=True)
        if actor_plan is None or critic_plan is None:
            raise ValueError(
                "a seed group runs actors and critics made of TorchRL MLPs (and a final "
                "TanhModule for the actor); this learner's networks cannot be planned"
            )
        if self.sac:
            self._sac_plan, self._sac_actor = _sac_actor_plan(losses[0]), losses[0].actor_network
            actor_plan = self._sac_plan[0]
        elif actor_plan.steps[-1][0] != "tanh":
            raise ValueError("a seed group's actor ends in a TanhModule onto the action box")
        if list(actor_plan.steps[0][1]) != ["observation"]:
            raise ValueError(
                f"a seed group's actor reads 'observation', not {actor_plan.steps[0][1]}"
            )
        if sorted(map(str, critic_plan.steps[0][1])) != sorted(
            ["observation", str(self.keys.action)]
        ):
            raise ValueError(f"a seed group's critics read {critic_plan.steps[0][1]}")
        self.actor_call, self.critic_call = actor_plan, critic_plan

        def fused(plan, name):
            return _stacked_params(plan, [getattr(x, name) for x in losses], self._members)

        self.actor = fused(actor_plan, "actor_network_params")
        # SAC's next actions come from the current actor
        self.target_actor = {} if self.sac else fused(actor_plan, "target_actor_network_params")
        self.critic = fused(critic_plan, f"{self._critic}_params")
        self.target_critic = fused(critic_plan, f"target_{self._critic}_params")
        self.actor_leaves, self.critic_leaves = (
            list(self.actor.values()),
            list(self.critic.values()),
        )

    # ---------------------------------------------------------------- networks
    def _policy(self, params: dict, obs: Tensor) -> Tensor:
        """Actions ``[S, ..., A]`` for observations ``[S, ..., F]``."""
        x = obs.reshape(obs.shape[0], -1, obs.shape[-1])
        action = self.actor_call(params, {"observation": x}, seeds=True)[self._out(self.actor_call)]
        return action.view(*obs.shape[:-1], action.shape[-1])

    def _q(self, params: dict, obs: Tensor, action: Tensor, detach: bool = False) -> Tensor:
        """``[S, K, R]`` values of the K critics for ``[S, R, F]`` inputs."""
        inputs = {self.keys.action: action, "observation": obs}
        value = self.critic_call(params, inputs, detach=detach, seeds=True)
        return value[self._out(self.critic_call)].squeeze(-1)

    @staticmethod
    def _out(plan: TensorCall):
        """The output a planned network's last step writes."""
        return plan.steps[-1][2]

    # ----------------------------------------------------------------- targets
    def batch_keys(self, available) -> list:
        """The entries of a batch that :meth:`update` and :meth:`update_world_model` read,
        of a replay buffer whose entries are ``available`` (nested keys): the observation,
        the action, the next observation, the reward, and ``terminated`` (or, where the
        data has none, ``done``)."""
        k = self.keys
        available = set(available)
        end = ("next", k.terminated)
        if end not in available:
            end = ("next", k.done)
        return ["observation", k.action, ("next", "observation"), ("next", k.reward), end]

    def _read(self, batch: TensorDictBase):
        S, k = self.num_seeds, self.keys
        if batch.batch_dims != 2 or batch.batch_size[0] != S:
            raise ValueError(
                f"a seed group of {S} takes batches of shape [{S}, B], got {tuple(batch.batch_size)}"
            )
        obs = batch.get("observation")
        nxt = batch.get(("next", "observation"))
        action = batch.get(k.action)
        reward = batch.get(("next", k.reward)).squeeze(-1)
        terminated = batch.get(("next", k.terminated), None)
        if terminated is None:
            terminated = batch.get(("next", k.done))
        return obs, action, nxt, reward, terminated.squeeze(-1)

    @torch.no_grad()
    def value_target(self, batch: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        """Each seed's critic target ``[S, B]`` and, for value expansion, its diagnostics
        (per sample, under the estimator's key names). SAC's is the soft target, its next
        actions drawn from the current actor as SACLoss draws them."""
        return self._target(*self._read(batch))

    def _target(self, obs, action, nxt, reward, terminated):
        if self.sac:
            alpha = self.log_alpha.detach().exp()  # [S]
            if self.expanding:
                # SACLoss draws its own next action before it asks the estimator: the same
                # draw, unused, keeps each seed's random stream where its learner's is
                self._noise(action)
                return self._expansion_target(
                    obs, action, nxt, reward, terminated, temperature=alpha
                )
            next_action, next_log_prob = self._sac_action(nxt)
            next_q = self._q(self.target_critic, nxt, next_action)  # [S, K, B]
            return VF.clipped_double_q_target(
                next_q, reward, terminated, self.gamma,
                next_log_prob=next_log_prob, temperature=alpha.view(-1, 1),
            ), {}  # fmt: skip
        if not self.expanding:
            next_action = self._policy(self.target_actor, nxt)
            if self.td3:  # target policy smoothing, drawn as TD3Loss draws it
                next_action = VF.smoothed_target_action(
                    next_action, self._noise(action), scale=self.policy_noise,
                    clip=self.noise_clip, low=self.min_action, high=self.max_action,
                )  # fmt: skip
            next_q = self._q(self.target_critic, nxt, next_action)
            return VF.clipped_double_q_target(next_q, reward, terminated, self.gamma), {}
        return self._expansion_target(obs, action, nxt, reward, terminated)

    def _expansion_target(self, obs, action, nxt, reward, terminated, temperature=None):
        """The value-expansion target of every seed; with SAC's ``temperature`` (``[S]``)
        the soft one, its imagined actions drawn from the current actor as SACLoss draws
        its next action."""
        wm, H = self.world_model, self.horizon
        N, (S, M, D) = wm.num_models, nxt.shape
        sample = self.rollout == "sample"
        if self.alpha_mode == "adaptive":
            err = wm.mean_prediction_error(obs, action, nxt)  # [S, M]
            alpha = VF.adaptive_alpha(err, self.alpha, self.alpha_error_scale)
        else:
            alpha = self.alpha

        def policy(s):  # [S, ..., D]; SAC's: (action, log_prob)
            if not self.sac:
                return self._policy(self.target_actor, s)
            a, log_prob = self._sac_action(s.reshape(S, -1, D))
            return a.view(*s.shape[:-1], a.shape[-1]), log_prob.view(s.shape[:-1])

        def critic(s, a):  # [S, K, R]
            return self._q(self.target_critic, s, a)

        target, var, weights = VF.value_expansion_target(
            nxt, reward, terminated, policy=policy, critic=critic,
            **world_model_calls(wm, sample), num_members=N, horizon=H,
            gamma=self.gamma, mix=self.mix, alpha=alpha, eps=self.variance_eps,
            moments=functools.partial(VF.horizon_moments, two_pass=True), temperature=temperature,
        )  # fmt: skip
        keys = self.diagnostic_keys
        diagnostics = {
            keys.alpha: alpha.expand(S, M).unsqueeze(-1),
            keys.horizon_variance: var,
            keys.horizon_weights: weights,
        }
        return target, diagnostics

    # ----------------------------------------------------------------- updates
    def _sac_action(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        """A reparameterised tanh-Gaussian action ``[S, B, A]`` and its log-probability
        ``[S, B]``, drawn as the recipe's SAC actor draws them: its own extractor and
        distribution module, the pre-tanh value ``loc + eps * scale`` scored as
        ``TanhNormal.rsample_and_log_prob`` scores it (``eps``: ``policy_noise_draw``)."""
        inputs = {"observation": obs}
        dist = TensorCall.gaussian_dist(
            self._sac_plan, self._sac_actor, self.actor, inputs, seeds=True
        )
        base = dist.root_dist
        preimage = base.loc + self._noise(base.loc) * base.scale
        transform = dist.transforms[0]
        action = transform(preimage)
        log_prob = dist.base_dist.log_prob(preimage) - _sum_rightmost(
            transform.log_abs_det_jacobian(preimage, action), len(dist.event_shape)
        )
        return action, log_prob

    def _actor_losses(self, obs: Tensor, out: dict) -> dict[str, Tensor]:
        """Each seed's actor loss (SAC's: and its temperature's) through the current
        critics, by name, ``[S]`` each; their outputs go into ``out``."""
        if not self.sac:
            q_actor = self._q(self.critic, obs, self._policy(self.actor, obs), detach=True)
            # the K critics' mean (EnsembleDDPGLoss), the first critic's value (TD3Loss)
            loss_actor = (-(q_actor[:, 0] if self.td3 else q_actor.mean(1))).mean(-1)  # [S]
            out.update(loss_actor=loss_actor.detach(), state_action_value_actor=q_actor.detach())
            return {"loss_actor": loss_actor}
        # SACLoss (v2): alpha log pi - min_k Q_k, and the temperature's loss
        alpha = self.log_alpha.detach().exp()  # [S]
        new_action, log_prob = self._sac_action(obs)
        q_actor = self._q(self.critic, obs, new_action, detach=True)
        loss_actor = (alpha.view(-1, 1) * log_prob - q_actor.min(1)[0]).mean(-1)
        loss_alpha = (-self.log_alpha.view(-1, 1) * (log_prob.detach() + self.target_entropy)).mean(
            -1
        )
        out.update(loss_actor=loss_actor.detach(), loss_alpha=loss_alpha.detach(), alpha=alpha,
                   entropy=-log_prob.detach().mean(-1))  # fmt: skip
        return {"loss_actor": loss_actor, "loss_alpha": loss_alpha}

    def update(self, batch: TensorDictBase, step_actor: bool = True) -> TensorDict:
        """One agent update of every seed on its own rows of ``batch`` (``[S, B]``):
        critics, then (with ``step_actor``) actor and soft target update, as
        :func:`~torchrl_rave.trainers.agent_update.agent_update` (or, with ``critic_first``,
        :func:`~torchrl_rave.trainers.agent_update.critic_first_update`) does for one learner,
        through those same functions. Returns per-seed outputs (batch size ``[S]``):
        ``loss_value``, ``loss_actor``, ``target_value`` ``[S, B]``, ``pred_value``
        ``[S, K, B]`` and the estimator's
        diagnostics; ``state_action_value_actor`` ``[S, K, B]``, or, for SAC, ``loss_alpha``,
        ``alpha`` and ``entropy``. SAC steps its actor and temperature at every update
        (``step_actor`` is ignored). With ``critic_first`` and without ``step_actor``, the
        actor's loss is not computed and its entries are absent."""
        step_actor = step_actor or self.sac
        obs, action, nxt, reward, terminated = self._read(batch)
        out = {}

        def critic_part(_):
            with torch.no_grad():
                target, diagnostics = self._target(obs, action, nxt, reward, terminated)
            current = self._q(self.critic, obs, action)  # [S, K, B]
            loss_value = (current - target.unsqueeze(1)).pow(2).sum(1).mean(-1)  # [S]
            out.update(loss_value=loss_value.detach(), target_value=target,
                       pred_value=current.detach(), **diagnostics)  # fmt: skip
            return {"loss_value": loss_value.sum()}  # the seeds' sum: each its own gradient

        def actor_part(_):
            return {k: v.sum() for k, v in self._actor_losses(obs, out).items()}

        optimizers, updater = self._agent_optimizers, self.target_updater
        if self.critic_first:  # without step_actor, no actor loss is computed
            parts = (critic_part, actor_part)
            critic_first_update(optimizers, updater, batch, parts, step_actor)
        else:  # one backward pass over every loss
            both = total_loss(lambda b: {**critic_part(b), **actor_part(b)})
            agent_update(None, optimizers, updater, batch, step_actor, both)
        return TensorDict(out, batch_size=[self.num_seeds])

    def _bootstrap_indices(self, B: int, device) -> Tensor:
        N, S = self.world_model.num_models, self.num_seeds
        if self._bootstrap is not None:
            return self._bootstrap(B, S)
        if not self.wm_losses[0].bootstrap:
            return torch.arange(B, device=device).expand(N, S, B)
        if self.streams is not None:  # each seed's [N, B], as its learner draws them
            return self.streams.stack(lambda i: torch.randint(B, (N, B), device=device), 1)
        return torch.randint(B, (N, S, B), device=device)

    def update_world_model(self, batch: TensorDictBase) -> TensorDict:
        """One step of every seed's world model on its own rows of ``batch`` (``[S, B]``),
        as :class:`~torchrl_rave.trainers.WorldModelTrainer.update` does for one: each
        member on a bootstrap resample of its seed's rows. Returns per-seed losses and
        the trainer's logged statistics (batch size ``[S]``)."""
        if self.world_model is None:
            raise RuntimeError("this seed group has no world model (TD(0) targets)")
        wm, loss0 = self.world_model, self.wm_losses[0]
        for w in self.wm_losses:
            w.world_model.check_normalizers()
        obs, action, nxt, reward, terminated = self._read(batch)
        S, B = reward.shape
        # drawn [N, S, B], as one learner draws [N, B]; used [S, N, B]
        idx = self._bootstrap_indices(B, obs.device).transpose(0, 1)
        seed = torch.arange(S, device=obs.device).view(S, 1, 1)

        def resample(x):
            return x[seed, idx]  # [S, N, B, F]

        obs, action, nxt = resample(obs), resample(action), resample(nxt)
        reward = resample(reward.unsqueeze(-1))
        terminated = resample(terminated.unsqueeze(-1)).to(obs.dtype)
        out = loss0.loss_terms(wm, obs, action, nxt, reward, terminated)
        self.wm_optimizer.zero_grad()
        (out["loss_transition"] + out["loss_reward"] + out["loss_termination"]).sum().backward()
        self.wm_optimizer.step()
        return TensorDict({k: v.detach() for k, v in out.items()}, batch_size=[S])

    # ------------------------------------------------------------- checkpoints
    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """The group's optimisers by name (their states hold every seed's moments)."""
        out = {"actor": self.actor_optimizer, "critic": self.critic_optimizer}
        if self.sac:
            out["alpha"] = self.alpha_optimizer
        if self.world_model is not None:
            out["world_model"] = self.wm_optimizer
        return out

    def state_dict(self) -> dict:
        return {name: opt.state_dict() for name, opt in self.optimizers().items()}

    def load_state_dict(self, state: dict) -> None:
        for name, opt in self.optimizers().items():
            opt.load_state_dict(state[name])

    def export_optimizer_states(
        self, optimizers: Sequence[Sequence[torch.optim.Optimizer]]
    ) -> None:
        """Writes each seed's slice of the group's Adam states (moments and step) into that
        learner's own optimisers (``optimizers[s]``: the ones holding its leaves), so that
        a learner's ordinary checkpoint holds its whole state: resumed alone or in a
        group, it continues exactly."""
        for group_param, leaves in self._members:
            state = self._state_of(group_param)
            for s, leaf in enumerate(leaves):
                for opt in optimizers[s]:
                    if any(leaf is p for g in opt.param_groups for p in g["params"]):
                        opt.state[leaf] = (
                            {} if state is None else
                            {k: v.clone() if k == "step" else v[s].clone()
                             for k, v in state.items()}
                        )  # fmt: skip

    def import_optimizer_states(
        self, optimizers: Sequence[Sequence[torch.optim.Optimizer]]
    ) -> None:
        """The inverse of :meth:`export_optimizer_states`: the group's Adam states stacked
        from the learners' optimisers (after they loaded a checkpoint). Leaves with no
        state anywhere (before the first step) stay without."""
        for group_param, leaves in self._members:
            found = []
            for s, leaf in enumerate(leaves):
                for opt in optimizers[s]:
                    if leaf in opt.state and opt.state[leaf]:
                        found.append(opt.state[leaf])
                        break
            if not found:
                continue
            if len(found) != len(leaves):
                raise ValueError("some learners of the group have optimiser states, others none")
            steps = {float(f["step"]) for f in found}
            if len(steps) != 1:
                raise ValueError(f"the learners' optimisers took different step counts: {steps}")
            opt = self._optimizer_of(group_param)
            opt.state[group_param] = {
                "step": found[0]["step"].clone(),
                **{k: torch.stack([f[k] for f in found]).to(group_param.dtype)
                   for k in found[0] if k != "step"},
            }  # fmt: skip

    def _optimizer_of(self, param) -> torch.optim.Optimizer:
        for opt in self.optimizers().values():
            if any(param is p for g in opt.param_groups for p in g["params"]):
                return opt
        raise KeyError("a fused parameter no optimiser holds")

    def _state_of(self, param) -> dict | None:
        state = self._optimizer_of(param).state.get(param)
        return state or None
