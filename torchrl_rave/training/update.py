"""The agent's update step, optionally compiled."""

from __future__ import annotations

from collections.abc import Callable

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

__all__ = ["agent_update", "compile_loss", "make_agent_step", "total_loss"]


def total_loss(loss) -> Callable[[TensorDictBase], tuple[TensorDictBase, torch.Tensor]]:
    """``batch -> (loss outputs, their sum)``: the part of an update that
    :func:`compile_loss` hands to ``torch.compile``."""

    def loss_and_total(batch: TensorDictBase):
        out = loss(batch)
        # Each loss sees the other networks detached (and targets carry no gradient), so
        # one backward over the sum gives every network exactly its own gradient.
        return out, sum(v for k, v in out.items() if k.startswith("loss_"))

    return loss_and_total


def compile_loss(fn: Callable, mode: str | None = None) -> Callable:
    """``torch.compile`` of a loss's forward, as the update steps use it.

    Only the forward is compiled (AOTAutograd compiles its backward alongside); the
    backward call, the fused Adam steps and the soft target update stay eager. Compiling
    those too costs graph breaks (fused Adam and ``zero_grad`` are not traced) and was
    slower on CPU (benchmarks/README.md). ``fallback_random`` makes the compiled code draw
    its random numbers (RAVE's rollout noise) from torch's generator, as eager code does,
    so a compiled run follows the eager run's random stream.
    """
    from torch._inductor import list_mode_options

    # torch.compile takes a mode or options, not both: the mode's own options, plus ours
    options = list_mode_options(mode) if mode not in (None, "default") else {}
    return torch.compile(fn, options={**options, "fallback_random": True})


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


def make_agent_step(cfg: DictConfig, loss, optimizers: dict, target_updater):
    """The recipe's agent update on a batch, ``agent_step(batch, step_actor)``; with
    ``compile.enabled`` its loss forward goes through :func:`compile_loss`
    (``compile.mode``), compiled at the first call. (The world model's step is
    :class:`WorldModelTrainer`'s, compiled alike.)"""
    loss_fn = total_loss(loss)
    if cfg.compile.enabled:
        loss_fn = compile_loss(loss_fn, cfg.compile.mode)

    def agent_step(batch, step_actor=True):
        return agent_update(loss, optimizers, target_updater, batch, step_actor, loss_fn)

    return agent_step
