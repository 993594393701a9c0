"""The order of one agent update, written once for a single learner and a seed group.

An agent update is the critics' loss, the actor's (and SAC temperature's) loss, their
optimiser steps and the soft target update. :func:`agent_update` takes them from one
forward pass with one backward pass over their sum; :func:`critic_first_update` steps the
critics before the actor's loss is computed. The recipe runs a single learner's TorchRL
loss through them (``torchrl_rave.recipe.update.make_agent_step``), and
:class:`~torchrl_rave.trainers.SeedGroup` runs its seed-batched losses through the same
two functions, so the two cannot order an update differently.

``optimizers`` holds ``"critic"`` and ``"actor"`` (and SAC's ``"alpha"``);
``target_updater`` is anything with a ``step()``, such as
:class:`~torchrl_rave.objectives.ForeachSoftUpdate`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase

__all__ = ["agent_update", "critic_first_update", "total_loss"]


def total_loss(loss) -> Callable[[TensorDictBase], tuple[TensorDictBase, torch.Tensor]]:
    """``batch -> (loss outputs, their sum)``: the part of an update that
    :func:`~torchrl_rave.objectives.compile.compile_loss` hands to ``torch.compile``."""

    def loss_and_total(batch: TensorDictBase):
        out = loss(batch)
        # Each loss sees the other networks detached (and targets carry no gradient), so
        # one backward over the sum gives every network exactly its own gradient.
        return out, sum(v for k, v in out.items() if k.startswith("loss_"))

    return loss_and_total


def agent_update(
    loss, optimizers: dict, target_updater, batch: TensorDictBase, step_actor=True, loss_fn=None
):
    """One agent step: critic (and, with ``step_actor``, actor, SAC temperature and the
    soft target update); returns the loss outputs. ``loss_fn`` replaces
    ``total_loss(loss)`` (a compiled one, say)."""
    out, total = (loss_fn or total_loss(loss))(batch)
    for name in ("actor", "critic", "alpha"):
        if name in optimizers:
            optimizers[name].zero_grad()
    total.backward()
    optimizers["critic"].step()
    if step_actor:
        optimizers["actor"].step()
        if "alpha" in optimizers:
            optimizers["alpha"].step()
        target_updater.step()
    return out


def critic_first_update(
    optimizers: dict, target_updater, batch: TensorDictBase, parts, step_actor=True
) -> dict:
    """One agent step with the critics stepped first (``optim.critic_first``): the critics'
    loss, its backward and step; then, with ``step_actor``, the actor's (and SAC
    temperature's) loss through the updated critics, its backward and steps, and the soft
    target update, as CleanRL's scripts and TorchRL's sota DDPG and TD3 scripts order them.
    ``parts``: ``(critic_part, actor_part)``, each ``batch -> {name: loss}``, the critics'
    part with one entry (a single learner's from
    :func:`~torchrl_rave.recipe.update.split_losses`, compiled or not). Returns the loss
    outputs (no ``loss_actor`` without ``step_actor``)."""
    critic_part, actor_part = parts
    out = critic_part(batch)
    ((key, value),) = out.items()
    optimizers["critic"].zero_grad()
    value.backward()
    optimizers["critic"].step()
    out[key] = value.detach()
    if step_actor:
        actor_out = actor_part(batch)
        for name in ("actor", "alpha"):
            if name in optimizers:
                optimizers[name].zero_grad()
        sum(v for k, v in actor_out.items() if k.startswith("loss_")).backward()
        optimizers["actor"].step()
        if "alpha" in optimizers:
            optimizers["alpha"].step()
        target_updater.step()
        out.update({k: v.detach() for k, v in actor_out.items()})
    return out
