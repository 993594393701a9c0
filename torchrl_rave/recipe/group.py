"""What the recipe's loop (:mod:`torchrl_rave.recipe.loop`) needs for ``seeds=[...]``: the
group's file (``<run_dir>/group.json``, its config), each seed's config, the newest
checkpoint every seed has, and the group's learner (:class:`GroupLearner`: every seed's
update as one call of a :class:`~torchrl_rave.trainers.SeedGroup`, on samples drawn by
:class:`GroupSampler`).

A group's seeds are ordinary runs, each in ``<run_dir>/seed<s>/``; the loop's docstring
says how they advance and draw their random numbers.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Callable
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase
from torchrl.data import RandomSampler, TensorDictReplayBuffer, TensorStorage

from torchrl_rave.recipe.agent import Agent, make_seed_group
from torchrl_rave.recipe.checkpoint import (
    PREFIX,
    DamagedCheckpoint,
    DamagedCheckpointWarning,
    read_group_file,
)
from torchrl_rave.recipe.config import GROUP_ALGORITHMS, ConfigError, check_group

__all__ = [
    "GROUP_ALGORITHMS",
    "GROUP_FILE",
    "GroupLearner",
    "GroupSampler",
    "check_group",
    "common_checkpoint",
    "group_config",
    "saved_group_config",
    "seed_config",
    "write_group_file",
]

GROUP_FILE = "group.json"


def group_config(run_dir: str | Path) -> dict:
    """The config a group was last saved with (``<run_dir>/group.json``), as a dict."""
    return read_group_file(run_dir)


def saved_group_config(root: Path, cfg: DictConfig) -> DictConfig:
    """The config the group at ``root`` was saved with, for ``resume=root`` with ``cfg``:
    refused when ``root`` holds one run, when ``cfg.seeds`` differ from the group's, or
    when a seed's directory is missing."""
    if not (root / GROUP_FILE).is_file():
        raise ConfigError([
            f"resume={str(root)!r} holds one run, not a seed group ({GROUP_FILE} is "
            "missing): resume it without seeds=, or start a new group elsewhere"
        ])  # fmt: skip
    saved = OmegaConf.create(group_config(root))
    if list(saved.seeds) != list(cfg.seeds):
        raise ConfigError([
            f"resume={str(root)!r}: config key seeds is {list(cfg.seeds)} but the group "
            f"was started with {list(saved.seeds)}; it cannot change on resume (train "
            "other seeds as a new group)"
        ])  # fmt: skip
    missing = [s for s in cfg.seeds if not (root / f"seed{s}").is_dir()]
    if missing:
        raise ConfigError([
            f"resume={str(root)!r}: {GROUP_FILE} names seed(s) {missing} that have no "
            f"seed<s>/ directory under it; the file was edited, or a seed's directory "
            "removed: restore it from a copy of the run directory"
        ])  # fmt: skip
    return saved


def seed_config(cfg: DictConfig, seed: int) -> DictConfig:
    """A group's ``cfg`` as seed ``seed``'s own run: its ``env.seed``, no ``seeds``."""
    one = cfg.copy()
    one.env.seed = seed
    one.seeds = None
    one.resume = None
    return one


def write_group_file(run_dir: Path, cfg: DictConfig) -> None:
    """Saves the group's ``cfg`` as ``<run_dir>/group.json`` (written whole, then renamed)."""
    tmp = run_dir / f".{GROUP_FILE}.tmp"
    tmp.write_text(json.dumps({"config": OmegaConf.to_container(cfg, resolve=True)}, indent=1))
    os.replace(tmp, run_dir / GROUP_FILE)


def common_checkpoint(seeds) -> int:
    """The newest frame count every seed (``.checkpoint``, ``.dir``) has an undamaged
    checkpoint of. Damaged
    checkpoints newer than it are set aside (``checkpoints/damaged/``) with a warning that
    names them, as a single run's resume does; with none in common, the error names each
    damaged one and why."""
    common, damaged = None, []
    for s in seeds:
        frames = set()
        for path in s.checkpoint.checkpoints():
            try:
                s.checkpoint.verify(path)
            except DamagedCheckpoint as err:  # skipped, as RunCheckpoint.load skips it
                damaged.append((s, path, str(err)))
                continue
            frames.add(int(path.name[len(PREFIX) :]))
        common = frames if common is None else common & frames
    if not common:
        why = f"; damaged: {'; '.join(r for *_, r in damaged)}" if damaged else ""
        raise FileNotFoundError(
            "no checkpoint that every seed of the group has: resume needs one "
            f"(under {[str(s.dir) for s in seeds]}){why}"
        )
    frame = max(common)
    newer = [(s, p, r) for s, p, r in damaged if int(p.name[len(PREFIX) :]) > frame]
    if newer:
        for s, path, _ in newer:
            s.checkpoint.set_aside([path])
        warnings.warn(
            f"skipped damaged checkpoint(s) (moved to checkpoints/damaged/): "
            f"{'; '.join(r for *_, r in newer)}; the group resumes from frame {frame}, the "
            "newest that every seed has",
            DamagedCheckpointWarning,
            stacklevel=3,
        )
    return frame


class GroupLearner:
    """A seed group's learner (see :mod:`torchrl_rave.recipe.update`): every update is one
    call of the :class:`~torchrl_rave.trainers.SeedGroup` on each seed's own sample. The
    group's optimisers hold every seed's moments; each seed's world-model trainer keeps its
    schedule (:meth:`~torchrl_rave.trainers.WorldModelTrainer.schedule`) and, at each
    checkpoint (:meth:`before_save`), its seed's slice of the moments, so that a seed's
    checkpoint is an ordinary run's."""

    def __init__(self, cfg: DictConfig, agents: list[Agent], rbs: list, streams) -> None:
        self.group = make_seed_group(cfg, agents, streams=streams)
        self.num_seeds = len(agents)
        self.policy_delay = cfg.td3.policy_delay if cfg.algorithm == "td3" else 1
        self.rbs = rbs
        self.trainers = [a.world_model_trainer for a in agents if a.world_model_trainer]
        self._optimizers = [_optimizers(a) for a in agents]
        self.group.import_optimizer_states(self._optimizers)
        self._sampler = None

    def before_save(self) -> None:
        """Each seed's slice of the group's optimiser states into its learner's own."""
        self.group.export_optimizer_states(self._optimizers)

    def _sample(self) -> TensorDictBase:
        if self._sampler is None or self._sampler.keys is None:  # until the buffers fill
            self._sampler = GroupSampler(self.rbs, self.group)
        return self._sampler()

    def _model_steps(self, call: bool, most: int | None = None):
        owed = {t.schedule(call, most) for t in self.trainers}  # the seeds advance in lockstep
        if len(owed) != 1:
            raise RuntimeError(f"the seeds' world-model schedules disagree: {owed} steps owed")
        out = None
        for _ in range(owed.pop()):
            out = self.group.update_world_model(self._sample())
        return out

    def pretrain(self, stop: Callable[[], bool] | None = None) -> None:
        """Every seed's pretraining steps, one group step at a time (see
        :meth:`~torchrl_rave.trainers.WorldModelTrainer.pretrain`)."""
        while self.pretraining_left() and not (stop is not None and stop()):
            self._model_steps(call=False, most=1)

    def pretraining_left(self) -> int:
        return max((t.pretraining_left for t in self.trainers), default=0)

    def world_model_step(self):
        return self._model_steps(call=True) if self.trainers else None

    def update(self, step_actor: bool) -> list[dict]:
        group = self.group
        out = group.update(self._sample(), step_actor)
        keys = group.diagnostic_keys if group.expanding else None
        return [dict(
            critic_loss=out["loss_value"][i],
            actor_loss=out["loss_actor"][i] if step_actor else None,
            temperature=out["alpha"][i] if group.sac else None,
            diagnostics=None if keys is None else
            (out[keys.alpha][i], out[keys.horizon_weights][i], out[keys.horizon_variance][i]),
        ) for i in range(self.num_seeds)]  # fmt: skip


class GroupSampler:
    """Every seed's replay-buffer sample as one ``[S, B]`` batch, holding the entries the
    seed group reads (:meth:`~torchrl_rave.trainers.SeedGroup.batch_keys`).

    Each seed's rows are the ones its own ``rb.sample()`` would give: its buffer's sampler
    draws the indices under the seed's stream, as ``rb.sample()`` draws them, and leaves
    the stream where ``rb.sample()`` leaves it. Only the five entries the group reads are
    gathered, from each seed's storage. ``rb.sample()`` per seed and a stack of the
    samples gather all of a run's 17 (``done``, ``truncated``, the step count, the
    collector's ids, ...) through TensorDict indexing: 2.8 ms against 0.5 ms for a batch
    of 8 seeds, about a tenth of a RAVE group's update step (``python
    benchmarks/seed_group.py --sampling``). Buffers of another kind (not a
    ``TensorDictReplayBuffer`` over a ``TensorStorage`` with a ``RandomSampler``, or with
    a transform), and buffers that hold no data yet, are sampled by ``rb.sample()`` and
    stacked."""

    def __init__(self, rbs, group) -> None:
        self.rbs, self.streams = list(rbs), group.streams
        direct = all(
            isinstance(rb, TensorDictReplayBuffer)
            and type(rb.sampler) is RandomSampler
            and isinstance(rb.storage, TensorStorage)
            and rb.storage.initialized
            and (rb.transform is None or len(rb.transform) == 0)
            and getattr(rb, "_sample_unit", None) is None
            for rb in self.rbs
        )
        #: the entries gathered straight from the storages; ``None``: ``rb.sample()``
        self.keys = (
            group.batch_keys(self.rbs[0].storage._storage.keys(True, True)) if direct else None
        )

    def __call__(self) -> TensorDictBase:
        rbs = self.rbs
        if self.keys is None:
            return self.streams.stack(lambda i: rbs[i].sample())
        index = self.streams.stack(
            lambda i: rbs[i].sampler.sample(rbs[i].storage, rbs[i].batch_size)[0]
        )
        stores = [rb.storage._storage for rb in rbs]  # the TensorDict of each storage
        return TensorDict(
            {key: torch.stack([st.get(key)[idx] for st, idx in zip(stores, index, strict=True)])
             for key in self.keys},
            batch_size=index.shape,
        )  # fmt: skip


def _optimizers(agent: Agent) -> list[torch.optim.Optimizer]:
    opts = list(agent.optimizers.values())
    if agent.world_model_trainer is not None:
        opts.append(agent.world_model_trainer.optimizer)
    return opts
