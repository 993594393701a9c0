"""Trains the world model beside an agent: loss, optimiser, normalisers and pretraining."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import ReplayBuffer
from torchrl.trainers import Trainer, TrainerHookBase

from torchrl_rave._checks import POSITIVE, check_positive_int
from torchrl_rave.modules.world_model import WorldModelEnsemble
from torchrl_rave.objectives.compile import compile_loss
from torchrl_rave.objectives.world_model_loss import WorldModelEnsembleLoss

__all__ = ["WorldModelTrainer"]


class WorldModelTrainer(TrainerHookBase):
    """Owns a :class:`~torchrl_rave.modules.WorldModelEnsemble`'s training schedule.

    Two calls fit any collector loop:

    - :meth:`extend` on every batch that enters the replay buffer: it merges the batch
      into the model's input and target normalisers (the model is trained and queried in
      normalised units, so skipping this leaves it on identity statistics).
    - :meth:`step` once per agent update, with the replay buffer: the first call pretrains
      the model (``pretrain_updates`` steps, paper: on the first ``F`` frames); after that
      it takes one model step every ``train_every`` calls. Start agent updates (and so
      these calls) once ``F`` frames are stored, e.g. with the collector's
      ``init_random_frames``.

    Each model step samples its own batch, moves it to the model's device (TorchRL's
    scripts keep the replay buffer on the CPU and the models on
    ``get_available_device()``; :meth:`extend` moves its batch likewise), computes
    :class:`~torchrl_rave.objectives.WorldModelEnsembleLoss` (transition + reward +
    termination) and takes one optimiser step, whose loss terms :meth:`step` returns for
    logging. ``state_dict``
    holds the optimiser and the schedule, so a resumed run continues it exactly.
    As a :class:`~torchrl.trainers.TrainerHookBase`, :meth:`register` hooks the same two
    calls into a TorchRL ``Trainer``.

    Args:
        world_model (WorldModelEnsemble): the ensemble to train.

    Keyword Args:
        lr (float): Adam learning rate. Defaults to 3e-4 (paper).
        pretrain_updates (int): model steps taken at the first :meth:`step`. Defaults to 500.
        train_every (int): one model step every this many :meth:`step` calls. Defaults to 1.
        loss (WorldModelEnsembleLoss, optional): defaults to one on ``world_model``.
        optimizer (torch.optim.Optimizer, optional): defaults to Adam over the model's
            parameters.

    Examples:
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> wm = WorldModelEnsemble(3, 1, num_models=2)
        >>> trainer = WorldModelTrainer(wm, pretrain_updates=5)
        >>> rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=16)
        >>> data = TensorDict(
        ...     observation=torch.randn(50, 3), action=torch.rand(50, 1),
        ...     next=TensorDict(observation=torch.randn(50, 3), reward=torch.randn(50, 1),
        ...                     terminated=torch.zeros(50, 1, dtype=torch.bool), batch_size=[50]),
        ...     batch_size=[50])
        >>> _ = rb.extend(data)
        >>> trainer.extend(data)          # normalisers, on every batch that enters the buffer
        >>> out = trainer.step(rb)        # first call: 5 pretraining steps, then one step
        >>> trainer.updates, sorted(out.keys())[:3]
        (6, ['loss_reward', 'loss_termination', 'loss_transition'])
    """

    def __init__(
        self,
        world_model: WorldModelEnsemble,
        *,
        lr: float = 3e-4,
        pretrain_updates: int = 500,
        train_every: int = 1,
        loss: WorldModelEnsembleLoss | None = None,
        optimizer: torch.optim.Optimizer | None = None,
    ) -> None:
        check_positive_int("pretrain_updates", pretrain_updates, minimum=0)
        check_positive_int("train_every", train_every)
        POSITIVE.check("lr", float(lr) if isinstance(lr, (int, float)) else lr)  # NaN too
        self.world_model = world_model
        self.loss = loss if loss is not None else WorldModelEnsembleLoss(world_model)
        # fused Adam: one kernel per step instead of a Python loop over tensors
        self.optimizer = optimizer or torch.optim.Adam(
            list(world_model.parameters()), lr=lr, fused=True
        )
        self.pretrain_updates = pretrain_updates
        self.train_every = train_every
        self.pretrain_steps = 0  # pretraining steps taken (a stop may cut pretraining short)
        self.calls = 0  # step() calls: one per agent update
        self.updates = 0  # optimiser steps taken
        self._loss_total = self._loss_total_eager

    # ---------------------------------------------------------------- the loop
    @property
    def device(self) -> torch.device:
        """The world model's device, where every batch is moved before use."""
        return next(self.world_model.parameters()).device

    def extend(self, data: TensorDictBase) -> None:
        """Merges a batch of real transitions (on any device) into the model's normalisers."""
        self.world_model.update_normalizers_from(self._on_device(data))

    def step(self, source: ReplayBuffer | TensorDictBase) -> TensorDictBase | None:
        """Call once per agent update; returns the last model step's loss outputs
        (detached), or ``None`` when this call took no step.

        Args:
            source: the replay buffer (each model step samples its own batch) or a batch
                (every step of this call, pretraining included, uses it).
        """
        return self._take(self.schedule(), source)

    def pretrain(
        self, source: ReplayBuffer | TensorDictBase, stop: Callable[[], bool] | None = None
    ) -> TensorDictBase | None:
        """The ``pretrain_updates`` steps, once; :meth:`step` calls it, and a loop may call
        it earlier (as soon as ``F`` frames are stored). Returns the last step's outputs.

        With ``stop``, asked before each step, pretraining ends early once it returns
        ``True``; the steps taken are counted (also in :meth:`state_dict`), and the next
        call takes the rest, so a run stopped in the middle of a long pretraining resumes
        it where it stopped."""
        out = None
        while self.pretraining_left and not (stop is not None and stop()):
            out = self._take(self.schedule(call=False, most=1), source)
        return out

    @property
    def pretraining_left(self) -> int:
        """The pretraining steps not taken yet."""
        return max(self.pretrain_updates - self.pretrain_steps, 0)

    @property
    def pretrained(self) -> bool:
        """Whether every pretraining step has been taken."""
        return not self.pretraining_left

    def schedule(self, call: bool = True, most: int | None = None) -> int:
        """Advances the schedule as :meth:`step` (``call=True``) or :meth:`pretrain`
        (``call=False``) does, and returns the number of model steps that call takes (the
        pretraining's at the first, then one every ``train_every`` calls), counted in
        ``updates`` as taken. :meth:`step` and :meth:`pretrain` then take them; a
        caller that takes them itself (a seed group steps all its seeds' models as one)
        uses this alone, so that each seed's trainer keeps its schedule for checkpoints.
        ``most`` bounds the pretraining steps counted by this call (``call=False``: one at
        a time, for a pretraining that can stop between steps)."""
        n = self.pretraining_left
        if most is not None:
            n = min(n, most)
        self.pretrain_steps += n
        if call:
            n += self.calls % self.train_every == 0
            self.calls += 1
        self.updates += n
        return n

    def _take(self, n: int, source) -> TensorDictBase | None:
        out = None
        for _ in range(n):
            out = self._update(self._on_device(self._batch(source)))
        return out

    def update(self, batch: TensorDictBase) -> TensorDictBase:
        """One optimiser step of the model on ``batch`` (moved to the model's device);
        returns the loss outputs."""
        self.updates += 1
        return self._update(self._on_device(batch))

    def compile(self, mode: str | None = None) -> WorldModelTrainer:
        """Runs :meth:`update`'s loss forward (and so its backward) through
        ``torch.compile``; the optimiser step stays eager, see
        :func:`~torchrl_rave.objectives.compile.compile_loss`."""
        self._loss_total = compile_loss(self._loss_total_eager, mode)
        return self

    @staticmethod
    def _batch(source) -> TensorDictBase:
        return source.sample() if isinstance(source, ReplayBuffer) else source

    def _on_device(self, data: TensorDictBase) -> TensorDictBase:
        device = self.device
        if data.device == device:
            return data
        return data.to(device, non_blocking=device.type == "cuda")  # to a GPU: stream-ordered

    def _loss_total_eager(self, batch: TensorDictBase):
        out = self.loss(batch)
        return out, out["loss_transition"] + out["loss_reward"] + out["loss_termination"]

    def _update(self, batch: TensorDictBase) -> TensorDictBase:
        out, total = self._loss_total(batch)
        self.optimizer.zero_grad()
        total.backward()
        self.optimizer.step()
        return out.detach()

    # ------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """The optimiser and the schedule (the model's weights live in its own ``state_dict``)."""
        return {
            "optimizer": self.optimizer.state_dict(),
            "pretrained": self.pretrained,
            "pretrain_steps": self.pretrain_steps,
            "calls": self.calls,
            "updates": self.updates,
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.optimizer.load_state_dict(state_dict["optimizer"])
        # a checkpoint written before pretraining could stop early holds only the flag
        done = self.pretrain_updates if state_dict["pretrained"] else 0
        self.pretrain_steps = int(state_dict.get("pretrain_steps", done))
        self.calls = int(state_dict["calls"])
        self.updates = int(state_dict["updates"])

    # ------------------------------------------------------------ TorchRL Trainer
    def register(
        self,
        trainer: Trainer,
        name: str = "world_model_trainer",
        replay_buffer: ReplayBuffer | None = None,
    ) -> None:
        """Hooks :meth:`extend` into ``batch_process`` (every collected batch) and
        :meth:`step` into ``process_optim_batch`` (every agent update; the model samples
        ``replay_buffer`` when given, else trains on the agent's batch)."""

        def extend(batch: TensorDictBase) -> TensorDictBase:
            self.extend(batch.reshape(-1))
            return batch

        def step(batch: TensorDictBase) -> TensorDictBase:
            self.step(replay_buffer if replay_buffer is not None else batch)
            return batch

        trainer.register_op("batch_process", extend)
        trainer.register_op("process_optim_batch", step)
        trainer.register_module(name, self)
