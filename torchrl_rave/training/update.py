"""The agent's update step, optionally compiled."""

from __future__ import annotations

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

__all__ = ["agent_update", "make_agent_step"]


def agent_update(loss, optimizers: dict, target_updater, batch: TensorDictBase, step_actor=True):
    """One agent step: critic (and, with ``step_actor``, actor, SAC temperature and the
    soft target update); returns the loss outputs."""
    out = loss(batch)
    for name in ("actor", "critic", "alpha"):
        if name in optimizers:
            optimizers[name].zero_grad()
    # Each loss sees the other networks detached (and targets carry no gradient), so one
    # backward over the sum gives every network exactly its own gradient.
    sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    optimizers["critic"].step()
    if step_actor:
        optimizers["actor"].step()
        if "alpha" in optimizers:
            optimizers["alpha"].step()
        target_updater.step()
    return out


def make_agent_step(cfg: DictConfig, loss, optimizers: dict, target_updater):
    """The recipe's agent update on a batch, ``agent_step(batch, step_actor)``; with
    ``compile.enabled`` it goes through ``torch.compile`` (``compile.mode``). Compiling
    happens at the first call, and again once for ``step_actor=False`` under TD3's policy
    delay. (The world model's step is :class:`WorldModelTrainer`'s, compiled alike.)"""

    def agent_step(batch, step_actor=True):
        return agent_update(loss, optimizers, target_updater, batch, step_actor)

    if cfg.compile.enabled:
        agent_step = torch.compile(agent_step, mode=cfg.compile.mode)
    return agent_step
