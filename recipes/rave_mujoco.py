"""Train RAVE, or one of the paper's baselines, on a gymnasium MuJoCo task.

python recipes/rave_mujoco.py                                  # RAVE, InvertedPendulum-v5, CPU
python recipes/rave_mujoco.py env.name=Hopper-v5 algorithm=steve collector.total_frames=100000
python recipes/rave_mujoco.py preset=paper env.name=HalfCheetah-v5           # paper settings
python recipes/rave_mujoco.py resume=outputs/2026-11-22/10-00-00             # continue a run

``algorithm`` picks ddpg | mve | steve | rave | rave_constant (the estimator settings of one
K-critic DDPG learner) or td3 | sac (TorchRL's losses). All share collection, evaluation,
logging and checkpoints. See recipes/README.md for every key and metric.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import time
from collections import defaultdict
from collections.abc import Callable

import hydra
import torch
import tqdm
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from utils import (  # noqa: E402
    Checkpointer,
    CollectorFailure,
    NonFiniteEnvOutput,
    check_config,
    check_finite,
    check_resumable,
    config_for_resume,
    evaluate,
    make_actor,
    make_collector,
    make_critic,
    make_env,
    make_logger,
    make_loss,
    make_optimizers,
    make_replay_buffer,
    make_update_steps,
    make_world_model,
    make_world_model_loss,
    push_policy_weights,
    replay_buffer_size,
    rng_state,
    saved_config,
    set_rng_state,
)

Probe = Callable[[int, object], dict]


class _StopRequest:
    """SIGINT/SIGTERM ask the loop to checkpoint and stop at the end of the current batch;
    a second signal stops at once."""

    def __init__(self) -> None:
        self.requested = False
        self._previous = {}

    def __enter__(self):
        if hasattr(signal, "SIGTERM") and _in_main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        self.requested = True
        signal.signal(signum, self._previous[signum])

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def _in_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def train(cfg: DictConfig, run_dir: str, probe: Probe | None = None) -> dict[str, float]:
    """Runs (or, with ``cfg.resume`` set, continues) one training run; returns the final
    evaluation metrics. Everything is written under ``run_dir``.

    ``probe(frames, loss)``, when given, is called after every collector batch's updates;
    the scalars it returns are logged with the other metrics (the toy study records its
    Q-estimates this way).
    """
    algo = check_config(cfg)
    cfg = cfg.copy()
    if cfg.resume:
        run_dir = cfg.resume
        saved_cfg = saved_config(run_dir)
        check_resumable(cfg, saved_cfg)
        cfg.replay_buffer.size = saved_cfg.replay_buffer.size
    else:
        cfg.replay_buffer.size = replay_buffer_size(cfg)  # fixed once, so resuming keeps it
    device = torch.device(cfg.collector.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.env.seed)

    env = make_env(cfg, device)
    eval_env = make_env(cfg, device)
    actor, policy = make_actor(cfg, env, algo)
    critic = make_critic(cfg, env)
    world_model = make_world_model(cfg, env).to(device) if algo.model_based else None
    loss, updater = make_loss(cfg, env, algo, actor, critic, world_model)
    loss, policy = loss.to(device), policy.to(device)
    wm_loss = make_world_model_loss(world_model)
    optimizers = make_optimizers(cfg, loss, world_model)
    rb = make_replay_buffer(cfg, device)
    checkpointer = Checkpointer(run_dir)

    counters = {"frames": 0, "updates": 0, "update_budget": 0.0, "pretrained": False}
    counters["next_eval"] = cfg.eval.interval
    counters["next_checkpoint"] = cfg.checkpoint.interval
    logger_state = None
    if cfg.resume:
        saved = checkpointer.load(rb)
        loss.load_state_dict(saved["loss"])
        policy.load_state_dict(saved["policy"])
        if world_model is not None:
            world_model.load_state_dict(saved["world_model"])
        for name, opt in optimizers.items():
            opt.load_state_dict(saved["optimizers"][name])
        counters.update(saved["counters"])
        set_rng_state(saved["rng"])
        logger_state = saved.get("logger")
    logger = make_logger(cfg, run_dir, logger_state)
    # A resumed run restarts its episode; a new seed keeps it from replaying old ones.
    env.set_seed(cfg.env.seed + counters["frames"])

    def save_checkpoint():
        state = {
            "config": OmegaConf.to_container(cfg),
            "counters": dict(counters),
            "loss": loss.state_dict(),
            "policy": policy.state_dict(),
            "world_model": None if world_model is None else world_model.state_dict(),
            "optimizers": {name: opt.state_dict() for name, opt in optimizers.items()},
            "rng": rng_state(),
            "logger": None if logger is None else logger.state_dict(),
        }
        return checkpointer.save(state, rb)

    def log(metrics: dict[str, float]) -> None:
        if logger is not None:
            for key, value in metrics.items():
                logger.log_scalar(key, value, step=counters["frames"])

    # compiled with compile.enabled
    update_world_model, update_agent = make_update_steps(cfg, loss, wm_loss, optimizers, updater)

    def world_model_step():
        return update_world_model(rb.sample())

    def agent_step(step_actor: bool):
        return update_agent(rb.sample(), step_actor)

    def guarded(collector):
        """The collector's batches; a worker that raises or dies stops the run cleanly: the
        state after the last complete batch is checkpointed and the error names the env."""
        iterator = iter(collector)
        while True:
            try:
                data = next(iterator)
            except StopIteration:
                return
            except Exception as err:
                if cfg.collector.backend == "direct":
                    raise
                where = save_checkpoint()
                try:
                    collector.shutdown()
                except Exception:  # noqa: BLE001 (a dead worker may fail the shutdown too)
                    logging.getLogger(__name__).warning("collector shutdown failed", exc_info=True)
                raise CollectorFailure(
                    f"a {cfg.collector.backend} collector worker running {cfg.env.name} failed "
                    f"after frame {counters['frames']}: {type(err).__name__}: {err}. The run "
                    f"stopped; checkpoint {where} holds everything up to that frame: resume "
                    f"with resume={run_dir}"
                ) from err
            yield data

    policy_delay = cfg.td3.policy_delay if algo.loss == "td3" else 1
    start_frames = max(cfg.collector.init_random_frames, cfg.replay_buffer.batch_size)
    if algo.model_based:
        start_frames = max(start_frames, cfg.world_model.pretrain_frames)

    def train_on_batch(n_frames: int) -> dict[str, torch.Tensor]:
        acc = defaultdict(list)
        if counters["frames"] < start_frames:
            return acc
        if algo.model_based and not counters["pretrained"]:
            for _ in range(cfg.world_model.pretrain_updates):
                world_model_step()
            counters["pretrained"] = True
        # utd_ratio updates per frame collected after the start
        new_frames = min(n_frames, counters["frames"] - start_frames)
        counters["update_budget"] += cfg.optim.utd_ratio * new_frames
        n_updates = int(counters["update_budget"])
        counters["update_budget"] -= n_updates
        for _ in range(n_updates):
            if algo.model_based and counters["updates"] % cfg.world_model.train_every == 0:
                wm = world_model_step()
                for key in ("transition_nll", "transition_mse", "reward_nll", "reward_mse"):
                    acc[f"train/wm_{key}"].append(wm[key].detach())
                acc["train/wm_termination_bce"].append(wm["termination_bce"].detach())
            step_actor = counters["updates"] % policy_delay == 0
            out = agent_step(step_actor)
            counters["updates"] += 1
            acc["train/loss_critic"].append(out["loss_qvalue"].detach())
            if step_actor:
                acc["train/loss_actor"].append(out["loss_actor"].detach())
            if "alpha" in out.keys():  # noqa: SIM118 (a TensorDict)
                acc["train/sac_alpha"].append(out["alpha"].detach())
            if algo.model_based:
                diag = loss.value_estimator.diagnostics
                acc["train/alpha"].append(diag["rave_alpha"].mean())
                for h, w in enumerate(diag["rave_horizon_weights"].mean(0).unbind(-1)):
                    acc[f"train/horizon_weight_h{h}"].append(w)
                for h, v in enumerate(diag["rave_horizon_variance"].mean(0).unbind(-1)):
                    acc[f"train/candidate_variance_h{h}"].append(v)
        return acc

    total = cfg.collector.total_frames
    last_eval = {}
    pbar = tqdm.tqdm(
        total=total, initial=counters["frames"], unit="frames", disable=not cfg.logger.progress_bar
    )
    start = time.perf_counter()
    frames_at_start = counters["frames"]
    collector = None
    with _StopRequest() as stop:
        if counters["frames"] < total:
            collector = make_collector(cfg, env, policy, device, counters["frames"])
            synced_at = counters["updates"]  # the workers start with the current weights
            t_collect = time.perf_counter()
            for data in guarded(collector):
                data = data.reshape(-1)
                collect_s = time.perf_counter() - t_collect
                bad = check_finite(data)
                if bad is not None:
                    where = save_checkpoint()
                    collector.shutdown()
                    raise NonFiniteEnvOutput(
                        f"{cfg.env.name} produced NaN/inf in {bad!r} within frames "
                        f"{counters['frames']}-{counters['frames'] + data.numel()}; the run "
                        f"stopped before that batch reached the replay buffer. Checkpoint "
                        f"{where} (frame {counters['frames']}) is intact: fix the env and "
                        f"rerun with resume={run_dir}"
                    )
                rb.extend(data)
                if world_model is not None:
                    world_model.update_normalizers_from(data)
                counters["frames"] += data.numel()
                t_update = time.perf_counter()
                acc = train_on_batch(data.numel())
                update_s = time.perf_counter() - t_update
                if counters["updates"] - synced_at >= cfg.collector.weight_sync_every:
                    push_policy_weights(collector, policy)
                    synced_at = counters["updates"]

                metrics = {k: torch.stack(v).mean().item() for k, v in acc.items()}
                done = data["next", "done"].squeeze(-1)
                if done.any():
                    metrics["train/episode_reward"] = (
                        data["next", "episode_reward"][done].mean().item()
                    )
                n_updates = len(acc.get("train/loss_critic", ()))
                metrics["time/collect_s"] = collect_s
                metrics["time/update_s"] = update_s
                if n_updates:
                    metrics["time/updates_per_s"] = n_updates / max(update_s, 1e-9)
                frames_now = counters["frames"]
                metrics["time/fps"] = (frames_now - frames_at_start) / (time.perf_counter() - start)
                if frames_now >= counters["next_eval"] or frames_now >= total:
                    t_eval = time.perf_counter()
                    eval_env.set_seed(cfg.env.seed + 1_000_003 + frames_now)
                    last_eval = evaluate(eval_env, actor, cfg.eval.episodes)
                    metrics.update(last_eval)
                    metrics["time/eval_s"] = time.perf_counter() - t_eval
                    while counters["next_eval"] <= frames_now:
                        counters["next_eval"] += cfg.eval.interval
                if probe is not None:
                    metrics.update(probe(frames_now, loss))
                log(metrics)
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
                if stop.requested:
                    break
                t_collect = time.perf_counter()
    pbar.close()
    if collector is not None:
        collector.shutdown()
    if stop.requested:
        print(f"stopped at frame {counters['frames']}; resume with resume={run_dir}")
        return last_eval
    if not last_eval:  # a run resumed from its final checkpoint
        eval_env.set_seed(cfg.env.seed + 1_000_003 + counters["frames"])
        last_eval = evaluate(eval_env, actor, cfg.eval.episodes)
    elapsed = time.perf_counter() - start
    print(
        f"{cfg.algorithm} on {cfg.env.name}, seed {cfg.env.seed}: {counters['frames']} frames, "
        f"{counters['updates']} updates, {elapsed:.0f} s this session\n"
        f"  eval/return         {last_eval['eval/return']:.1f} ± "
        f"{last_eval['eval/return_std']:.1f} over {cfg.eval.episodes} episodes\n"
        f"  eval/episode_length {last_eval['eval/episode_length']:.1f}\n"
        f"  eval/falling_rate   {last_eval['eval/falling_rate']:.2f}\n"
        f"  run directory       {run_dir}"
    )
    if logger is not None and hasattr(logger, "shutdown"):
        logger.shutdown()
    return {**last_eval, "frames": counters["frames"], "updates": counters["updates"]}


@hydra.main(config_path=".", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float:
    run_dir = HydraConfig.get().runtime.output_dir
    if cfg.resume:
        cfg = config_for_resume(cfg.resume, list(HydraConfig.get().overrides.task))
    return train(cfg, run_dir)["eval/return"]


if __name__ == "__main__":
    main()
