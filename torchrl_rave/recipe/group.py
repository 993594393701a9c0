"""The recipe with ``seeds=[...]``: S independent runs trained by one process, their updates
batched across seeds (:class:`~torchrl_rave.trainers.SeedGroup`).

Each seed is an ordinary run of its own, written to ``<run_dir>/seed<s>/``: its own train and
evaluation envs seeded with its seed, replay buffer, world model, critics, actor, optimiser
state and exploration noise, and its own metrics and checkpoints, which every reader of a
run directory (``read_scalar``, ``load_policy``, the analysis scripts) takes as they are.
The seeds advance in lockstep: every collector gives one batch, every replay buffer takes
its own, and the batch's updates run for all seeds at once. ``<run_dir>/group.json`` holds
the group's config; ``resume=<run_dir>`` continues every seed from the newest checkpoint
all of them have.

Each seed also has its own random stream (:class:`~torchrl_rave.trainers.SeedStreams`):
its networks are initialised after ``torch.manual_seed(seed)``, as a single run's are, and
everything drawn for it afterwards (random and exploratory actions, replay sampling, the
world model's bootstrap and rollouts, TD3's and SAC's noise) comes from its stream, in a
single run's order. So a seed draws the same numbers in any group, alone or not, as a
single run of that seed does; what can still differ is float rounding of the batched
kernels.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
import warnings
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase
from torchrl.checkpoint import GlobalRNGState
from torchrl.data import RandomSampler, TensorDictReplayBuffer, TensorStorage

from torchrl_rave.recipe.agent import (
    Agent,
    make_agent,
    make_env,
    make_replay_buffer,
    make_seed_group,
    q_at_points,
)
from torchrl_rave.recipe.checkpoint import (
    PREFIX,
    DamagedCheckpoint,
    DamagedCheckpointWarning,
    RunCheckpoint,
    read_group_file,
)
from torchrl_rave.recipe.collect import (
    NonFiniteEnvOutput,
    StopRequest,
    check_finite,
    guarded_batches,
    make_collector,
    push_or_stop,
    shutdown_on_error,
    stop_run,
)
from torchrl_rave.recipe.config import (
    ConfigError,
    apply_process_settings,
    check_resumable,
    learning_start,
    replay_buffer_size,
)
from torchrl_rave.recipe.episode import EpisodeCheckpoint, resume_collecting
from torchrl_rave.recipe.evaluate import evaluate_agent, make_logger
from torchrl_rave.recipe.loop import batch_metrics, nothing_to_train, record_update
from torchrl_rave.trainers import SeedStreams

__all__ = [
    "GROUP_ALGORITHMS",
    "GROUP_FILE",
    "GroupSampler",
    "check_group",
    "group_config",
    "train_group",
]

#: the algorithms a seed group trains (ppo runs one seed per process)
GROUP_ALGORITHMS = ("ddpg", "mve", "steve", "rave", "rave_constant", "td3", "sac")
GROUP_FILE = "group.json"


def check_group(cfg: DictConfig) -> list[str]:
    """The problems of ``seeds=`` with the rest of ``cfg`` (empty when it can run)."""
    seeds = list(cfg.seeds)
    problems = []
    if not seeds or len(set(seeds)) != len(seeds):
        problems.append(f"config key seeds={seeds}: expected a list of distinct seeds")
    if cfg.algorithm not in GROUP_ALGORITHMS:
        problems.append(
            f"config key seeds={seeds}: a seed group trains {', '.join(GROUP_ALGORITHMS)}; "
            f"algorithm={cfg.algorithm} runs one seed per process (leave seeds unset)"
        )
    if cfg.get("curriculum") is not None and cfg.curriculum.kwarg is not None:
        problems.append("config key seeds: a seed group does not run a curriculum")
    reward = cfg.get("reward")
    if reward is not None and (reward.weights is not None or reward.delayed is not None):
        problems.append("config key seeds: a seed group does not relabel reward terms")
    if cfg.compile.enabled:
        problems.append("config key seeds: a seed group's update is not compiled; set "
                        "compile.enabled=false")  # fmt: skip
    return problems


def group_config(run_dir: str | Path) -> dict:
    """The config a group was last saved with (``<run_dir>/group.json``), as a dict."""
    return read_group_file(run_dir)


def _write_group_file(run_dir: Path, cfg: DictConfig) -> None:
    tmp = run_dir / f".{GROUP_FILE}.tmp"
    tmp.write_text(json.dumps({"config": OmegaConf.to_container(cfg, resolve=True)}, indent=1))
    os.replace(tmp, run_dir / GROUP_FILE)


@dataclass
class _Seed:
    """One seed's run: its config, directory and everything it owns."""

    seed: int
    cfg: DictConfig
    dir: Path
    env: object
    eval_env: object
    agent: Agent
    rb: object
    checkpoint: RunCheckpoint
    logger: object = None
    collector: object = None
    episode: EpisodeCheckpoint = field(default_factory=EpisodeCheckpoint)
    rng_at_load: dict | None = None  # its stream as its checkpoint saved it


def _seed_config(cfg: DictConfig, seed: int) -> DictConfig:
    one = cfg.copy()
    one.env.seed = seed
    one.seeds = None
    one.resume = None
    return one


def _common_checkpoint(seeds: list[_Seed]) -> int:
    """The newest frame count every seed has an undamaged checkpoint of. Damaged
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


def train_group(cfg: DictConfig, run_dir: str) -> dict[str, float]:
    """Trains (or, with ``cfg.resume`` set, continues) the runs of ``cfg.seeds`` as one
    group into ``run_dir``; returns each seed's final evaluation metrics under
    ``seed<s>/<metric>`` and their mean over seeds under ``<metric>``."""
    problems = check_group(cfg)
    if problems:
        raise ConfigError(problems)
    cfg = cfg.copy()
    root = Path(cfg.resume or run_dir)
    if cfg.resume:
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
        check_resumable(cfg, saved)
        cfg.replay_buffer.size = saved.replay_buffer.size
    else:
        cfg.replay_buffer.size = replay_buffer_size(cfg)
    device = torch.device(cfg.collector.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    apply_process_settings(cfg)

    record = cfg.collector.backend == "direct"  # in-process envs keep their episodes
    seeds: list[_Seed] = []
    rng = SeedStreams(len(cfg.seeds), device)
    for i, seed in enumerate(cfg.seeds):
        one = _seed_config(cfg, int(seed))
        torch.manual_seed(one.env.seed)  # the single run's initialisation, seed by seed
        env = make_env(one, device, record_episode=record)
        eval_env = make_env(one, device)
        agent = make_agent(one, env, device)
        seed_dir = root / f"seed{seed}"
        seed_dir.mkdir(parents=True, exist_ok=True)
        seeds.append(_Seed(int(seed), one, seed_dir, env, eval_env, agent,
                           make_replay_buffer(one, device), RunCheckpoint(seed_dir)))  # fmt: skip
        rng.capture(i)  # from here on, seed i draws from its own stream
    transition = seeds[0].env.fake_tensordict()
    for s in seeds:
        s.checkpoint.preflight(
            lambda block, a=s.agent: a.checkpoint_bytes(cfg.replay_buffer.size, transition, block)
        )
    counters = {"frames": 0, "updates": 0, "update_budget": 0.0, "curriculum_stage": 0}
    counters.update(next_eval=cfg.eval.interval, next_checkpoint=cfg.checkpoint.interval)
    logger_states = [{} for _ in seeds]
    if cfg.resume:
        frame = _common_checkpoint(seeds)
        for i, s in enumerate(seeds):
            own = dict(counters)
            path = s.checkpoint.root / f"{PREFIX}{frame:012d}"
            with rng.use(i):  # restores seed i's stream as its checkpoint saved it
                s.checkpoint.load(
                    path=path, counters=own, replay_buffer=s.rb, logger=logger_states[i],
                    **s.agent.state_components(),
                )  # fmt: skip
                s.rng_at_load = GlobalRNGState().state_dict()
            s.episode.load_state_dict(s.checkpoint.read_optional("episode", path))
            if i == 0:
                counters.update(own)
    for s, state in zip(seeds, logger_states, strict=True):
        s.logger = make_logger(s.cfg, str(s.dir), state or None)
    group = make_seed_group(cfg, [s.agent for s in seeds], streams=rng)
    learner_optimizers = [_optimizers(s.agent) for s in seeds]
    group.import_optimizer_states(learner_optimizers)
    for i, s in enumerate(seeds):
        with rng.use(i):
            s.env.set_seed(s.seed + counters["frames"])

    def save_checkpoint():
        group.export_optimizer_states(learner_optimizers)
        _write_group_file(root, cfg)
        paths = []
        for i, s in enumerate(seeds):
            with rng.use(i):  # the checkpoint's random state is seed i's stream
                paths.append(s.checkpoint.save(
                    counters["frames"],
                    config=OmegaConf.to_container(s.cfg, resolve=True),
                    counters=dict(counters),
                    replay_buffer=s.rb,
                    logger={} if s.logger is None else s.logger.state_dict(),
                    episode=s.episode,
                    **s.agent.state_components(),
                ))  # fmt: skip
        return paths

    def save_after_failure():
        # mid-batch (a hung or failed collector) or a dropped batch (NaN): the episodes
        # no longer match the saved frames; a resumed group starts new ones
        for s in seeds:
            s.episode.attach(None, None)
        return save_checkpoint()

    total = cfg.collector.total_frames
    last = [{} for _ in seeds]
    start, frames_at_start = time.perf_counter(), counters["frames"]
    with StopRequest() as stop, contextlib.ExitStack() as on_error:
        for s in seeds:  # on an error, no seed's workers outlive the run
            on_error.enter_context(shutdown_on_error(lambda s=s: s.collector))
        # no collectors for a group resumed at or past its total (a collector of no frames
        # would fail), as the single run's loop does not start then
        collecting = seeds if counters["frames"] < total else []
        for i, s in enumerate(collecting):
            with rng.use(i):
                s.collector = make_collector(
                    s.cfg, s.env, s.agent.policy, device, counters["frames"]
                )
                s.episode.attach(s.env, s.collector)
                if s.rng_at_load is not None:  # a resumed seed continues its episode
                    resume_collecting(s.episode, s.env, s.collector, s.seed + counters["frames"],
                                      s.rng_at_load)  # fmt: skip
                    s.rng_at_load = None
        iterators = [
            guarded_batches(s.collector, s.cfg, save_after_failure, lambda: counters["frames"],
                            str(s.dir))
            for s in collecting
        ]  # fmt: skip
        t_collect = time.perf_counter()
        for batches in _lockstep(iterators, rng):
            collect_s = time.perf_counter() - t_collect
            data = [b.reshape(-1) for b in batches]
            for s, d in zip(seeds, data, strict=True):
                bad = check_finite(d)
                if bad is not None:
                    where = stop_run(s.collector, save_after_failure)
                    raise NonFiniteEnvOutput(
                        f"{cfg.env.name} (seed {s.seed}) produced {bad} within frames "
                        f"{counters['frames']}-{counters['frames'] + d.numel()}; {where}: fix "
                        f"the env and rerun with resume={root}"
                    )
            counters["frames"] += data[0].numel()
            t_update = time.perf_counter()
            for s, d in zip(seeds, data, strict=True):
                s.rb.extend(d)
                if s.agent.world_model_trainer is not None:
                    s.agent.world_model_trainer.extend(d)
            acc = update_group_on_batch(cfg, seeds, group, counters, data[0].numel())
            update_s = time.perf_counter() - t_update
            for s in seeds:
                push_or_stop(s.collector, s.agent.policy, s.cfg, save_after_failure,
                             counters["frames"], str(s.dir))  # fmt: skip
            frames_now = counters["frames"]
            evaluate = frames_now >= counters["next_eval"] or frames_now >= total
            fps = (frames_now - frames_at_start) / (time.perf_counter() - start)
            for i, (s, d) in enumerate(zip(seeds, data, strict=True)):
                metrics = batch_metrics(acc[i], d, collect_s, update_s, fps)
                if evaluate:
                    t_eval = time.perf_counter()
                    with rng.use(i):
                        s.eval_env.set_seed(s.seed + 1_000_003 + frames_now)
                        last[i] = evaluate_agent(s.cfg, s.eval_env, s.agent)
                    metrics.update(last[i])
                    metrics["time/eval_s"] = time.perf_counter() - t_eval
                metrics.update(q_at_points(s.agent.loss, cfg.logger.q_points, cfg.env.reward_scale))
                if s.logger is not None:
                    for key, value in metrics.items():
                        s.logger.log_scalar(key, value, step=frames_now)
            if evaluate:
                while counters["next_eval"] <= frames_now:
                    counters["next_eval"] += cfg.eval.interval
            if frames_now >= counters["next_checkpoint"] or frames_now >= total or stop.requested:
                while counters["next_checkpoint"] <= frames_now:
                    counters["next_checkpoint"] += cfg.checkpoint.interval
                save_checkpoint()
            if stop.requested or frames_now >= total:
                break
            t_collect = time.perf_counter()
    for s in seeds:
        if s.collector is not None:
            s.collector.shutdown()
    if stop.requested:
        print(f"stopped at frame {counters['frames']}; resume with resume={root}")
    elif not last[0]:  # a group resumed from its final checkpoint
        print(nothing_to_train("group", counters["frames"], cfg.collector.total_frames))
        for i, s in enumerate(seeds):
            with rng.use(i):
                s.eval_env.set_seed(s.seed + 1_000_003 + counters["frames"])
                last[i] = evaluate_agent(s.cfg, s.eval_env, s.agent)
    for s in seeds:
        if s.logger is not None and hasattr(s.logger, "shutdown"):
            s.logger.shutdown()
    out: dict[str, float] = {}
    for s, metrics in zip(seeds, last, strict=True):
        out.update({f"seed{s.seed}/{k}": v for k, v in metrics.items()})
        if metrics:
            print(f"{cfg.algorithm} on {cfg.env.name}, seed {s.seed}: eval/return "
                  f"{metrics['eval/return']:.1f}, run directory {s.dir}")  # fmt: skip
    for key in last[0]:
        out[key] = sum(m[key] for m in last) / len(last)
    return out


def _lockstep(iterators, rng: SeedStreams):
    """One batch of every seed's collector, each drawn under its seed's stream, until the
    first runs out (at once, for no collectors)."""
    while iterators:
        batches = []
        for i, it in enumerate(iterators):
            with rng.use(i):
                batch = next(it, None)
            if batch is None:
                return
            batches.append(batch)
        yield batches


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


def update_group_on_batch(cfg: DictConfig, seeds, group, counters: dict, n_frames: int):
    """The updates a batch of ``n_frames`` new frames (per seed) pays for, as
    :func:`~torchrl_rave.recipe.loop.update_on_batch` for one run: the same schedule, the
    world model's pretraining and ``train_every``, every step one group call on the seeds'
    own samples. Returns each seed's training metrics."""
    acc = [defaultdict(list) for _ in seeds]
    start_frames = learning_start(cfg)[0]
    trainers = [s.agent.world_model_trainer for s in seeds]
    model_based = trainers[0] is not None
    if counters["frames"] < start_frames:
        return acc

    sample = GroupSampler([s.rb for s in seeds], group)

    def model_step():
        out = group.update_world_model(sample())
        for t in trainers:
            t.updates += 1
        return out

    if model_based and not trainers[0].pretrained:
        for _ in range(trainers[0].pretrain_updates):
            model_step()
        for t in trainers:
            t.pretrained = True
    new_frames = min(n_frames, counters["frames"] - start_frames)
    counters["update_budget"] += cfg.optim.utd_ratio * new_frames
    n_updates = int(counters["update_budget"])
    counters["update_budget"] -= n_updates
    policy_delay = cfg.td3.policy_delay if cfg.algorithm == "td3" else 1
    for _ in range(n_updates):
        wm = None
        if model_based:
            if trainers[0].calls % trainers[0].train_every == 0:
                wm = model_step()
            for t in trainers:
                t.calls += 1
        step_actor = counters["updates"] % policy_delay == 0
        out = group.update(sample(), step_actor)
        counters["updates"] += 1
        keys = group.diagnostic_keys if group.expanding else None
        for i in range(len(seeds)):
            record_update(
                acc[i],
                critic_loss=out["loss_value"][i],
                actor_loss=out["loss_actor"][i] if step_actor else None,
                temperature=out["alpha"][i] if group.sac else None,
                world_model=None if wm is None else wm[i],
                diagnostics=None if keys is None else
                (out[keys.alpha][i], out[keys.horizon_weights][i], out[keys.horizon_variance][i]),
            )  # fmt: skip
    return acc
