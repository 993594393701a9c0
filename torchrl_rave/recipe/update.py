"""The updates a collected batch pays for: the schedule (:func:`update_on_batch`), one
agent's update step, optionally compiled (:class:`AgentLearner`), and PPO's iteration.

The schedule is written once for any number of seeds: it drives a *learner*, the updates
of a run's seeds, which is :class:`AgentLearner` for a single run and
:class:`~torchrl_rave.recipe.group.GroupLearner` for a seed group (one batched update
of all its seeds). A learner has ``num_seeds``, ``policy_delay``, and four calls:
``pretrain(stop)`` (the world models' pretraining, once; it ends early when ``stop()``
turns true, and the next call takes the rest), ``pretraining_left()`` (the pretraining
steps not taken yet), ``world_model_step()`` (the model steps one agent update owes, each
seed's outputs or ``None``) and ``update(step_actor)`` (one agent update: each seed's
:func:`~torchrl_rave.recipe.metrics.record_update` keywords).

A stop requested in the middle of a batch's updates (Ctrl-C, SIGTERM) ends them after the
current step: the updates not taken stay in ``counters["update_budget"]`` (and the
pretraining steps not taken in the world-model trainers), so the run checkpoints within one
update and a resumed run takes them before it collects again (:func:`batch_cut_short`).

The order of one agent update (``agent_update``, ``critic_first_update``, ``total_loss``)
is :mod:`torchrl_rave.trainers.agent_update`'s, which a seed group's update runs too; the
names still import from here.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.objectives import SACLoss, TD3Loss

from torchrl_rave.objectives import EnsembleDDPGLoss
from torchrl_rave.objectives.compile import compile_loss
from torchrl_rave.recipe.agent import critic_loss_key
from torchrl_rave.recipe.config import learning_start
from torchrl_rave.recipe.metrics import record_update
from torchrl_rave.trainers.agent_update import agent_update, critic_first_update, total_loss

__all__ = [
    "AgentLearner",
    "split_losses",
    "make_agent_step",
    "ppo_update",
    "batch_cut_short",
    "update_on_batch",
]


def split_losses(loss) -> tuple[Callable, Callable]:
    """The critics' and the actor's parts of ``loss``, each ``batch -> {name: output}``,
    for :func:`~torchrl_rave.trainers.agent_update.critic_first_update`:
    ``EnsembleDDPGLoss.loss_value`` / ``loss_actor``,
    ``TD3Loss.value_loss`` / ``actor_loss``, ``SACLoss.qvalue_v2_loss`` / ``actor_loss``
    with the temperature's loss on the actor's draws (as ``SACLoss.forward`` computes it).
    Each part draws its random numbers in the order ``loss(batch)`` draws them."""

    if isinstance(loss, EnsembleDDPGLoss):
        return (
            lambda batch: {"loss_value": loss.loss_value(batch)[0]},
            lambda batch: {"loss_actor": loss.loss_actor(batch)[0]},
        )
    if isinstance(loss, TD3Loss):
        return (
            lambda batch: {"loss_qvalue": loss.value_loss(batch)[0]},
            lambda batch: {"loss_actor": loss.actor_loss(batch)[0]},
        )
    if isinstance(loss, SACLoss) and loss._version == 2:

        def actor(batch):
            alpha = loss._alpha
            loss_actor, meta = loss.actor_loss(batch)
            loss_alpha = loss._reduce_loss(
                loss.alpha_loss(meta["log_prob"]),
                tensordict=batch,
                weights=loss._maybe_get_priority_weight(batch),
            )
            return {"loss_actor": loss_actor, "loss_alpha": loss_alpha, "alpha": alpha}

        return lambda batch: {"loss_qvalue": loss.qvalue_v2_loss(batch)[0]}, actor
    raise TypeError(
        f"optim.critic_first: no critic and actor parts are known for {type(loss).__name__} "
        "(EnsembleDDPGLoss, TD3Loss and SACLoss v2 have them)"
    )


def make_agent_step(cfg: DictConfig, loss, optimizers: dict, target_updater):
    """The recipe's agent update on a batch, ``agent_step(batch, step_actor)``: one
    backward pass over the summed losses
    (:func:`~torchrl_rave.trainers.agent_update.agent_update`), or with
    ``optim.critic_first`` the critics stepped before the actor's loss
    (:func:`~torchrl_rave.trainers.agent_update.critic_first_update`). With
    ``compile.enabled`` each loss forward goes through
    :func:`~torchrl_rave.objectives.compile.compile_loss` (``compile.mode``), compiled at
    the first call. (The world model's step is
    :class:`~torchrl_rave.trainers.WorldModelTrainer`'s, compiled alike.)"""

    def compiled(fn):
        return compile_loss(fn, cfg.compile.mode) if cfg.compile.enabled else fn

    if cfg.optim.critic_first:
        parts = tuple(compiled(part) for part in split_losses(loss))

        def agent_step(batch, step_actor=True):
            return critic_first_update(optimizers, target_updater, batch, parts, step_actor)

        return agent_step
    loss_fn = compiled(total_loss(loss))

    def agent_step(batch, step_actor=True):
        return agent_update(loss, optimizers, target_updater, batch, step_actor, loss_fn)

    return agent_step


def ppo_update(
    cfg: DictConfig, agent, rollout_buffer, data: TensorDictBase, counters: dict
) -> dict[str, list[torch.Tensor]]:
    """One PPO iteration on a freshly collected batch ``data`` (time along its last batch
    dimension): ``ppo.epochs`` passes, each computing GAE with the current value network
    and then taking one clipped-objective step per minibatch of ``rollout_buffer``
    (sampled without replacement). The learning rate follows ``ppo.lr_schedule`` from the
    frames collected before this batch, so a resumed run continues it exactly.
    ``counters["updates"]`` counts minibatch steps. Returns each step's metrics."""
    p, loss, optimizers = cfg.ppo, agent.loss, agent.optimizers
    lr = p.lr
    if p.lr_schedule == "linear":
        before = counters["frames"] - data.numel()
        lr = p.lr * max(0.0, 1.0 - before / cfg.collector.total_frames)
    for opt in optimizers.values():
        for group in opt.param_groups:
            group["lr"] = lr
    params = [q for opt in optimizers.values() for g in opt.param_groups for q in g["params"]]
    acc = defaultdict(list)
    for _ in range(p.epochs):
        with torch.no_grad():
            loss.value_estimator(data)  # advantage and value target, in place
        rollout_buffer.empty()  # exactly this batch: a short last batch leaves nothing stale
        rollout_buffer.extend(data.reshape(-1))
        for batch in rollout_buffer:
            out = loss(batch)
            total = out["loss_objective"] + out["loss_critic"]
            if "loss_entropy" in out.keys():  # noqa: SIM118 (a TensorDict)
                total = total + out["loss_entropy"]
            for opt in optimizers.values():
                opt.zero_grad()
            total.backward()
            if p.max_grad_norm is not None:
                torch.nn.utils.clip_grad_norm_(params, p.max_grad_norm)
            for opt in optimizers.values():
                opt.step()
            counters["updates"] += 1
            acc["train/loss_actor"].append(out["loss_objective"].detach())
            acc["train/loss_critic"].append(out["loss_critic"].detach())
            acc["train/ppo_kl_approx"].append(out["kl_approx"].detach())
            acc["train/ppo_clip_fraction"].append(out["clip_fraction"].detach())
            if "entropy" in out.keys():  # noqa: SIM118
                acc["train/ppo_entropy"].append(out["entropy"].detach())
    acc["train/lr"].append(torch.tensor(lr))
    return acc


class AgentLearner:
    """A single run's learner (see the module's docstring): its agent's own loss,
    optimisers and world-model trainer, each step on a sample of its replay buffer."""

    num_seeds = 1

    def __init__(self, cfg: DictConfig, agent, rb) -> None:
        self.agent, self.rb = agent, rb
        self.policy_delay = cfg.td3.policy_delay if agent.algorithm.loss == "td3" else 1
        self._step = make_agent_step(cfg, agent.loss, agent.optimizers, agent.target_updater)
        self._critic_key = critic_loss_key(agent.loss)

    def pretrain(self, stop: Callable[[], bool] | None = None) -> None:
        if self.agent.world_model_trainer is not None:
            self.agent.world_model_trainer.pretrain(self.rb, stop)

    def pretraining_left(self) -> int:
        trainer = self.agent.world_model_trainer
        return 0 if trainer is None else trainer.pretraining_left

    def world_model_step(self) -> list | None:
        trainer = self.agent.world_model_trainer
        return None if trainer is None else [trainer.step(self.rb)]

    def update(self, step_actor: bool) -> list[dict]:
        out = self._step(self.rb.sample(), step_actor)
        diagnostics = None
        if self.agent.algorithm.model_based:
            estimator = self.agent.loss.value_estimator
            diag, keys = estimator.diagnostics, estimator.tensor_keys
            diagnostics = (
                diag[keys.alpha],
                diag[keys.horizon_weights],
                diag[keys.horizon_variance],
            )
        return [dict(
            critic_loss=out[self._critic_key].detach(),
            actor_loss=out["loss_actor"].detach() if step_actor else None,
            temperature=out["alpha"].detach() if "alpha" in out.keys() else None,  # noqa: SIM118
            diagnostics=diagnostics,
        )]  # fmt: skip


def update_on_batch(
    cfg: DictConfig,
    learner,
    counters: dict,
    n_frames: int,
    stop: Callable[[], bool] | None = None,
) -> list[dict[str, list[torch.Tensor]]]:
    """The updates a batch of ``n_frames`` new frames (per seed) pays for: ``optim.utd_ratio``
    per frame once the learning starts, the world models pretrained first (once), each
    agent update after the model steps it owes, the actor every ``policy_delay`` updates.
    Returns each seed's training metrics of every update.

    ``stop`` is asked before every pretraining step and every update; once it returns
    ``True`` the rest is left owed (see the module's docstring). With ``n_frames=0`` the
    call takes only what an earlier call left owed."""
    acc = [defaultdict(list) for _ in range(learner.num_seeds)]
    start_frames = learning_start(cfg)[0]
    if counters["frames"] < start_frames:
        return acc
    new_frames = min(n_frames, counters["frames"] - start_frames)
    counters["update_budget"] += cfg.optim.utd_ratio * new_frames
    learner.pretrain(stop)  # once, as soon as F frames are stored
    if learner.pretraining_left():  # stopped: the updates wait for the rest of it
        return acc
    n_updates = int(counters["update_budget"])
    counters["update_budget"] -= n_updates
    for k in range(n_updates):
        if stop is not None and stop():
            counters["update_budget"] += n_updates - k  # owed
            break
        wm = learner.world_model_step()
        step_actor = counters["updates"] % learner.policy_delay == 0
        outs = learner.update(step_actor)
        counters["updates"] += 1
        for i, out in enumerate(outs):
            record_update(acc[i], world_model=None if wm is None else wm[i], **out)
    return acc


def batch_cut_short(cfg: DictConfig, learner, counters: dict) -> bool:
    """Whether a stop left updates of the last batch owed (:func:`update_on_batch` with
    ``stop``): pretraining steps once learning has started, or whole agent updates."""
    if learner is None or counters["frames"] < learning_start(cfg)[0]:
        return False
    return counters["update_budget"] >= 1 or learner.pretraining_left() > 0
