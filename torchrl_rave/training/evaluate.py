"""Evaluation episodes and the logger of a run."""

from __future__ import annotations

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.record.loggers import Logger, get_logger

from torchrl_rave.training.collect import NonFiniteEnvOutput


def make_logger(cfg: DictConfig, run_dir: str, state: dict | None = None) -> Logger | None:
    """The run's logger (``logger.backend``) writing under ``run_dir``; ``state`` is a
    resumed run's saved logger state, whose directory gives way to ``run_dir`` (the run
    directory may have been moved or copied since)."""
    if not cfg.logger.backend:
        return None
    if state and "log_dir" in state:
        state = {**state, "log_dir": str(run_dir)}
    return get_logger(
        cfg.logger.backend,
        logger_name=str(run_dir),
        experiment_name=cfg.logger.exp_name or cfg.algorithm,
        state_dict=state,
        wandb_kwargs={"project": cfg.logger.project, "config": OmegaConf.to_container(cfg)},
    )


@torch.no_grad()
def evaluate(env, actor, episodes: int) -> dict[str, float]:
    """Deterministic-policy episodes: return mean/std, length, and the falling rate.
    NaN/inf in an observation or reward raises :class:`NonFiniteEnvOutput`."""
    returns, lengths, falls = [], [], []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(episodes):
            rollout = env.rollout(1_000_000, actor, break_when_any_done=True)
            for key in ("observation", ("next", "observation"), ("next", "reward")):
                if not bool(torch.isfinite(rollout[key]).all()):
                    raise NonFiniteEnvOutput(
                        f"the evaluation env produced NaN/inf in {key!r} in evaluation "
                        f"episode {len(returns)}"
                    )
            returns.append(rollout["next", "episode_reward"][-1].item())
            lengths.append(rollout["next", "step_count"][-1].item())
            # terminated (fell) rather than truncated by the time limit
            falls.append(float(rollout["next", "terminated"][-1].item()))
    r = torch.tensor(returns)
    return {
        "eval/return": r.mean().item(),
        "eval/return_std": r.std(unbiased=False).item(),
        "eval/episode_length": float(np.mean(lengths)),
        "eval/falling_rate": float(np.mean(falls)),
    }
