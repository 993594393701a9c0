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
updates on this workload (``benchmarks/README.md``, the seed-group section).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch.distributions.utils import _sum_rightmost
from torch.nn import functional as F
from torchrl.objectives import SACLoss, TD3Loss

from torchrl_rave.modules.ensemble import (
    EnsembleLinear,
    EnsembleMLP,
    GaussianEnsembleMLP,
    ensemble_affine,
    inplace_activation,
)
from torchrl_rave.modules.normalizer import RunningNormalizer
from torchrl_rave.modules.tensor_call import TensorCall, _leaf
from torchrl_rave.objectives import functional as VF
from torchrl_rave.objectives.ensemble_ddpg import EnsembleDDPGLoss
from torchrl_rave.objectives.value_expansion import ValueExpansionEstimator
from torchrl_rave.objectives.world_model_loss import WorldModelEnsembleLoss, world_model_loss_terms

__all__ = ["SeedGroup"]

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


# outputs of more floats than this (2 MiB) are computed as bmm + add_ (see _Linear)
_LARGE = 1 << 19


class _Linear:
    """One grouped affine layer and the activation after it (``None``: none).

    The weight is ``[S, *E, out, in]`` (``output_major``, ``nn.Linear``'s layout) or
    ``[S, *E, in, out]`` (:class:`~torchrl_rave.modules.EnsembleLinear`'s), with ``E`` the
    ensemble dimensions (none for the actor, ``K`` critics, ``N`` world-model members).
    Inputs are ``[S, R, in]``, shared by a seed's members, or ``[S, *E, R, in]``, one block
    per member; the output is ``[S, *E, R, out]``. Each layer is one ``baddbmm`` over the
    ``S x E`` matrices; a layer of one matrix (a group of one's actor, or DDPG's one
    critic) is the ``F.linear`` call its single learner makes, so that a group of one
    rounds as its single run does.

    Outputs larger than the caches (over 2 MiB) cost a pass over memory for each
    element-wise step, so the layer avoids them where it can. Without autograd, a ReLU
    layer's output is returned with its bias still *owed*: ``max(x w, -b)``, which is
    ``relu(x w + b) - b``, with ``b`` handed on (:meth:`apply`) and folded into the next
    layer's bias as ``b + owed w``. That is one pass (the clamp) where ``bias add`` and
    ``relu`` take two. At S = 8 it spares five of the value target's passes over
    13.6 MB tensors (``benchmarks/README.md``, the seed-group section). The product is the
    same up to rounding. At the default sizes a group of one's outputs stay under 2 MiB,
    so it still rounds as its single run does (with a larger batch or network, this path
    and the in-place bias add below round otherwise than its learner's ``baddbmm``)."""

    __slots__ = ("weight", "bias", "activation", "output_major")

    def __init__(self, weight, bias, activation, output_major: bool) -> None:
        self.weight, self.bias, self.activation = weight, bias, activation
        self.output_major = output_major

    def __call__(self, x: Tensor, detach: bool = False, owed: Tensor | None = None) -> Tensor:
        return _settle(*self.apply(x, detach, owed))

    def apply(
        self, x: Tensor, detach: bool = False, owed: Tensor | None = None
    ) -> tuple[Tensor, Tensor | None]:
        """The layer on ``x + owed`` (``owed``: a bias ``[S * E, 1, in]`` that ``x`` does
        not hold yet, or ``None``); returns ``(y, owed)`` in the same sense."""
        w, b = self.weight, self.bias
        if detach:
            w, b = w.detach(), None if b is None else b.detach()
        if self.output_major:
            w = w.mT  # a transposed view: BLAS reads it as it is
        elif w.shape[-1] < w.shape[-2]:  # as EnsembleLinear._matmul_weight
            w = w.mT.clone(memory_format=torch.contiguous_format).mT
        lead, (fan_in, fan_out) = w.shape[:-2], w.shape[-2:]
        rows = x.shape[-2]
        flat = len(lead) == 1 and x.dim() == 3  # one matrix per seed: x, w, y are [S, ., .]
        if not flat:
            if x.dim() == 3 and len(lead) > 1:  # shared by the members: one copy per member
                x = x.unsqueeze(1).expand(*lead, rows, fan_in)
            x = x.reshape(-1, rows, fan_in)
            w = w.reshape(-1, fan_in, fan_out)
        if b is not None:
            b = b.reshape(-1, 1, fan_out)
        if owed is not None:  # (x + owed) w + b = x w + (owed w + b)
            b = ensemble_affine(owed, w, b)
        large = x.shape[0] * rows * fan_out > _LARGE
        if (
            large
            and b is not None
            and type(self.activation) is torch.nn.ReLU
            and not (torch.is_grad_enabled() and (x.requires_grad or w.requires_grad))
        ):
            y = torch.bmm(x, w).clamp_(min=b.neg())  # relu(x w + b) - b
            return y.view(*lead, rows, fan_out), b
        if x.shape[0] == 1 and self.output_major:
            # one matrix (a group of one's actor, or its one critic): the 2-D call its
            # learner makes (nn.Linear's, as TensorCall makes for one member); BLAS need
            # not round a batch of one as it rounds that call, and on some CPUs does not
            y = F.linear(x[0], w[0].mT, None if b is None else b.reshape(fan_out))
        elif large and b is not None:
            # an output larger than the caches: baddbmm first writes the bias over all of
            # it and BLAS then reads it back; the product, then the bias added in place,
            # spares one pass (a RAVE target layer at S = 8: 6.6 -> 5.5 ms at 1 thread)
            y = torch.bmm(x, w).add_(b)
        else:
            y = ensemble_affine(x, w, b)  # the S x E maps of [S * E, rows, in] in one kernel
        if self.activation is not None:
            # on the product itself, before the view: an in-place op on a view makes
            # autograd rebase it (CopySlices), whose backward clones and zero-fills the
            # whole output (128 of the ATen calls of a RAVE group update)
            inplace = inplace_activation(self.activation)
            y = self.activation(y) if inplace is None else inplace(y)
        return (y if y.dim() == len(lead) + 2 else y.view(*lead, rows, fan_out)), None


def _settle(y: Tensor, owed: Tensor | None) -> Tensor:
    """``y`` with the bias it owes (see :class:`_Linear`) added."""
    if owed is None:
        return y
    return y.add_(owed.view(*y.shape[:-2], 1, y.shape[-1]))


def _run(
    layers: list[_Linear], x: Tensor, detach: bool = False, settle: bool = True
) -> Tensor | tuple[Tensor, Tensor | None]:
    """The layers in turn; with ``settle=False``, ``(y, owed)`` as :meth:`_Linear.apply`."""
    owed = None
    for layer in layers:
        x, owed = layer.apply(x, detach, owed)
    return _settle(x, owed) if settle else (x, owed)


def _mlp_layers(
    plan: TensorCall, params: Sequence[TensorDictBase], dim: int, members: _Members
) -> tuple:
    """The grouped linear layers of a planned TorchRL MLP (one ``"mlp"`` step, optionally
    followed by a ``"tanh"`` step) from each learner's ``params``; returns ``(layers,
    leaves, in_keys, tanh)`` with ``leaves`` the fused tensors in order."""
    kinds = [step[0] for step in plan.steps]
    if kinds not in (["mlp"], ["mlp", "tanh"]):
        raise ValueError(f"a seed group runs plain MLP networks, got the planned steps {kinds}")
    _, in_keys, _, entries = plan.steps[0]
    layers, leaves = [], []
    for is_linear, layer, *keys in entries:
        if not is_linear:
            if not layers or layers[-1].activation is not None:
                raise ValueError("a seed group needs one activation after each linear layer")
            layers[-1].activation = layer
            continue
        fused = []
        for key in keys:
            fused.append(
                None if key is None
                else _fuse([_leaf(p, *key) for p in params], dim, isinstance(
                    _leaf(params[0], *key), torch.nn.Parameter), members)
            )  # fmt: skip
        layers.append(_Linear(fused[0], fused[1], None, output_major=True))
        leaves += [t for t in fused if t is not None]
    tanh = None
    if len(plan.steps) == 2:
        _, _, _, (module, _, low, high), rescale, clamp = plan.steps[1]
        tanh = (getattr(module, low), getattr(module, high), rescale, clamp)
    return layers, leaves, list(in_keys), tanh


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


class _GroupedNormalizer:
    """A :class:`~torchrl_rave.modules.normalizer.RunningNormalizer` per seed, read from
    fused ``[S, F]`` statistics (updates go through each learner's own normaliser, whose
    buffers are views of these)."""

    def __init__(self, normalizers) -> None:
        self.min_std = _same("normaliser min_std", [n.min_std for n in normalizers])
        self.mean = _fuse([n.mean for n in normalizers], 0, False)
        self.var = _fuse([n.var for n in normalizers], 0, False)
        self.count = _fuse([n.count for n in normalizers], 0, False)

    def _stats(self, x: Tensor):
        # [S, 1, ..., F]: broadcasts against [S, *members, rows, F]
        shape = (x.shape[0],) + (1,) * (x.dim() - 2) + (x.shape[-1],)
        return self.mean.view(shape), RunningNormalizer.floored_std(self.var, self.min_std).view(
            shape
        )

    def normalize(self, x: Tensor) -> Tensor:
        mean, std = self._stats(x)
        return (x - mean) / std

    def denormalize(self, x: Tensor) -> Tensor:
        mean, std = self._stats(x)
        return x * std + mean


class _GroupedWorldModel:
    """The world models of all seeds as one ``[S, N]`` ensemble; the methods mirror
    :class:`~torchrl_rave.modules.WorldModelEnsemble`'s with inputs ``[S, R, F]`` (shared
    by the members) or ``[S, N, R, F]`` (per member) and outputs ``[S, N, R, F']``."""

    def __init__(
        self, models, draw: Callable[[Tensor, Tensor, bool], Tensor], members: _Members
    ) -> None:
        self.members = members
        self.num_models = _same("world_model.num_models", [m.num_models for m in models])
        self.draw = draw
        self.leaves: list[Tensor] = []
        self.transition = self._gaussian([m.transition for m in models])
        self.reward_model = self._gaussian([m.reward_model for m in models])
        self.termination = self._mlp([m.termination for m in models])
        self.obs_norm = _GroupedNormalizer([m.obs_norm for m in models])
        self.action_norm = _GroupedNormalizer([m.action_norm for m in models])
        self.delta_norm = _GroupedNormalizer([m.delta_norm for m in models])
        self.reward_norm = _GroupedNormalizer([m.reward_norm for m in models])

    def _linear(self, layers: Sequence[EnsembleLinear], activation) -> _Linear:
        w = _fuse([layer.weight for layer in layers], 0, True, self.members)
        b = _fuse([layer.bias for layer in layers], 0, True, self.members)
        self.leaves += [w, b]
        return _Linear(w, b, activation, output_major=False)

    def _mlp(self, mlps: Sequence[EnsembleMLP], last_activation: bool = False) -> list[_Linear]:
        depth = _same("world-model layer counts", [len(m.layers) for m in mlps])
        activation = mlps[0].activation
        return [
            self._linear([m.layers[i] for m in mlps],
                         activation if i < depth - 1 or last_activation else None)
            for i in range(depth)
        ]  # fmt: skip

    def _gaussian(self, heads) -> dict:
        out = {
            "trunk": self._mlp([h.trunk for h in heads], last_activation=True),
            "mean": self._linear([h.mean_head for h in heads], None),
            "logvar": self._linear([h.logvar_head for h in heads], None),
            "max": _fuse([h.max_logvar for h in heads], 0, True, self.members),
            "min": _fuse([h.min_logvar for h in heads], 0, True, self.members),
        }
        self.leaves += [out["max"], out["min"]]
        return out

    @staticmethod
    def _gaussian_forward(head: dict, x: Tensor) -> tuple[Tensor, Tensor]:
        h, owed = _run(head["trunk"], x, settle=False)
        means, logvars = head["mean"], head["logvar"]
        if torch.is_grad_enabled() or means.weight.shape[0] == 1:
            mean, raw = means(h, owed=owed), logvars(h, owed=owed)
        else:
            # without autograd, in a group of more than one: both heads as one layer of
            # twice the width. BLAS runs an 11-wide product far below its speed; the
            # 22-wide one takes about the time of one 11-wide (a rollout step's heads at
            # S = 8: 0.40 -> 0.21 ms). A group of one keeps its single run's calls.
            width = means.weight.shape[-1]
            both = _Linear(torch.cat([means.weight, logvars.weight], -1),
                           torch.cat([means.bias, logvars.bias], -1), None, False)  # fmt: skip
            y = both(h, owed=owed)
            mean, raw = y[..., :width], y[..., width:]
        # [S, N, 1, F] bounds
        return mean, GaussianEnsembleMLP.bounded_logvar(raw, head["max"], head["min"])

    @staticmethod
    def bound_penalty(head: dict) -> Tensor:
        """Each seed's ``sum(max_logvar) - sum(min_logvar)``, ``[S]``."""
        return head["max"].sum((1, 2, 3)) - head["min"].sum((1, 2, 3))

    def _sa(self, obs: Tensor, action: Tensor) -> Tensor:
        return torch.cat([self.obs_norm.normalize(obs), self.action_norm.normalize(action)], -1)

    def predict_transition(self, obs, action):
        return self._gaussian_forward(self.transition, self._sa(obs, action))

    def step(self, obs, action, sample: bool) -> Tensor:
        delta = self.draw(*self.predict_transition(obs, action), sample)
        base = obs if obs.dim() == 4 else obs.unsqueeze(1)  # [S, R, D] is every member's
        return base + self.delta_norm.denormalize(delta)

    def predict_reward(self, obs, action, next_obs):
        x = torch.cat([self._sa(obs, action), self.obs_norm.normalize(next_obs)], -1)
        return self._gaussian_forward(self.reward_model, x)

    def reward(self, obs, action, next_obs, sample: bool) -> Tensor:
        return self.reward_norm.denormalize(
            self.draw(*self.predict_reward(obs, action, next_obs), sample)
        )

    def termination_logits(self, next_obs: Tensor) -> Tensor:
        return _run(self.termination, self.obs_norm.normalize(next_obs))

    def target_delta(self, obs, next_obs):
        return self.delta_norm.normalize(next_obs - obs)


class SeedStreams:
    """One random stream per seed of a group trained in one process.

    Torch draws from process-global generators (the CPU one and each accelerator's), so a
    seed's stream is kept as a saved generator state and swapped in around everything
    done for that seed: :meth:`use` for a phase (collection, sampling, evaluation, a
    checkpoint), :meth:`stack` for one draw per seed inside a batched update. Work done
    under ``use(i)`` sees exactly the generator a single run of seed ``i`` would see, so a
    seed's draws do not depend on the other seeds of its group. Python's ``random`` and
    NumPy's global generator are left shared (the recipe draws from neither: its envs have
    their own generators).

    Args:
        num_seeds (int): the group's size.
        device (torch.device, optional): the device the group's tensors live on; a CUDA
            device's generator is swapped along with the CPU's.

    Each seed's state is taken with :meth:`capture` once the seed has been set up (after
    ``torch.manual_seed`` and its networks' initialisation, as a single run does them).

    Examples:
        >>> streams = SeedStreams(2)
        >>> for i, seed in enumerate([0, 1]):
        ...     _ = torch.manual_seed(seed)
        ...     streams.capture(i)
        >>> with streams.use(1):
        ...     a = torch.rand(3)
        >>> _ = torch.manual_seed(1)
        >>> torch.equal(a, torch.rand(3))
        True
    """

    def __init__(self, num_seeds: int, device: torch.device | str | None = None) -> None:
        self.num_seeds = num_seeds
        self._generators = [torch.default_generator]
        device = torch.device(device) if device is not None else None
        if device is not None and device.type == "cuda":
            index = device.index if device.index is not None else torch.cuda.current_device()
            self._generators.append(torch.cuda.default_generators[index])
        self._states: list[list[Tensor] | None] = [None] * num_seeds

    def capture(self, i: int) -> None:
        """Takes the generators' current state as seed ``i``'s stream."""
        self._states[i] = [g.get_state() for g in self._generators]

    @contextlib.contextmanager
    def use(self, i: int):
        """A context in which the process's generators are seed ``i``'s; on leaving it the
        advanced state is kept as seed ``i``'s stream."""
        self._enter(i)
        try:
            yield
        finally:
            self.capture(i)

    def _enter(self, i: int) -> None:
        state = self._states[i]
        if state is None:
            raise RuntimeError(f"seed {i}'s random stream was never captured (capture({i}))")
        for g, one in zip(self._generators, state, strict=True):
            g.set_state(one)

    def stack(self, draw: Callable[[int], Tensor], dim: int = 0) -> Tensor:
        """``draw(i)`` for each seed under its own stream, stacked along ``dim``."""
        out = []
        for i in range(self.num_seeds):
            self._enter(i)
            out.append(draw(i))
            self.capture(i)
        return torch.stack(out, dim)


def _horizon_moments(candidates: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`~torchrl_rave.objectives.functional.horizon_moments` in two passes: the mean
    over the ``Ni x Nj x K`` candidates, then the mean of the squared deviations. The same
    moments to float rounding, 8-9x faster here than ``var_mean``'s one-pass reduction
    over the leading dimensions (``[4, 4, 4, S, 128, 4]`` at 2 threads: 1.15 -> 0.14 ms at
    S = 4, 2.16 -> 0.24 ms at S = 8)."""
    flat = candidates.flatten(0, 2)
    mean = flat.mean(0)
    deviation = flat - mean
    return mean, deviation.mul_(deviation).mean(0)


def _randn_like(x: Tensor, streams: SeedStreams | None) -> Tensor:
    """Standard normal noise shaped as ``x`` (the seed leading): seed by seed from
    ``streams``, or one draw for the group."""
    if streams is None:
        return torch.randn_like(x)
    return streams.stack(lambda i: torch.randn_like(x[i]))


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
    ) -> None:
        losses = list(losses)
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
            self.world_model = _GroupedWorldModel(
                [w.world_model for w in world_model_losses],
                draw or _gaussian_draw(streams),
                self._members,
            )
            for name in ("bootstrap", "logvar_bound_coeff", "reward_coeff", "termination_coeff"):
                _same(f"world-model loss {name}", [getattr(w, name) for w in world_model_losses])
            if lr_world_model is None:
                raise ValueError("a value-expansion group needs lr_world_model")
            self.wm_optimizer = torch.optim.Adam(
                self.world_model.leaves, lr=lr_world_model, fused=True
            )
        # the weight ForeachSoftUpdate lerps with: 1 - eps, eps = 1 - tau (the same float)
        self.tau = 1.0 - (1.0 - float(tau))
        self.actor_optimizer = torch.optim.Adam(self.actor_leaves, lr=lr_actor, fused=True)
        self.critic_optimizer = torch.optim.Adam(self.critic_leaves, lr=lr_critic, fused=True)
        if self.sac:
            if lr_alpha is None:
                raise ValueError("a SAC seed group needs lr_alpha")
            self.log_alpha = _fuse([x.log_alpha for x in losses], 0, True, self._members)
            self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=lr_alpha, fused=True)
            _, self._extractor, self._dist = _sac_actor_plan(losses[0])

    # ----------------------------------------------------------------- set-up
    def _estimator_setup(self, losses) -> None:
        estimators = [loss.value_estimator for loss in losses]
        kinds = _same("value estimator", [type(e) for e in estimators])
        self.expanding = issubclass(kinds, ValueExpansionEstimator)
        e = estimators[0]
        _same("gamma", [float(x.gamma) for x in estimators])
        self.gamma = e.gamma.detach().clone()  # the estimator's own float32 number
        if not self.expanding:
            from torchrl.objectives.value import TD0Estimator

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
            actor_plan = _sac_actor_plan(losses[0])[0]
        self.actor, actor_leaves, self.actor_in_keys, tanh = _mlp_layers(
            actor_plan, [loss.actor_network_params for loss in losses], 0, self._members
        )
        self.target_actor = []  # SAC's next actions come from the current actor
        if not self.sac:
            self.target_actor, _, _, _ = _mlp_layers(
                actor_plan, [x.target_actor_network_params for x in losses], 0, self._members
            )
            if tanh is None:
                raise ValueError("a seed group's actor ends in a TanhModule onto the action box")
        self.tanh = tanh
        self.critic, critic_leaves, self.critic_in_keys, _ = _mlp_layers(
            critic_plan, [getattr(x, f"{self._critic}_params") for x in losses], 0, self._members
        )
        self.target_critic, _, _, _ = _mlp_layers(
            critic_plan,
            [getattr(x, f"target_{self._critic}_params") for x in losses],
            0,
            self._members,
        )
        self.actor_leaves, self.critic_leaves = actor_leaves, critic_leaves
        self._lerp = (
            [t for layer in self.target_actor + self.target_critic
             for t in (layer.weight, layer.bias) if t is not None],
            [t.detach() for t in ([] if self.sac else actor_leaves) + critic_leaves],
        )  # fmt: skip

    # ---------------------------------------------------------------- networks
    def _policy(self, layers, obs: Tensor) -> Tensor:
        """Actions ``[S, ..., A]`` for observations ``[S, ..., F]``."""
        low, high, rescale, clamp = self.tanh
        x = _run(layers, obs.reshape(obs.shape[0], -1, obs.shape[-1]))
        x = x.view(*obs.shape[:-1], x.shape[-1]).tanh()
        if clamp:
            eps = torch.finfo(x.dtype).resolution
            x = x.clamp(-1 + eps, 1 - eps)
        return low + (high - low) * (x + 1) / 2 if rescale else x

    def _q(self, layers, obs: Tensor, action: Tensor, detach: bool = False) -> Tensor:
        """``[S, K, R]`` values of the K critics for ``[S, R, F]`` inputs."""
        inputs = {self.keys.action: action, "observation": obs}
        xs = [inputs.get(k) for k in self.critic_in_keys]
        if any(x is None for x in xs):
            raise ValueError(f"a seed group's critics read {self.critic_in_keys}")
        return _run(layers, torch.cat(xs, -1), detach).squeeze(-1)

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
        if list(self.actor_in_keys) != ["observation"]:
            raise ValueError(f"a seed group's actor reads 'observation', not {self.actor_in_keys}")
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
        (per sample, under the estimator's key names)."""
        obs, action, nxt, reward, terminated = self._read(batch)
        if not self.expanding:
            next_action = self._policy(self.target_actor, nxt)
            if self.td3:  # target policy smoothing, drawn as TD3Loss draws it
                noise = (self._noise(action) * self.policy_noise).clamp(
                    -self.noise_clip, self.noise_clip
                )
                next_action = (next_action + noise).clamp(self.min_action, self.max_action)
            next_q = self._q(self.target_critic, nxt, next_action)
            not_terminated = (~terminated).int()
            return reward + self.gamma * not_terminated * next_q.min(1)[0], {}
        return self._expansion_target(obs, action, nxt, reward, terminated)

    def _expansion_target(self, obs, action, nxt, reward, terminated, temperature=None):
        """The value-expansion target of every seed; with SAC's ``temperature`` (``[S]``)
        the soft one, its imagined actions drawn from the current actor as SACLoss draws
        its next action."""
        wm, H = self.world_model, self.horizon
        N, (S, M, D) = wm.num_models, nxt.shape
        sample = self.rollout == "sample"
        if self.alpha_mode == "adaptive":
            mean, _ = wm.predict_transition(obs, action)  # [S, N, M, D]
            err = (mean.mean(1) - wm.target_delta(obs, nxt)).pow(2).sum(-1)
            alpha = VF.adaptive_alpha(err, self.alpha, self.alpha_error_scale)  # [S, M]
        else:
            alpha = self.alpha

        def policy(s):  # [S, ..., D]; SAC's: (action, log_prob)
            if not self.sac:
                return self._policy(self.target_actor, s)
            a, log_prob = self._sac_action(s.reshape(S, -1, D))
            return a.view(*s.shape[:-1], a.shape[-1]), log_prob.view(s.shape[:-1])

        def step(s, a, per_member):  # [S, M, D] shared by the members, or [S, N, M, D]
            return wm.step(s, a, sample)

        def imagined_reward(s, a, s2):  # [S, Nj, Ni, M, H], one [S, Ni*M*H] batch per seed
            A = a.shape[-1]
            r = wm.reward(s.reshape(S, -1, D), a.reshape(S, -1, A), s2.reshape(S, -1, D), sample)
            return r.view(S, N, N, M, H)

        def termination_prob(s2):  # [S, Ni, M, H]
            return torch.sigmoid(wm.termination_logits(s2.reshape(S, N, M * H, D))).view(S, N, M, H)

        def critic(s, a):  # [S, K, R]
            return self._q(self.target_critic, s, a)

        target, var, weights = VF.value_expansion_target(
            nxt, reward, terminated, policy=policy, step=step, imagined_reward=imagined_reward,
            termination_prob=termination_prob, critic=critic, num_members=N, horizon=H,
            gamma=self.gamma, mix=self.mix, alpha=alpha, eps=self.variance_eps,
            moments=_horizon_moments, temperature=temperature,
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
        loc, scale = self._extractor(_run(self.actor, obs))
        dist = self._dist.get_dist(TensorDict(loc=loc, scale=scale, batch_size=loc.shape[:-1]))
        base = dist.root_dist
        preimage = base.loc + self._noise(base.loc) * base.scale
        transform = dist.transforms[0]
        action = transform(preimage)
        log_prob = dist.base_dist.log_prob(preimage) - _sum_rightmost(
            transform.log_abs_det_jacobian(preimage, action), len(dist.event_shape)
        )
        return action, log_prob

    def _update_sac(self, batch: TensorDictBase) -> TensorDict:
        """SACLoss (v2) for every seed: the critics' target from the current actor's next
        action less ``alpha log pi`` under the target critics' minimum, the actor's
        ``alpha log pi - min_k Q_k`` and the temperature's loss, in SACLoss's order."""
        obs, action, nxt, reward, terminated = self._read(batch)
        alpha = self.log_alpha.detach().exp()  # [S]
        diagnostics = {}
        with torch.no_grad():
            if self.expanding:
                # SACLoss draws its own next action before it asks the estimator: the same
                # draw, unused, keeps each seed's random stream where its learner's is
                self._noise(action)
                target, diagnostics = self._expansion_target(
                    obs, action, nxt, reward, terminated, temperature=alpha
                )
            else:
                next_action, next_log_prob = self._sac_action(nxt)
                next_q = self._q(self.target_critic, nxt, next_action)  # [S, K, B]
                next_value = (next_q - alpha.view(-1, 1, 1) * next_log_prob.unsqueeze(1)).min(1)[0]
                target = reward + self.gamma * (~terminated).int() * next_value
        current = self._q(self.critic, obs, action)
        loss_value = (current - target.unsqueeze(1)).pow(2).sum(1).mean(-1)
        new_action, log_prob = self._sac_action(obs)
        q_actor = self._q(self.critic, obs, new_action, detach=True)
        loss_actor = (alpha.view(-1, 1) * log_prob - q_actor.min(1)[0]).mean(-1)
        loss_alpha = (-self.log_alpha.view(-1, 1) * (log_prob.detach() + self.target_entropy)).mean(
            -1
        )
        for opt in self.optimizers().values():
            opt.zero_grad()
        (loss_value.sum() + loss_actor.sum() + loss_alpha.sum()).backward()
        self.critic_optimizer.step()
        self.actor_optimizer.step()
        self.alpha_optimizer.step()
        with torch.no_grad():
            torch._foreach_lerp_(self._lerp[0], self._lerp[1], self.tau)
        return TensorDict(
            {
                "loss_value": loss_value.detach(),
                "loss_actor": loss_actor.detach(),
                "loss_alpha": loss_alpha.detach(),
                "alpha": alpha,
                "entropy": -log_prob.detach().mean(-1),
                "target_value": target,
                "pred_value": current.detach(),
                **diagnostics,
            },
            batch_size=[self.num_seeds],
        )

    def update(self, batch: TensorDictBase, step_actor: bool = True) -> TensorDict:
        """One agent update of every seed on its own rows of ``batch`` (``[S, B]``):
        critics, then (with ``step_actor``) actor and soft target update, as
        :func:`~torchrl_rave.recipe.update.agent_update` does for one learner. Returns
        per-seed outputs (batch size ``[S]``): ``loss_value``, ``loss_actor``,
        ``target_value`` ``[S, B]``, ``pred_value`` and ``state_action_value_actor``
        ``[S, K, B]`` and the estimator's diagnostics. SAC steps its actor and temperature
        at every update, and returns ``alpha`` and ``entropy`` besides."""
        if self.sac:
            return self._update_sac(batch)
        target, diagnostics = self.value_target(batch)
        obs, action, _, _, _ = self._read(batch)
        current = self._q(self.critic, obs, action)  # [S, K, B]
        loss_value = (current - target.unsqueeze(1)).pow(2).sum(1).mean(-1)  # [S]
        q_actor = self._q(self.critic, obs, self._policy(self.actor, obs), detach=True)
        # the K critics' mean (EnsembleDDPGLoss), the first critic's value (TD3Loss)
        loss_actor = (-(q_actor[:, 0] if self.td3 else q_actor.mean(1))).mean(-1)  # [S]
        self.actor_optimizer.zero_grad()
        self.critic_optimizer.zero_grad()
        (loss_value.sum() + loss_actor.sum()).backward()
        self.critic_optimizer.step()
        if step_actor:
            self.actor_optimizer.step()
            with torch.no_grad():
                torch._foreach_lerp_(self._lerp[0], self._lerp[1], self.tau)
        return TensorDict(
            {
                "loss_value": loss_value.detach(),
                "loss_actor": loss_actor.detach(),
                "target_value": target,
                "pred_value": current.detach(),
                "state_action_value_actor": q_actor.detach(),
                **diagnostics,
            },
            batch_size=[self.num_seeds],
        )

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
        out = world_model_loss_terms(
            wm.predict_transition(obs, action),
            wm.target_delta(obs, nxt),
            wm.predict_reward(obs, action, nxt),
            wm.reward_norm.normalize(reward),
            wm.termination_logits(nxt),
            terminated,
            (wm.bound_penalty(wm.transition), wm.bound_penalty(wm.reward_model)),
            reward_coeff=loss0.reward_coeff,
            termination_coeff=loss0.termination_coeff,
            logvar_bound_coeff=loss0.logvar_bound_coeff,
        )
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
