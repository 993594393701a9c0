"""Calling TensorDict modules on plain tensors with given, optionally stacked, parameters.

The value-expansion target evaluates the target actor ``1 + H_max`` times and ``K`` target
critics on ``M (1 + N H_max)`` rows per update. Through the TensorDict API each call wraps
its inputs in a TensorDict, swaps the target parameters in with ``to_module`` and, for
``K`` stacked critics, goes through ``torch.vmap``: on small networks that overhead costs
more than the arithmetic. :class:`TensorCall` plans the call once and then runs

- every :class:`~tensordict.nn.TensorDictModule` whose module is a plain ``nn.Sequential``
  (TorchRL's :class:`~torchrl.modules.MLP` included) of ``nn.Linear`` layers and
  parameter-free element-wise activations as direct ``linear`` / ``baddbmm`` calls on the
  given parameters (stacked parameters: one batched matmul per layer for all ``K``
  members), and
- any other module (a :class:`~torchrl.modules.TanhModule`, a custom module) through its
  own ``forward`` on a small TensorDict, with its parameters swapped in.

Anything the plan cannot prove equivalent (normalisation or dropout layers, modules with
a custom ``forward``, stacked parameters through a non-MLP module) is refused at planning
time: :meth:`TensorCall.plan` returns ``None`` and the caller keeps the TensorDict path.
"""

from __future__ import annotations

import weakref
from collections.abc import Mapping

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import (
    NormalParamExtractor,
    TensorDictModule,
    TensorDictModuleBase,
    TensorDictParams,
    TensorDictSequential,
)
from tensordict.utils import NestedKey
from torch import nn
from torch.nn import functional as F
from torchrl.modules import MLP, TanhModule

from torchrl_rave.modules.ensemble import _Linear, _run, ensemble_affine, inplace_activation

__all__ = ["PlannedCalls", "TensorCall"]

# Parameter-free activations that act element-wise (safe to apply to [K, M, F] at once).
_ELEMENTWISE = (
    nn.ReLU,
    nn.Tanh,
    nn.ELU,
    nn.LeakyReLU,
    nn.SiLU,
    nn.GELU,
    nn.Sigmoid,
    nn.Softplus,
    nn.Mish,
    nn.Identity,
)


def _linear_layers(module: nn.Module, prefix: tuple[str, ...] = ()) -> list | None:
    """``(parameter key, is_linear, layer)`` for every layer of a plain Linear/activation
    ``nn.Sequential`` (nested plain Sequentials flattened), or ``None``."""
    if not isinstance(module, nn.Sequential):
        return None
    if type(module).forward not in (nn.Sequential.forward, MLP.forward):
        return None
    if getattr(module, "_reshape_out", False):
        return None
    layers = []
    for name, layer in module.named_children():
        key = (*prefix, name)
        if type(layer) is nn.Linear:
            layers.append((key, True, layer))
        elif isinstance(layer, _ELEMENTWISE) and not any(True for _ in layer.parameters()):
            layers.append((key, False, layer))
        else:
            inner = _linear_layers(layer, key)
            if inner is None:
                return None
            layers += inner
    return layers


def _stacked_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None):
    """``x @ W^T + b`` for ``K`` stacked ``nn.Linear`` layers (``[K, out, in]``): ``x`` is
    ``[M, F]`` (shared) or ``[K, M, F]``."""
    return ensemble_affine(
        x, weight.transpose(-1, -2), None if bias is None else bias.unsqueeze(-2)
    )


def _leaf(params: TensorDictBase | dict, key: tuple[str, ...], flat: str) -> torch.Tensor:
    """``params.get(key)`` (a plain ``dict``: keyed by the dotted ``flat``, as a seed group
    holds its stacked leaves). A :class:`~tensordict.nn.TensorDictParams` also holds its leaves
    in its ``nn.Module`` parameter and buffer dicts under the dotted key ``flat``, rebuilt
    whenever an entry is set or the module is moved or cast (they are what ``parameters()``,
    and so every optimiser, sees): one dict look-up there instead of a nested TensorDict
    get, which costs several microseconds per leaf and dozens of leaves per update."""
    if type(params) is dict:
        return params[flat]
    if isinstance(params, TensorDictParams):
        leaf = params._parameters.get(flat)
        if leaf is None:
            leaf = params._buffers.get(flat)
        if leaf is not None:
            return leaf
    return params.get(key)


def _shared_state(params: TensorDictBase, prefix: tuple[str, ...]) -> TensorDictBase:
    """The sub-module's entries of ``params``; with stacked parameters, member 0's (only
    parameter-free modules are planned then, and their buffers are the same for all)."""
    sub = params.get(prefix) if prefix else params
    return sub[(0,) * sub.batch_dims] if sub.batch_dims else sub


class TensorCall:
    """A planned, TensorDict-free call of a TensorDict module.

    Build it with :meth:`plan`; call it with the parameters (laid out as
    ``TensorDict.from_module(module)``, optionally with a leading ensemble dimension) and a
    mapping of input tensors. It returns the module's outputs by key.

    Examples:
        >>> from torchrl.modules import MLP, ValueOperator
        >>> critic = ValueOperator(MLP(in_features=5, out_features=1, num_cells=[8]),
        ...                        in_keys=["observation", "action"])
        >>> call = TensorCall.plan(critic, stacked=True)
        >>> params = TensorDict.from_module(critic).data.expand(4).clone()  # K = 4 members
        >>> out = call(params, {"observation": torch.randn(6, 3), "action": torch.randn(6, 2)})
        >>> out["state_action_value"].shape
        torch.Size([4, 6, 1])
    """

    def __init__(self, steps: list[tuple], out_keys: list[NestedKey]) -> None:
        self.steps = steps
        self.out_keys = out_keys
        # id(leaf) -> (weakref to the leaf, its member-0 view without autograd history)
        self._member_views: dict[int, tuple[weakref.ref, torch.Tensor]] = {}

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_member_views": {}}  # weak references do not pickle

    def _member(self, leaf: torch.Tensor, detach: bool) -> torch.Tensor:
        """``leaf[0]`` of a one-member stack (``leaf.detach()[0]`` with ``detach``).

        Where autograd need not see the view (the leaf needs no gradient, gradients are
        off, or ``detach``), the view is made once per leaf and kept: it shares the leaf's
        storage and version counter, so in-place updates (optimiser steps, target lerps)
        show through it, and a replaced leaf is a new key. A view autograd tracks is made
        afresh at every call: after an in-place update of its leaf, a kept one would
        backpropagate through ``as_strided`` instead."""
        if not detach and leaf.requires_grad and torch.is_grad_enabled():
            return leaf.squeeze(0)
        if torch.compiler.is_compiling():
            return leaf.detach().squeeze(0)
        hit = self._member_views.get(id(leaf))
        if hit is None or hit[0]() is not leaf:
            if len(self._member_views) > 256:  # forget views of leaves that are gone
                self._member_views = {
                    k: v for k, v in self._member_views.items() if v[0]() is not None
                }
            hit = (weakref.ref(leaf), leaf.detach().squeeze(0))
            self._member_views[id(leaf)] = hit
        return hit[1]

    @classmethod
    def plan(cls, module: TensorDictModuleBase, *, stacked: bool = False) -> TensorCall | None:
        """Plans ``module``; ``None`` when some part cannot be run exactly on tensors.

        Args:
            module (TensorDictModuleBase): a TensorDictModule or TensorDictSequential.
            stacked (bool): the parameters will carry a leading ensemble dimension; only
                Linear/activation MLPs (and parameter-free modules) are accepted then.
        """
        steps = cls._plan(module, (), stacked)
        if steps is None:
            return None
        return cls(steps, list(module.out_keys))

    @classmethod
    def _plan(cls, module, prefix: tuple[str, ...], stacked: bool) -> list[tuple] | None:
        if type(module) is TensorDictSequential and not getattr(module, "partial_tolerant", False):
            steps = []
            for i, sub in enumerate(module.module):
                sub_steps = cls._plan(sub, (*prefix, "module", str(i)), stacked)
                if sub_steps is None:
                    return None
                steps += sub_steps
            return steps
        if (
            isinstance(module, TensorDictModule)
            and type(module).forward is TensorDictModule.forward
            and len(module.out_keys) == 1
            and not getattr(module, "out_to_in_map", False)
        ):
            layers = _linear_layers(module.module, (*prefix, "module"))
            # several inputs are concatenated by TorchRL's MLP only
            several = len(module.in_keys) > 1
            if layers is not None and (not several or type(module.module) is MLP):
                # each linear layer's parameter keys, nested and dotted (see _leaf)
                layers = [
                    (is_linear, layer, *(cls._param_keys(key, layer) if is_linear else ()))
                    for key, is_linear, layer in layers
                ]
                return [("mlp", list(module.in_keys), module.out_keys[0], layers)]
        if type(module) is TanhModule and len(module.in_keys) == 1:
            # TorchRL's squashing onto the action box, done on the tensor (bounds are buffers)
            key = module.out_keys[0]
            name = key if isinstance(key, str) else "_".join(key)
            bounds = (module, prefix, f"{name}_low", f"{name}_high")
            return [
                ("tanh", module.in_keys[0], key, bounds, bool(module.non_trivial), module.clamp)
            ]
        has_state = any(True for _ in module.parameters()) or any(True for _ in module.buffers())
        if stacked and any(True for _ in module.parameters()):
            return None
        return [("module", prefix if has_state else None, module)]

    @classmethod
    def plan_gaussian_actor(cls, actor: TensorDictModuleBase):
        """A Gaussian policy as it is built in TorchRL's sota SAC script and the recipe,
        ``ProbabilisticActor(TensorDictModule(Sequential(<MLP>, NormalParamExtractor),
        out_keys=[loc, scale]), ...)``, planned: ``(call, extractor, head)`` with ``call``
        the MLP as tensor calls (output ``"loc_scale"``, parameters keyed as in the actor's
        own), ``extractor`` the ``NormalParamExtractor`` and ``head`` the distribution
        module (its ``get_dist`` takes the extractor's outputs under the first module's
        ``out_keys``). ``None`` for any other actor, which then runs as a module."""
        try:
            first, head = actor.module[0], actor.module[-1]
            mlp, extractor = first.module[0], first.module[-1]
        except (AttributeError, IndexError, TypeError, KeyError):
            return None
        if (
            len(actor.module) != 2
            or not hasattr(head, "get_dist")
            or type(first).forward is not TensorDictModule.forward
            or not isinstance(first.module, nn.Sequential)
            or len(first.module) != 2
            or not isinstance(extractor, NormalParamExtractor)
            or len(first.out_keys) != 2
        ):
            return None
        layers = _linear_layers(mlp, ("module", "0", "module", "0"))
        if layers is None:
            return None
        layers = [
            (is_linear, layer, *(cls._param_keys(key, layer) if is_linear else ()))
            for key, is_linear, layer in layers
        ]
        call = cls([("mlp", list(first.in_keys), "loc_scale", layers)], ["loc_scale"])
        return call, extractor, head

    @staticmethod
    def gaussian_dist(planned: tuple, actor: TensorDictModuleBase, params, inputs, seeds=False):
        """The action distribution of ``actor`` planned by :meth:`plan_gaussian_actor`
        (``planned``) under ``params`` for ``inputs`` (key -> ``[R, F]``; with ``seeds``,
        stacked seeds' parameters and ``[S, R, F]`` inputs): its MLP as tensor calls, then
        its own extractor and distribution module."""
        call, extractor, head = planned
        loc, scale = extractor(call(params, inputs, seeds=seeds)["loc_scale"])
        names = actor.module[0].out_keys
        return head.get_dist(TensorDict(dict(zip(names, (loc, scale), strict=True)),
                                        batch_size=loc.shape[:-1]))  # fmt: skip

    @staticmethod
    def _grouped(params: dict, layers: list) -> list[_Linear]:
        """An MLP step's layers as grouped layers on stacked seeds' ``params``, each
        activation folded into the layer before it."""
        out = []
        for is_linear, layer, *keys in layers:
            if not is_linear:
                if not out or out[-1].activation is not None:
                    raise ValueError(
                        "stacked seeds' MLPs need one linear layer before each activation"
                    )
                out[-1].activation = layer
                continue
            weight_key, bias_key = keys
            bias = None if bias_key is None else _leaf(params, *bias_key)
            out.append(_Linear(_leaf(params, *weight_key), bias, None, output_major=True))
        return out

    @staticmethod
    def _param_keys(key: tuple[str, ...], layer: nn.Linear) -> tuple:
        names = ["weight"] + (["bias"] if layer.bias is not None else [])
        keys = [((*key, name), ".".join((*key, name))) for name in names]
        return keys[0], keys[1] if len(keys) > 1 else None

    def __call__(
        self,
        params: TensorDictBase | None,
        inputs: Mapping[NestedKey, torch.Tensor],
        *,
        detach: bool = False,
        seeds: bool = False,
    ) -> dict[NestedKey, torch.Tensor]:
        """The module's outputs by key for ``inputs`` under ``params`` (``None``: the
        module's own parameters); ``detach=True`` uses the parameters detached (gradients
        still reach the inputs), as ``params.detach()`` would.

        With ``seeds=True``, ``params`` are stacked seeds' (a dict of ``[S, ...]`` leaves by
        dotted key, a :class:`~torchrl_rave.trainers.SeedGroup`'s; ``[S, K, ...]`` for a
        plan made with ``stacked=True``) and the inputs ``[S, R, F]``: each MLP runs as
        the grouped layers of :mod:`~torchrl_rave.modules.ensemble` (one batched matmul
        per layer for all seeds), its ``TanhModule`` with the module's own bounds. Only
        MLP and tanh steps are planned for seeds."""
        values = dict(inputs)
        for step in self.steps:
            if step[0] == "mlp" and seeds:
                _, in_keys, out_key, layers = step
                xs = [values[k] for k in in_keys]
                values[out_key] = _run(self._grouped(params, layers), torch.cat(xs, -1), detach)
            elif step[0] == "mlp":
                _, in_keys, out_key, layers = step
                xs = [values[k] for k in in_keys]
                x = xs[0] if len(xs) == 1 else torch.cat(xs, -1)
                fresh = False  # whether x is a linear layer's own output
                # One stacked member (DDPG's single critic): plain 2-D linear calls on the
                # member's squeezed parameters, cheaper than batched matmuls with the same
                # numbers; x gets its member dimension back at the end (an in-place
                # activation on that view would cost autograd a CopySlices node).
                single = False
                for is_linear, layer, *keys in layers:
                    if not is_linear:
                        # element-wise and parameter-free: no hooks needed; in place on a
                        # linear layer's output, never on the caller's input
                        inplace = inplace_activation(layer) if fresh else None
                        x = layer.forward(x) if inplace is None else inplace(x)
                        fresh = False
                        continue
                    fresh = True
                    if params is None:
                        w, b = layer.weight, layer.bias
                    else:
                        weight_key, bias_key = keys
                        w = _leaf(params, *weight_key)
                        b = None if bias_key is None else _leaf(params, *bias_key)
                    if w.dim() == 3 and w.shape[0] == 1:
                        single = True
                        x = x.squeeze(0) if x.dim() == 3 else x
                        w = self._member(w, detach)
                        b = None if b is None else self._member(b, detach)
                    elif detach:
                        w, b = w.detach(), None if b is None else b.detach()
                    x = F.linear(x, w, b) if w.dim() == 2 else _stacked_linear(x, w, b)
                values[out_key] = x.unsqueeze(0) if single else x
            elif step[0] == "tanh":
                _, in_key, out_key, (module, prefix, low_name, high_name), rescale, clamp = step
                if params is None or seeds:
                    low, high = getattr(module, low_name), getattr(module, high_name)
                elif params.batch_dims == 0:
                    low, high = (
                        _leaf(params, (*prefix, n), ".".join((*prefix, n)))
                        for n in (low_name, high_name)
                    )
                else:
                    sub = _shared_state(params, prefix)
                    low, high = sub.get(low_name), sub.get(high_name)
                x = values[in_key].tanh()
                if clamp:
                    eps = torch.finfo(x.dtype).resolution
                    x = x.clamp(-1 + eps, 1 - eps)
                values[out_key] = low + (high - low) * (x + 1) / 2 if rescale else x
            elif seeds:
                raise ValueError(f"stacked seeds' parameters run MLP and tanh steps, not {step[2]}")
            else:
                _, prefix, module = step
                batch = next(iter(values.values())).shape[:-1]
                td = TensorDict({k: values[k] for k in module.in_keys if k in values}, batch)
                if prefix is not None and params is not None:
                    state = _shared_state(params, prefix)
                    with (state.detach() if detach else state).to_module(
                        module, preserve_module_state=False
                    ):
                        td = module(td)
                else:
                    td = module(td)
                for k in module.out_keys:
                    values[k] = td.get(k)
        return {k: values[k] for k in self.out_keys}


class PlannedCalls:
    """The :class:`TensorCall` plans of one owner's networks, made once per
    ``(name, stacked)`` and kept; every lookup gives ``None`` while ``enabled`` is off or
    when a network cannot be planned (the owner then takes its TensorDict path).

    Examples:
        >>> from torchrl.modules import MLP, ValueOperator
        >>> critic = ValueOperator(MLP(in_features=5, out_features=1, num_cells=[8]),
        ...                        in_keys=["observation", "action"])
        >>> calls = PlannedCalls()
        >>> calls.get("critic", critic, stacked=True) is calls.get("critic", critic, stacked=True)
        True
        >>> calls.enabled = False
        >>> calls.get("critic", critic) is None
        True
    """

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self._plans: dict[tuple[str, bool], TensorCall | None] = {}

    def get(
        self, name: str, module: TensorDictModuleBase, stacked: bool = False
    ) -> TensorCall | None:
        if not self.enabled:
            return None
        key = (name, stacked)
        if key not in self._plans:
            self._plans[key] = TensorCall.plan(module, stacked=stacked)
        return self._plans[key]

    def gaussian_actor(self, actor: TensorDictModuleBase):
        """:meth:`TensorCall.plan_gaussian_actor` of ``actor``, made once; ``None`` while
        ``enabled`` is off or when it cannot be planned."""
        if not self.enabled:
            return None
        key = ("gaussian_actor", False)
        if key not in self._plans:
            self._plans[key] = TensorCall.plan_gaussian_actor(actor)
        return self._plans[key]

    def actions(
        self,
        actor: TensorDictModuleBase,
        params: TensorDictBase | None,
        inputs: Mapping[NestedKey, torch.Tensor],
        action_key: NestedKey,
    ) -> torch.Tensor:
        """``actor``'s ``action_key`` ``[*B, A]`` for ``inputs`` (key -> ``[*B, F]``) under
        ``params`` (``None``: the module's own): its planned call on the rows flattened
        from ``*B`` when it can be planned, otherwise the module itself.

        Examples:
            >>> from torchrl.modules import MLP, Actor
            >>> actor = Actor(MLP(in_features=3, out_features=2, num_cells=[8]))
            >>> PlannedCalls().actions(actor, None, {"observation": torch.randn(4, 5, 3)},
            ...                        "action").shape
            torch.Size([4, 5, 2])
        """
        batch = next(iter(inputs.values())).shape[:-1]
        call = self.get("actor", actor)
        if call is not None:
            flat = {k: v.reshape(-1, v.shape[-1]) for k, v in inputs.items()}
            out = call(params, flat)[action_key]
            return out.reshape(*batch, out.shape[-1])
        td = TensorDict(dict(inputs), batch_size=batch)
        if params is None:
            return actor(td).get(action_key)
        with params.to_module(actor, preserve_module_state=False):
            return actor(td).get(action_key)

    def values(
        self,
        critic: TensorDictModuleBase,
        params: TensorDictBase | None,
        inputs: Mapping[NestedKey, torch.Tensor],
        value_key: NestedKey,
        *,
        detach: bool = False,
        randomness: str = "error",
    ) -> torch.Tensor:
        """``[K, *B]`` values ``value_key`` of ``K`` critics for ``inputs`` (key ->
        ``[*B, F]``): ``params`` stacked ``[K, ...]``, or plain (or ``None``, the module's
        own) for ``K = 1``. ``detach=True`` uses the parameters detached (gradients still
        reach the inputs). A planned call on the flattened rows when the critic can be
        planned; otherwise the module, vmapped over the members with ``randomness``.

        Examples:
            >>> from torchrl.modules import MLP, ValueOperator
            >>> critic = ValueOperator(MLP(in_features=5, out_features=1, num_cells=[8]),
            ...                        in_keys=["observation", "action"])
            >>> params = TensorDict.from_module(critic).data.expand(4).clone()
            >>> x = {"observation": torch.randn(2, 6, 3), "action": torch.randn(2, 6, 2)}
            >>> PlannedCalls().values(critic, params, x, "state_action_value").shape
            torch.Size([4, 2, 6])
        """
        batch = next(iter(inputs.values())).shape[:-1]
        stacked = params is not None and params.batch_dims >= 1
        call = self.get("critic", critic, stacked)
        if call is not None:
            flat = {k: v.reshape(-1, v.shape[-1]) for k, v in inputs.items()}
            q = call(params, flat, detach=detach)[value_key].squeeze(-1)  # [K, M] or [M]
            q = q if stacked else q.unsqueeze(0)
            return q.reshape(q.shape[0], *batch)
        if detach and params is not None:
            params = params.detach()

        def member(p):
            td = TensorDict(dict(inputs), batch_size=batch)
            if p is None:
                return critic(td).get(value_key)
            with p.to_module(critic, preserve_module_state=False):
                return critic(td).get(value_key)

        if stacked:
            return torch.vmap(member, (0,), randomness=randomness)(params).squeeze(-1)
        return member(params).squeeze(-1).unsqueeze(0)
