"""The recipe's training loop: one run of any ``algorithm=``, from a config, into a run
directory, resumable from its checkpoints.

:func:`train` is what ``python recipes/rave_mujoco.py`` and the ``torchrl-rave-train``
command run, with the pieces of :mod:`torchrl_rave.recipe`; call it from a script with a
config from :func:`~torchrl_rave.recipe.schema.default_config`.

Examples:
    >>> cfg = default_config("collector.total_frames=200", algorithm="ddpg")  # doctest: +SKIP
    >>> train(cfg, "runs/ddpg")["eval/return"]  # doctest: +SKIP
"""

from __future__ import annotations

import time
from collections import defaultdict
from pathlib import Path

import torch
import tqdm
from omegaconf import DictConfig, OmegaConf
from torchrl.checkpoint import GlobalRNGState
from torchrl.data import ReplayBuffer

from torchrl_rave.recipe.agent import (
    Agent,
    critic_loss_key,
    make_agent,
    make_env,
    make_replay_buffer,
    q_at_points,
)
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
    learning_start,
    replay_buffer_size,
    resolve_config,
    warn_if_no_updates,
)
from torchrl_rave.recipe.curriculum import make_curriculum, stage_config
from torchrl_rave.recipe.episode import EpisodeCheckpoint, resume_collecting
from torchrl_rave.recipe.evaluate import evaluate_agent, make_logger
from torchrl_rave.recipe.reward import make_reward_relabelling, update_reward_weights
from torchrl_rave.recipe.schema import default_config, defaults  # noqa: F401 (the example)
from torchrl_rave.recipe.update import make_agent_step, ppo_update


def train(cfg: DictConfig, run_dir: str) -> dict[str, float]:
    """Runs (or, with ``cfg.resume`` set, continues) one training run; returns the final
    evaluation metrics. Everything is written under ``run_dir``, which no other process
    may train into meanwhile (:func:`exclusive_run`). A new run into a directory that
    holds one already is refused (``FileExistsError``, naming ``resume=``)."""
    check_config(cfg)
    warn_if_no_updates(resolve_config(cfg))
    if not cfg.resume:
        check_new_run_dir(run_dir, group=cfg.get("seeds") is not None)
        Path(run_dir).mkdir(parents=True, exist_ok=True)
    with exclusive_run(cfg.resume or run_dir):
        if cfg.get("seeds") is not None:  # S runs in one process, updates batched
            from torchrl_rave.recipe.group import train_group

            return train_group(cfg, run_dir)
        return _train(cfg, run_dir)


def _train(cfg: DictConfig, run_dir: str) -> dict[str, float]:
    cfg = resolve_config(cfg).copy()  # ppo: its rollout sets the collector's batch
    if cfg.resume:
        run_dir = cfg.resume
        saved = saved_config(run_dir, defaults())
        check_resumable(cfg, saved)
        cfg.replay_buffer.size = saved.replay_buffer.size
    else:
        cfg.replay_buffer.size = replay_buffer_size(cfg)  # fixed once, so resuming keeps it
    device = torch.device(cfg.collector.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    apply_process_settings(cfg)
    torch.manual_seed(cfg.env.seed)

    # Environments, agent, replay buffer; an in-process collector's env keeps its episode
    # for the checkpoints (a worker collector's workers keep theirs)
    # A curriculum's envs carry its stage's setting, the first stage's from the start.
    record = cfg.collector.backend == "direct"
    curriculum, run_cfg = make_curriculum(cfg), cfg
    if curriculum is not None:
        run_cfg = stage_config(cfg, curriculum)
    env, eval_env = make_env(run_cfg, device, record_episode=record), make_env(run_cfg, device)
    agent = make_agent(cfg, env, device)
    rb = make_replay_buffer(cfg, device)
    relabel, delayed = make_reward_relabelling(cfg, env)
    if relabel is not None:  # every sample is relabelled with the weights of the moment
        rb.append_transform(relabel)
    update_agent = None
    if not agent.algorithm.on_policy:
        update_agent = make_agent_step(cfg, agent.loss, agent.optimizers, agent.target_updater)

    # Counters and checkpoints; a resumed run restores everything it saved. Before any
    # work: the checkpoints can be written, and the disk has room for one.
    checkpoint = RunCheckpoint(run_dir)
    transition = env.fake_tensordict()
    checkpoint.preflight(
        lambda block: agent.checkpoint_bytes(cfg.replay_buffer.size, transition, block)
    )
    counters = {"frames": 0, "updates": 0, "update_budget": 0.0, "curriculum_stage": 0}
    counters.update(next_eval=cfg.eval.interval, next_checkpoint=cfg.checkpoint.interval)
    logger_state: dict = {}
    episode, rng_at_load = EpisodeCheckpoint(), None
    if cfg.resume:
        state = dict(counters=counters, replay_buffer=rb, logger=logger_state)
        loaded = checkpoint.load(**state, **agent.state_components())
        rng_at_load = GlobalRNGState().state_dict()
        episode.load_state_dict(checkpoint.read_optional("episode", loaded))
    logger = make_logger(cfg, run_dir, logger_state or None)
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
        run_cfg = stage_config(cfg, curriculum)
        env.close()
        eval_env.close()
        env = make_env(run_cfg, device, record_episode=record)
        eval_env = make_env(run_cfg, device)
    # A resumed run continues the episode of its checkpoint where it can (below); where it
    # cannot, a new seed keeps it from replaying old episodes.
    env.set_seed(cfg.env.seed + counters["frames"])

    def save_checkpoint():
        return checkpoint.save(
            counters["frames"],
            config=OmegaConf.to_container(cfg, resolve=True),
            counters=counters,
            replay_buffer=rb,
            logger={} if logger is None else logger.state_dict(),
            episode=episode,
            **agent.state_components(),
        )

    def save_after_failure():
        # mid-batch (a hung or failed collector) or a dropped batch (NaN): the episode
        # no longer matches the saved frames; a resumed run starts a new one
        episode.attach(None, None)
        return save_checkpoint()

    # Main loop
    total = cfg.collector.total_frames
    last_eval = {}
    pbar = tqdm.tqdm(
        total=total, initial=counters["frames"], unit="frames", disable=not cfg.logger.progress_bar
    )
    start, frames_at_start = time.perf_counter(), counters["frames"]
    collector = None
    with StopRequest() as stop, shutdown_on_error(lambda: collector):
        while counters["frames"] < total:  # again after each curriculum stage
            collector = make_collector(run_cfg, env, agent.policy, device, counters["frames"])
            episode.attach(env, collector)
            if rng_at_load is not None:  # the first collector of a resumed run
                seed = cfg.env.seed + counters["frames"]
                resume_collecting(episode, env, collector, seed, rng_at_load)
                rng_at_load = None
            next_stage = False
            synced_at = counters["updates"]  # the workers start with the current weights
            episode.workers_behind = False
            shared = workers_share_weights(collector, agent.policy)
            t_collect = time.perf_counter()
            batches = guarded_batches(
                collector, cfg, save_after_failure, lambda: counters["frames"], run_dir
            )
            for batch in batches:
                data = batch.reshape(-1)
                collect_s = time.perf_counter() - t_collect
                bad = check_finite(data)
                if bad is not None:
                    where = stop_run(collector, save_after_failure)
                    raise NonFiniteEnvOutput(
                        f"{cfg.env.name} produced {bad} within frames "
                        f"{counters['frames']}-{counters['frames'] + data.numel()}; the run "
                        f"stopped before that batch reached the replay buffer; {where} "
                        f"(frame {counters['frames']}): fix the env and rerun with "
                        f"resume={run_dir}"
                    )
                counters["frames"] += data.numel()
                t_update = time.perf_counter()
                if agent.algorithm.on_policy:  # GAE runs along each worker's time axis
                    acc = ppo_update(cfg, agent, rb, batch, counters)
                else:
                    rb.extend(data)
                    if agent.world_model_trainer is not None:
                        agent.world_model_trainer.extend(data)
                    weights = {}
                    if relabel is not None:
                        weights = update_reward_weights(cfg, relabel, delayed, counters, last_eval)
                    acc = update_on_batch(cfg, agent, update_agent, rb, counters, data.numel())
                    for key, value in weights.items():
                        acc[key].append(torch.tensor(value))
                update_s = time.perf_counter() - t_update
                if counters["updates"] - synced_at >= cfg.collector.weight_sync_every:
                    push_or_stop(collector, agent.policy, cfg, save_after_failure,
                                 counters["frames"], run_dir)  # fmt: skip
                    synced_at = counters["updates"]
                episode.workers_behind = counters["updates"] != synced_at and not shared

                frames_now = counters["frames"]
                fps = (frames_now - frames_at_start) / (time.perf_counter() - start)
                metrics = batch_metrics(acc, data, collect_s, update_s, fps)
                stage = None if curriculum is None else curriculum.stage  # collected in
                if frames_now >= counters["next_eval"] or frames_now >= total:
                    t_eval = time.perf_counter()
                    eval_env.set_seed(cfg.env.seed + 1_000_003 + frames_now)
                    try:
                        last_eval = evaluate_agent(cfg, eval_env, agent)
                    except NonFiniteEnvOutput as err:
                        where = stop_run(collector, save_checkpoint)
                        raise NonFiniteEnvOutput(
                            f"{cfg.env.name}: {err} at frame {frames_now}; {where}: fix the "
                            f"env and rerun with resume={run_dir}"
                        ) from None
                    metrics.update(last_eval)
                    metrics["time/eval_s"] = time.perf_counter() - t_eval
                    while counters["next_eval"] <= frames_now:
                        counters["next_eval"] += cfg.eval.interval
                    if curriculum is not None and frames_now < total:
                        next_stage = curriculum.update(last_eval)
                        counters["curriculum_stage"] = curriculum.stage
                        if next_stage:  # the next stage starts new episodes in new envs
                            episode.attach(None, None)
                if stage is not None:
                    metrics["train/curriculum_stage"] = stage
                metrics.update(q_at_points(agent.loss, cfg.logger.q_points, cfg.env.reward_scale))
                if logger is not None:
                    for key, value in metrics.items():
                        logger.log_scalar(key, value, step=frames_now)
                pbar.update(data.numel())
                if last_eval:
                    pbar.set_postfix(eval_return=f"{last_eval['eval/return']:.1f}")
                if (
                    frames_now >= counters["next_checkpoint"]
                    or frames_now >= total
                    or stop.requested
                ):
                    while counters["next_checkpoint"] <= frames_now:
                        counters["next_checkpoint"] += cfg.checkpoint.interval
                    save_checkpoint()
                if stop.requested or next_stage:
                    break
                t_collect = time.perf_counter()
            if stop.requested or not next_stage:
                break
            # the next stage: new envs with its setting, and a collector for them
            collector.shutdown()
            run_cfg = stage_config(cfg, curriculum)
            env.close()
            eval_env.close()
            env = make_env(run_cfg, device, record_episode=record)
            eval_env = make_env(run_cfg, device)
            env.set_seed(cfg.env.seed + counters["frames"])
    pbar.close()
    if collector is not None:
        collector.shutdown()
    if stop.requested:
        print(f"stopped at frame {counters['frames']}; resume with resume={run_dir}")
        return last_eval
    if not last_eval:  # a run resumed from its final checkpoint
        print(nothing_to_train("run", counters["frames"], cfg.collector.total_frames))
        eval_env.set_seed(cfg.env.seed + 1_000_003 + counters["frames"])
        last_eval = evaluate_agent(cfg, eval_env, agent)
    elapsed = time.perf_counter() - start
    print(
        f"{cfg.algorithm} on {cfg.env.name}, seed {cfg.env.seed}: {counters['frames']} frames, "
        f"{counters['updates']} updates, {elapsed:.0f} s of training since this start\n"
        f"  eval/return         {last_eval['eval/return']:.1f} ± "
        f"{last_eval['eval/return_std']:.1f} over {cfg.eval.episodes} episodes\n"
        f"  eval/episode_length {last_eval['eval/episode_length']:.1f}\n"
        f"  eval/falling_rate   {last_eval['eval/falling_rate']:.2f}\n"
        f"  run directory       {run_dir}"
    )
    if logger is not None and hasattr(logger, "shutdown"):
        logger.shutdown()
    return {**last_eval, "frames": counters["frames"], "updates": counters["updates"]}


def nothing_to_train(what: str, frames: int, total: int) -> str:
    """What a run (or a seed group) resumed at or past its ``collector.total_frames``
    says before it evaluates its restored policy."""
    return (
        f"nothing to train: the {what} is at {frames} frames and collector.total_frames="
        f"{total} (raise it to train on); evaluating its last checkpoint"
    )


def update_on_batch(
    cfg: DictConfig, agent: Agent, update_agent, rb: ReplayBuffer, counters: dict, n_frames: int
) -> dict[str, list[torch.Tensor]]:
    """The updates a batch of ``n_frames`` new frames pays for (``optim.utd_ratio`` per
    frame once the learning starts); returns the training metrics of each update."""
    acc = defaultdict(list)
    start_frames = learning_start(cfg)[0]
    wm_trainer = agent.world_model_trainer
    if counters["frames"] < start_frames:
        return acc
    if wm_trainer is not None:
        wm_trainer.pretrain(rb)  # once, as soon as F frames are stored
    new_frames = min(n_frames, counters["frames"] - start_frames)
    counters["update_budget"] += cfg.optim.utd_ratio * new_frames
    n_updates = int(counters["update_budget"])
    counters["update_budget"] -= n_updates
    policy_delay = cfg.td3.policy_delay if agent.algorithm.loss == "td3" else 1
    critic_key = critic_loss_key(agent.loss)
    for _ in range(n_updates):
        wm = None if wm_trainer is None else wm_trainer.step(rb)
        step_actor = counters["updates"] % policy_delay == 0
        out = update_agent(rb.sample(), step_actor)
        counters["updates"] += 1
        diagnostics = None
        if agent.algorithm.model_based:
            estimator = agent.loss.value_estimator
            diag, keys = estimator.diagnostics, estimator.tensor_keys
            diagnostics = (
                diag[keys.alpha],
                diag[keys.horizon_weights],
                diag[keys.horizon_variance],
            )
        record_update(
            acc,
            critic_loss=out[critic_key].detach(),
            actor_loss=out["loss_actor"].detach() if step_actor else None,
            temperature=out["alpha"].detach() if "alpha" in out.keys() else None,  # noqa: SIM118
            world_model=wm,
            diagnostics=diagnostics,
        )
    return acc


#: the world-model step's outputs logged as ``train/wm_<name>``
WORLD_MODEL_METRICS = ("transition_nll", "transition_mse", "reward_nll", "reward_mse",
                       "termination_bce")  # fmt: skip


def record_update(
    acc: dict, *, critic_loss, actor_loss=None, temperature=None, world_model=None,
    diagnostics=None,
) -> None:  # fmt: skip
    """Appends one update's training metrics to ``acc`` under their logged names: the
    critic's (and actor's) loss, SAC's temperature, the world-model step's outputs, and a
    value-expansion target's per-sample diagnostics ``(alpha, horizon weights, candidate
    variances)`` as batch means (``alpha`` is eq. 12's confidence)."""
    if world_model is not None:
        for key in WORLD_MODEL_METRICS:
            acc[f"train/wm_{key}"].append(world_model[key])
    acc["train/loss_critic"].append(critic_loss)
    if actor_loss is not None:
        acc["train/loss_actor"].append(actor_loss)
    if temperature is not None:
        acc["train/sac_temperature"].append(temperature)
    if diagnostics is not None:
        alpha, weights, variance = diagnostics
        acc["train/rave_alpha"].append(alpha.mean())
        for h, w in enumerate(weights.mean(0).unbind(-1)):
            acc[f"train/horizon_weight_h{h}"].append(w)
        for h, v in enumerate(variance.mean(0).unbind(-1)):
            acc[f"train/candidate_variance_h{h}"].append(v)


def batch_metrics(acc: dict, data, collect_s: float, update_s: float, fps: float) -> dict:
    """One collected batch's logged metrics: the means of its updates' ``acc``, the return
    of the training episodes that ended in ``data``, and its timings."""
    metrics = {k: torch.stack(v).mean().item() for k, v in acc.items()}
    done = data["next", "done"].squeeze(-1)
    if done.any():
        metrics["train/episode_reward"] = data["next", "episode_reward"][done].mean().item()
    n_updates = len(acc.get("train/loss_critic", ()))
    metrics["time/collect_s"] = collect_s
    metrics["time/update_s"] = update_s
    if n_updates:
        metrics["time/updates_per_s"] = n_updates / max(update_s, 1e-9)
    metrics["time/fps"] = fps
    return metrics
