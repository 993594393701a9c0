"""Train RAVE (DDPG base, K-critic ensemble, probabilistic world-model ensemble) on MuJoCo.

python recipes/rave_mujoco.py                         # InvertedPendulum-v5, CPU-sized
python recipes/rave_mujoco.py env.name=Hopper-v5 collector.total_frames=100000
"""

from __future__ import annotations

import os
import sys
import time

import hydra
import torch
import tqdm
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig
from torchrl.record.loggers import generate_exp_name, get_logger

sys.path.insert(0, os.path.dirname(__file__))
from utils import (  # noqa: E402
    evaluate,
    make_actor_critic,
    make_collector,
    make_env,
    make_losses,
    make_replay_buffer,
    make_world_model,
)


@hydra.main(config_path=".", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float:
    device = torch.device(cfg.collector.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    torch.manual_seed(cfg.env.seed)
    run_dir = HydraConfig.get().runtime.output_dir
    exp_name = generate_exp_name("RAVE", cfg.logger.exp_name)
    logger = None
    if cfg.logger.backend:
        logger = get_logger(cfg.logger.backend, logger_name=run_dir, experiment_name=exp_name)

    env = make_env(cfg, device)
    eval_env = make_env(cfg, device)
    actor, critic, exploration = make_actor_critic(cfg, env)
    world_model = make_world_model(cfg, env)
    loss, updater, wm_loss = make_losses(cfg, env, actor, critic, world_model)
    actor, world_model = actor.to(device), world_model.to(device)
    loss, wm_loss = loss.to(device), wm_loss.to(device)
    collector = make_collector(cfg, env, exploration, device)
    rb = make_replay_buffer(cfg, device)

    opt_actor = torch.optim.Adam(
        loss.actor_network_params.values(True, True), lr=cfg.optim.lr_actor
    )
    opt_critic = torch.optim.Adam(
        loss.qvalue_network_params.values(True, True), lr=cfg.optim.lr_critic
    )
    opt_wm = torch.optim.Adam(world_model.parameters(), lr=cfg.world_model.lr)

    def update_world_model(batch):
        out = wm_loss(batch)
        opt_wm.zero_grad()
        (out["loss_transition"] + out["loss_reward"] + out["loss_termination"]).backward()
        opt_wm.step()
        return out

    def update(batch):
        out = loss(batch)
        # The actor loss sees detached critic weights and the target carries no gradient,
        # so one backward over the sum gives each network exactly its own gradient.
        opt_critic.zero_grad()
        opt_actor.zero_grad()
        (out["loss_qvalue"] + out["loss_actor"]).backward()
        opt_critic.step()
        opt_actor.step()
        updater.step()
        return out

    frames, pretrained = 0, False
    pbar = tqdm.tqdm(total=cfg.collector.total_frames, unit="frames")
    last_return = float("nan")
    start = time.time()
    for data in collector:
        data = data.reshape(-1)
        frames += data.numel()
        rb.extend(data)
        world_model.update_normalizers_from(data)
        metrics = {}
        done = data["next", "done"].squeeze(-1)
        if done.any():
            metrics["train/episode_reward"] = data["next", "episode_reward"][done].mean().item()
        if frames >= cfg.world_model.pretrain_frames:
            if not pretrained:
                for _ in range(cfg.world_model.pretrain_updates):
                    update_world_model(rb.sample())
                pretrained = True
            for _ in range(max(1, int(cfg.optim.utd_ratio * data.numel()))):
                wm_out = update_world_model(rb.sample())
                out = update(rb.sample())
            diag = loss.value_estimator.diagnostics
            metrics.update(
                {
                    "train/loss_critic": out["loss_qvalue"].item(),
                    "train/loss_actor": out["loss_actor"].item(),
                    "train/wm_transition_nll": wm_out["transition_nll"].item(),
                    "train/wm_transition_mse": wm_out["transition_mse"].item(),
                    "train/wm_reward_mse": wm_out["reward_mse"].item(),
                    "train/alpha": diag["rave_alpha"].mean().item(),
                }
            )
        collector.update_policy_weights_()
        metrics["time/fps"] = frames / (time.time() - start)
        if logger is not None:
            for k, v in metrics.items():
                logger.log_scalar(k, v, step=frames)
        last_return = metrics.get("train/episode_reward", last_return)
        pbar.update(data.numel())
        pbar.set_postfix(ret=f"{last_return:.1f}")
    pbar.close()
    collector.shutdown()
    results = evaluate(eval_env, actor, cfg.eval.episodes)
    if logger is not None:
        for k, v in results.items():
            logger.log_scalar(k, v, step=frames)
    eval_return = results["eval/return"]
    print(
        f"{cfg.env.name}: {frames} frames, eval return {eval_return:.1f} ± {results['eval/return_std']:.1f} "
        f"over {cfg.eval.episodes} episodes, {time.time() - start:.0f} s"
    )
    return eval_return


if __name__ == "__main__":
    main()
