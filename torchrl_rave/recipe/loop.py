"""The recipe's training loop: one run of any ``algorithm=``, or a seed group
(``seeds=[...]``), from a config, into a run directory, resumable from its checkpoints.

:func:`~torchrl_rave.recipe.train` is what ``python recipes/rave_mujoco.py`` and the ``torchrl-rave-train``
command run, with the pieces of :mod:`torchrl_rave.recipe`; call it from a script with a
config from :func:`~torchrl_rave.recipe.default_config`.

A single run is a group of one: the loop below holds a list of runs, each with its env,
agent, replay buffer, checkpoints and logger, and one *learner* updates them all
(:mod:`torchrl_rave.recipe.update`). With ``seeds=[...]`` each seed is an ordinary run of
its own in ``<run_dir>/seed<s>/``, which every reader of a run directory takes as it is;
the seeds advance in lockstep (every collector gives one batch, every replay buffer takes
its own), their updates batched by a :class:`~torchrl_rave.trainers.SeedGroup`
(:class:`~torchrl_rave.recipe.group.GroupLearner`). ``<run_dir>/group.json`` holds the
group's config; ``resume=<run_dir>`` continues every seed from the newest checkpoint all of
them have.

Each seed of a group also has its own random stream
(:class:`~torchrl_rave.trainers.SeedStreams`): its networks are initialised after
``torch.manual_seed(seed)``, as a single run's are, and everything drawn for it afterwards
(random and exploratory actions, replay sampling, the world model's bootstrap and rollouts,
TD3's and SAC's noise) comes from its stream, in a single run's order. So a seed draws the
same numbers in any group, alone or not, as a single run of that seed does; what can still
differ is float rounding of the batched kernels.

Examples:
    >>> cfg = default_config("collector.total_frames=200", algorithm="ddpg")  # doctest: +SKIP
    >>> train(cfg, "runs/ddpg")["eval/return"]  # doctest: +SKIP
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
import tqdm
from omegaconf import DictConfig, OmegaConf
from torchrl.checkpoint import GlobalRNGState

from torchrl_rave.recipe.agent import Agent, make_agent, make_env, make_replay_buffer, q_at_points
from torchrl_rave.recipe.checkpoint import (
    RunCheckpoint,
    check_new_run_dir,
    exclusive_run,
    saved_config,
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
    workers_share_weights,
)
from torchrl_rave.recipe.config import (
    apply_process_settings,
    check_config,
    check_resumable,
    replay_buffer_size,
    resolve_config,
    warn_if_no_updates,
)
from torchrl_rave.recipe.curriculum import make_curriculum, stage_config
from torchrl_rave.recipe.episode import EpisodeCheckpoint, resume_collecting
from torchrl_rave.recipe.evaluate import evaluate_agent, make_logger
from torchrl_rave.recipe.group import (
    GroupLearner,
    common_checkpoint,
    saved_group_config,
    seed_config,
    write_group_file,
)
from torchrl_rave.recipe.metrics import batch_metrics, update_means
from torchrl_rave.recipe.reward import make_reward_relabelling, update_reward_weights
from torchrl_rave.recipe.schema import default_config, defaults  # noqa: F401 (the example)
from torchrl_rave.recipe.update import (
    AgentLearner,
    batch_cut_short,
    ppo_update,
    update_on_batch,
)
from torchrl_rave.trainers import SeedStreams

__all__ = ["nothing_to_train", "train"]


def train(cfg: DictConfig, run_dir: str) -> dict[str, float]:
    """Runs (or, with ``cfg.resume`` set, continues) one training run, or the seed group of
    ``cfg.seeds``; returns the final evaluation metrics (a group's: each seed's under
    ``seed<s>/<metric>``, their mean over seeds under ``<metric>``). Everything is written
    under ``run_dir``, which no other process may train into meanwhile
    (``exclusive_run``). A new run into a directory that holds one already is refused
    (``FileExistsError``, naming ``resume=``)."""
    check_config(cfg)
    warn_if_no_updates(resolve_config(cfg))
    if not cfg.resume:
        check_new_run_dir(run_dir, group=cfg.get("seeds") is not None)
        Path(run_dir).mkdir(parents=True, exist_ok=True)
    with exclusive_run(cfg.resume or run_dir):
        return _train(cfg, run_dir)


@dataclass
class _Run:
    """One seed's run: its config, directory and everything it owns."""

    seed: int
    cfg: DictConfig
    dir: Path
    env: object
    eval_env: object
    agent: Agent
    rb: object
    checkpoint: RunCheckpoint
    relabel: object = None  # reward relabelling: the replay buffer's transform, its schedule
    delayed: object = None
    logger: object = None
    logger_state: dict = field(default_factory=dict)
    episode: EpisodeCheckpoint = field(default_factory=EpisodeCheckpoint)
    collector: object = None
    rng_at_load: dict | None = None
    last_eval: dict = field(default_factory=dict)


class _SharedStream:
    """A single run's random stream: the process's generators, as they are."""

    @staticmethod
    def use(i: int):
        return contextlib.nullcontext()


def _lockstep(iterators, streams):
    """One batch of every run's collector, each drawn under its seed's stream, until the
    first runs out (at once, for no collectors)."""
    while iterators:
        batches = []
        for i, it in enumerate(iterators):
            with streams.use(i):
                batch = next(it, None)
            if batch is None:
                return
            batches.append(batch)
        yield batches


def _train(cfg: DictConfig, run_dir: str) -> dict[str, float]:
    group = cfg.get("seeds") is not None
    cfg = resolve_config(cfg).copy()  # ppo: its rollout sets the collector's batch
    root = Path(cfg.resume or run_dir)
    if cfg.resume:
        saved = saved_group_config(root, cfg) if group else saved_config(root, defaults())
        check_resumable(cfg, saved)
        cfg.replay_buffer.size = saved.replay_buffer.size
    else:
        cfg.replay_buffer.size = replay_buffer_size(cfg)  # fixed once, so resuming keeps it
    device = torch.device(cfg.collector.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    apply_process_settings(cfg)

    # Each seed's environments, agent and replay buffer, initialised after its seed is
    # set, as a single run's; an in-process collector's env keeps its episode for the
    # checkpoints (a worker collector's workers keep theirs). A curriculum's envs carry
    # its stage's setting, the first stage's from the start.
    record = cfg.collector.backend == "direct"
    curriculum = make_curriculum(cfg)

    def staged(one: DictConfig) -> DictConfig:  # a seed's config with the curriculum's stage
        return one if curriculum is None else stage_config(one, curriculum)

    def envs(one: DictConfig):
        return make_env(staged(one), device, record_episode=record), make_env(staged(one), device)

    seeds = [int(s) for s in cfg.seeds] if group else [int(cfg.env.seed)]
    streams = SeedStreams(len(seeds), device) if group else _SharedStream()
    runs: list[_Run] = []
    for i, seed in enumerate(seeds):
        one = seed_config(cfg, seed) if group else cfg
        torch.manual_seed(seed)
        env, eval_env = envs(one)
        agent = make_agent(one, env, device)
        seed_dir = root / f"seed{seed}" if group else root
        seed_dir.mkdir(parents=True, exist_ok=True)
        run = _Run(seed, one, seed_dir, env, eval_env, agent, make_replay_buffer(one, device),
                   RunCheckpoint(seed_dir))  # fmt: skip
        run.relabel, run.delayed = make_reward_relabelling(one, env)
        if run.relabel is not None:  # every sample is relabelled with the weights of the moment
            run.rb.append_transform(run.relabel)
        runs.append(run)
        if group:
            streams.capture(i)  # from here on, seed i draws from its own stream

    # Counters and checkpoints; a resumed run restores everything it saved. Before any
    # work: the checkpoints can be written, and the disk has room for one.
    transition = runs[0].env.fake_tensordict()
    for run in runs:
        run.checkpoint.preflight(
            lambda block, a=run.agent: a.checkpoint_bytes(cfg.replay_buffer.size, transition, block)
        )
    counters = {"frames": 0, "updates": 0, "update_budget": 0.0, "curriculum_stage": 0}
    counters.update(next_eval=cfg.eval.interval, next_checkpoint=cfg.checkpoint.interval)
    if cfg.resume:  # a group: from the newest checkpoint every seed has
        frame = common_checkpoint(runs) if group else None
        for i, run in enumerate(runs):
            path = None if frame is None else run.checkpoint.path(frame)
            with streams.use(i):  # restores seed i's stream as its checkpoint saved it
                loaded = run.checkpoint.load(
                    path=path, counters=counters if i == 0 else dict(counters),
                    replay_buffer=run.rb, logger=run.logger_state, **run.agent.state_components(),
                )  # fmt: skip
                run.rng_at_load = GlobalRNGState().state_dict()
            run.episode.load_state_dict(run.checkpoint.read_optional("episode", loaded))
    for run in runs:
        run.logger = make_logger(run.cfg, str(run.dir), run.logger_state or None)
    # A resumed run continues its curriculum's stage, in envs built for it.
    if curriculum is not None and counters["curriculum_stage"]:
        try:
            curriculum.load_state_dict({"stage": counters["curriculum_stage"]})
        except (TypeError, ValueError):
            raise ValueError(
                f"{loaded}: its counters hold curriculum_stage="
                f"{counters['curriculum_stage']!r}, not a stage of curriculum.stages "
                f"({len(curriculum.values)} stages, from 0); the checkpoint was edited, or "
                "the run was saved with other stages: resume with those"
            ) from None
        for run in runs:
            run.env.close()
            run.eval_env.close()
            run.env, run.eval_env = envs(run.cfg)
    on_policy = runs[0].agent.algorithm.on_policy
    learner = None
    if group:
        learner = GroupLearner(cfg, [r.agent for r in runs], [r.rb for r in runs], streams)
    elif not on_policy:
        learner = AgentLearner(cfg, runs[0].agent, runs[0].rb)
    # A resumed run continues the episode of its checkpoint where it can (below); where it
    # cannot, a new seed keeps it from replaying old episodes.
    for i, run in enumerate(runs):
        with streams.use(i):
            run.env.set_seed(run.seed + counters["frames"])

    def save_checkpoint():
        if group:
            learner.before_save()
            write_group_file(root, cfg)
        paths = []
        for i, run in enumerate(runs):
            with streams.use(i):  # the checkpoint's random state is seed i's stream
                paths.append(run.checkpoint.save(
                    counters["frames"],
                    config=OmegaConf.to_container(run.cfg, resolve=True),
                    counters=dict(counters),
                    replay_buffer=run.rb,
                    logger={} if run.logger is None else run.logger.state_dict(),
                    episode=run.episode,
                    **run.agent.state_components(),
                ))  # fmt: skip
        return paths if group else paths[0]

    def save_after_failure():
        # mid-batch (a hung or failed collector) or a dropped batch (NaN): the episodes
        # no longer match the saved frames; a resumed run starts new ones
        for run in runs:
            run.episode.attach(None, None)
        return save_checkpoint()

    def named(run: _Run) -> str:
        return f"{cfg.env.name} (seed {run.seed})" if group else cfg.env.name

    def evaluate(i: int, run: _Run, frames_now: int) -> dict:
        """Seed i's evaluation at ``frames_now``, its metrics and their time."""
        t_eval = time.perf_counter()
        with streams.use(i):
            run.eval_env.set_seed(run.seed + 1_000_003 + frames_now)
            try:
                run.last_eval = evaluate_agent(run.cfg, run.eval_env, run.agent)
            except NonFiniteEnvOutput as err:
                where = stop_run(run.collector, save_checkpoint)
                raise NonFiniteEnvOutput(
                    f"{named(run)}: {err} at frame {frames_now}; {where}: fix "
                    f"the env and rerun with resume={root}"
                ) from None
        return {**run.last_eval, "time/eval_s": time.perf_counter() - t_eval}

    def evaluated(frames_now: int) -> bool:
        """After the evaluations at ``frames_now``: the next one's frame, and whether the
        curriculum moves to its next stage."""
        while counters["next_eval"] <= frames_now:
            counters["next_eval"] += cfg.eval.interval
        if curriculum is None or frames_now >= total:
            return False
        next_stage = curriculum.update(runs[0].last_eval)
        counters["curriculum_stage"] = curriculum.stage
        if next_stage:  # the next stage starts new episodes in new envs
            runs[0].episode.attach(None, None)
        return next_stage

    def checkpoint_due(frames_now: int) -> bool:
        if frames_now >= counters["next_checkpoint"] or frames_now >= total:
            while counters["next_checkpoint"] <= frames_now:
                counters["next_checkpoint"] += cfg.checkpoint.interval
            return True
        return False

    def next_stage_envs() -> None:
        for run in runs:
            if run.collector is not None:
                run.collector.shutdown()
            run.env.close()
            run.eval_env.close()
            run.env, run.eval_env = envs(run.cfg)
            run.env.set_seed(run.seed + counters["frames"])

    def batch_updates(n_frames: int) -> list[dict] | None:
        """The updates a batch of ``n_frames`` new frames pays for (:func:`update_on_batch`,
        a stop may cut them short), the reward terms relabelled with the weights of the
        batch; each seed's training metrics with those weights, or ``None`` when a stop
        left some updates owed."""
        weights = [{} if run.relabel is None else update_reward_weights(
            cfg, run.relabel, run.delayed, counters, run.last_eval) for run in runs]  # fmt: skip
        accs = update_on_batch(cfg, learner, counters, n_frames, stop=lambda: stop.requested)
        if batch_cut_short(cfg, learner, counters):
            return None
        for acc, w in zip(accs, weights, strict=True):
            for key, value in w.items():
                acc[key].append(torch.tensor(value))
        return accs

    def log_batch(i: int, run: _Run, metrics: dict, frames_now: int, evaluate_now: bool,
                  stage: int | None) -> None:  # fmt: skip
        """Logs seed i's batch ``metrics`` at ``frames_now``, with its evaluation where due,
        the curriculum ``stage`` it was collected in and the critics at the fixed points."""
        if evaluate_now:
            metrics.update(evaluate(i, run, frames_now))
        if stage is not None:
            metrics["train/curriculum_stage"] = stage
        metrics.update(q_at_points(run.agent.loss, cfg.logger.q_points, cfg.env.reward_scale))
        if run.logger is not None:
            for key, value in metrics.items():
                run.logger.log_scalar(key, value, step=frames_now)

    def finish_cut_batch() -> bool:
        """A run resumed from the checkpoint of a stop that cut a batch's updates short
        takes them now, before it collects again, as the run would have: the owed
        pretraining and updates, then the batch's evaluation and checkpoint where due, and
        its log (the means of the updates taken here, the evaluation). Returns whether
        it finished the batch (a new stop may cut it short again)."""
        accs = batch_updates(0)  # the relabelling weights: the delayed term's start is saved
        if accs is None:
            save_checkpoint()
            return False
        frames_now = counters["frames"]
        evaluate_now = frames_now >= counters["next_eval"] or frames_now >= total
        stage = None if curriculum is None else curriculum.stage
        for i, (run, acc) in enumerate(zip(runs, accs, strict=True)):
            log_batch(i, run, update_means(acc), frames_now, evaluate_now, stage)
        if evaluate_now and evaluated(frames_now):
            next_stage_envs()
        if checkpoint_due(frames_now) or stop.requested:
            save_checkpoint()
        for i, run in enumerate(runs):  # the random state the next batch starts from
            with streams.use(i):
                run.rng_at_load = GlobalRNGState().state_dict()
        return True

    # Main loop
    total = cfg.collector.total_frames
    pbar = tqdm.tqdm(
        total=total, initial=counters["frames"], unit="frames", disable=not cfg.logger.progress_bar
    )
    start, frames_at_start = time.perf_counter(), counters["frames"]
    with StopRequest() as stop, contextlib.ExitStack() as on_error:
        for run in runs:  # on an error, no run's workers outlive it
            on_error.enter_context(shutdown_on_error(lambda run=run: run.collector))
        if cfg.resume and batch_cut_short(cfg, learner, counters):
            finish_cut_batch()
        while counters["frames"] < total and not stop.requested:  # again after each stage
            for i, run in enumerate(runs):
                with streams.use(i):
                    run.collector = make_collector(
                        staged(run.cfg), run.env, run.agent.policy, device, counters["frames"]
                    )
                    run.episode.attach(run.env, run.collector)
                    if run.rng_at_load is not None:  # the first collector of a resumed run
                        resume_collecting(run.episode, run.env, run.collector,
                                          run.seed + counters["frames"], run.rng_at_load)  # fmt: skip
                        run.rng_at_load = None
                run.episode.workers_behind = False
            next_stage = False
            synced_at = counters["updates"]  # the workers start with the current weights
            shared = [workers_share_weights(r.collector, r.agent.policy) for r in runs]
            iterators = [
                guarded_batches(r.collector, r.cfg, save_after_failure, lambda: counters["frames"],
                                str(r.dir))
                for r in runs
            ]  # fmt: skip
            t_collect = time.perf_counter()
            for batches in _lockstep(iterators, streams):
                collect_s = time.perf_counter() - t_collect
                data = [b.reshape(-1) for b in batches]
                for run, d in zip(runs, data, strict=True):
                    bad = check_finite(d)
                    if bad is not None:
                        where = stop_run(run.collector, save_after_failure)
                        raise NonFiniteEnvOutput(
                            f"{named(run)} produced {bad} within frames "
                            f"{counters['frames']}-{counters['frames'] + d.numel()}; the run "
                            f"stopped before that batch reached the replay buffer; {where} "
                            f"(frame {counters['frames']}): fix the env and rerun with "
                            f"resume={root}"
                        )
                n_frames = data[0].numel()
                counters["frames"] += n_frames
                t_update = time.perf_counter()
                if on_policy:  # GAE runs along each worker's time axis
                    accs = [ppo_update(cfg, run.agent, run.rb, b, counters)
                            for run, b in zip(runs, batches, strict=True)]  # fmt: skip
                else:
                    for run, d in zip(runs, data, strict=True):
                        run.rb.extend(d)
                        if run.agent.world_model_trainer is not None:
                            run.agent.world_model_trainer.extend(d)
                    accs = batch_updates(n_frames)
                    if accs is None:  # cut short by a stop: checkpoint now
                        for run, s in zip(runs, shared, strict=True):  # their copies will
                            run.episode.workers_behind = not s  # be older than the learner's
                        save_checkpoint()  # a resumed run takes the rest first (and logs)
                        break
                update_s = time.perf_counter() - t_update
                if counters["updates"] - synced_at >= cfg.collector.weight_sync_every:
                    for run in runs:
                        push_or_stop(run.collector, run.agent.policy, run.cfg, save_after_failure,
                                     counters["frames"], str(run.dir))  # fmt: skip
                    synced_at = counters["updates"]
                for run, s in zip(runs, shared, strict=True):
                    run.episode.workers_behind = counters["updates"] != synced_at and not s

                frames_now = counters["frames"]
                evaluate_now = frames_now >= counters["next_eval"] or frames_now >= total
                fps = (frames_now - frames_at_start) / (time.perf_counter() - start)
                stage = None if curriculum is None else curriculum.stage  # collected in
                for i, (run, d, acc) in enumerate(zip(runs, data, accs, strict=True)):
                    log_batch(i, run, batch_metrics(acc, d, collect_s, update_s, fps),
                              frames_now, evaluate_now, stage)  # fmt: skip
                if evaluate_now:
                    next_stage = evaluated(frames_now)
                pbar.update(n_frames)
                if runs[0].last_eval:
                    pbar.set_postfix(eval_return=f"{runs[0].last_eval['eval/return']:.1f}")
                if checkpoint_due(frames_now) or stop.requested:
                    save_checkpoint()
                if stop.requested or next_stage or frames_now >= total:
                    break
                t_collect = time.perf_counter()
            if stop.requested or not next_stage:
                break
            next_stage_envs()  # the next stage: new envs with its setting, new collectors
    pbar.close()
    for run in runs:
        if run.collector is not None:
            run.collector.shutdown()
    if stop.requested:
        print(f"stopped at frame {counters['frames']}; resume with resume={root}")
    elif not runs[0].last_eval:  # a run resumed from its final checkpoint
        print(nothing_to_train("group" if group else "run", counters["frames"], total))
        for i, run in enumerate(runs):
            with streams.use(i):
                run.eval_env.set_seed(run.seed + 1_000_003 + counters["frames"])
                run.last_eval = evaluate_agent(run.cfg, run.eval_env, run.agent)
    elapsed = time.perf_counter() - start
    for run in runs:
        last = run.last_eval
        if last:
            print(
                f"{cfg.algorithm} on {cfg.env.name}, seed {run.seed}: {counters['frames']} "
                f"frames, {counters['updates']} updates, {elapsed:.0f} s of training since "
                f"this start\n"
                f"  eval/return         {last['eval/return']:.1f} ± "
                f"{last['eval/return_std']:.1f} over {cfg.eval.episodes} episodes\n"
                f"  eval/episode_length {last['eval/episode_length']:.1f}\n"
                f"  eval/falling_rate   {last['eval/falling_rate']:.2f}\n"
                f"  run directory       {run.dir}"
            )
        if run.logger is not None and hasattr(run.logger, "shutdown"):
            run.logger.shutdown()
    if not group:
        last = runs[0].last_eval
        return last if stop.requested else {**last, "frames": counters["frames"],
                                            "updates": counters["updates"]}  # fmt: skip
    out: dict[str, float] = {}
    for run in runs:
        out.update({f"seed{run.seed}/{k}": v for k, v in run.last_eval.items()})
    for key in runs[0].last_eval:
        out[key] = sum(r.last_eval[key] for r in runs) / len(runs)
    return out


def nothing_to_train(what: str, frames: int, total: int) -> str:
    """What a run (or a seed group) resumed at or past its ``collector.total_frames``
    says before it evaluates its restored policy."""
    return (
        f"nothing to train: the {what} is at {frames} frames and collector.total_frames="
        f"{total} (raise it to train on); evaluating its last checkpoint"
    )
