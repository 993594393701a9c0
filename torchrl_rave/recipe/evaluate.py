"""Evaluation episodes (return, falling rate, the critics' value error) and the logger of a run."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.record.loggers import Logger, get_logger

from torchrl_rave.recipe.agent import bootstrap_value
from torchrl_rave.recipe.collect import NonFiniteEnvOutput


def make_logger(cfg: DictConfig, run_dir: str, state: dict | None = None) -> Logger | None:
    """The run's logger (``logger.backend``) writing under ``run_dir``; ``state`` is a
    resumed run's saved logger state, whose directory gives way to ``run_dir`` (the run
    directory may have been moved or copied since) and whose experiment name gives way to
    the config's (a saved name never leads the metrics elsewhere)."""
    if not cfg.logger.backend:
        return None
    if cfg.logger.backend == "mlflow":
        return _mlflow_logger(cfg, Path(run_dir))
    exp_name = cfg.logger.exp_name or cfg.algorithm
    if state:  # the run directory and the config decide where metrics go, not saved state
        state = {**state, "exp_name": exp_name}
        if "log_dir" in state:
            state["log_dir"] = str(run_dir)
    return get_logger(
        cfg.logger.backend,
        logger_name=str(run_dir),
        experiment_name=exp_name,
        state_dict=state,
        wandb_kwargs={"project": cfg.logger.project, "config": OmegaConf.to_container(cfg)},
    )


MLFLOW_DB = "mlflow.db"  # a run's MLflow store, inside its run directory


def _mlflow_logger(cfg: DictConfig, run_dir: Path) -> Logger:
    """TorchRL's MLflow logger on a store inside the run directory (an SQLite database:
    MLflow no longer writes plain-file stores). Each start of a run, a resumed one too,
    is an MLflow run of the same experiment; the run reader joins them in order."""
    import mlflow
    from torchrl.record.loggers.mlflow import MLFlowLogger

    mlflow.end_run()  # one MLflow run per start: close any the process left open
    store = f"sqlite:///{(run_dir / MLFLOW_DB).resolve()}"
    logger = MLFlowLogger(
        exp_name=cfg.logger.exp_name or cfg.algorithm,
        tracking_uri=store,
        artifact_location=str((run_dir / "mlartifacts").resolve()),
    )
    return logger


# A state counts in the value error once the return beyond the episode's time limit, which
# its Monte-Carlo return lacks, is weighted below this (gamma ** (T - t) < 0.01).
TRUNCATION_WEIGHT = 0.01


def discounted_returns(rewards: np.ndarray, gamma: float) -> np.ndarray:
    """``G_t = sum_{t' >= t} gamma^(t' - t) r_t'`` ``[T]`` of one episode's rewards ``[T]``."""
    out = np.zeros(len(rewards), dtype=np.float64)
    running = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        running = rewards[t] + gamma * running
        out[t] = running
    return out


def value_error_states(length: int, terminated: bool, gamma: float) -> np.ndarray:
    """The steps ``t`` of an episode of ``length`` steps whose Monte-Carlo return is a fair
    target for the critic: every step of an episode that terminated (nothing follows its
    end), and of one cut by the time limit only the steps with ``gamma ** (length - t) <
    TRUNCATION_WEIGHT`` (at gamma 0.99, the first ``length - 458`` steps)."""
    steps = np.arange(length)
    if terminated:
        return steps
    return steps[gamma ** (length - steps).astype(np.float64) < TRUNCATION_WEIGHT]


def value_error(predicted: np.ndarray, returns: np.ndarray) -> dict[str, float]:
    """``eval/q_bias`` (mean of predicted minus true), ``eval/q_rmse``, ``eval/q_corr``
    (Pearson; NaN when either side is constant) and ``eval/q_states`` over paired
    predictions and Monte-Carlo returns ``[n]`` (NaN statistics when ``n = 0``)."""
    n = len(returns)
    err = predicted - returns
    ok = n > 1 and predicted.std() > 0 and returns.std() > 0
    return {
        "eval/q_bias": float(err.mean()) if n else float("nan"),
        "eval/q_rmse": float(np.sqrt((err**2).mean())) if n else float("nan"),
        "eval/q_corr": float(np.corrcoef(predicted, returns)[0, 1]) if ok else float("nan"),
        "eval/q_states": float(n),
    }


@torch.no_grad()
def evaluate(
    env,
    actor,
    episodes: int,
    value: Callable[[TensorDictBase], torch.Tensor] | None = None,
    gamma: float = 0.99,
    reward_scale: float = 1.0,
) -> dict[str, float]:
    """Deterministic-policy episodes: return mean/std, length, and the falling rate.
    NaN/inf in an observation or reward raises ``NonFiniteEnvOutput``.

    With ``value`` (the critics' estimate ``[T]`` of the return from each step's state and
    action, e.g. ``torchrl_rave.recipe.agent.bootstrap_value``), the value error is
    measured too (:func:`value_error`): at the steps :func:`value_error_states` keeps, the
    estimate against the discounted Monte-Carlo return of the episode's own rewards with
    ``gamma``, both divided by ``reward_scale`` (environment reward units). The actions
    are the deterministic policy's, so the estimate is ``Q(s_t, pi(s_t))``.
    """
    returns, lengths, falls, predicted, true = [], [], [], [], []
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
            if value is not None:
                rewards = rollout["next", "reward"].reshape(-1).double().numpy() / reward_scale
                keep = value_error_states(len(rewards), bool(falls[-1]), gamma)
                q = value(rollout).reshape(-1).double().numpy() / reward_scale
                predicted.append(q[keep])
                true.append(discounted_returns(rewards, gamma)[keep])
    r = torch.tensor(returns)
    out = {
        "eval/return": r.mean().item(),
        "eval/return_std": r.std(unbiased=False).item(),
        "eval/episode_length": float(np.mean(lengths)),
        "eval/falling_rate": float(np.mean(falls)),
    }
    if value is not None:
        out.update(value_error(np.concatenate(predicted), np.concatenate(true)))
    return out


def evaluate_agent(cfg: DictConfig, env, agent) -> dict[str, float]:
    """:func:`evaluate` of a recipe agent (:class:`~torchrl_rave.recipe.agent.Agent`):
    ``cfg.eval.episodes`` episodes of its deterministic actor, with the value error of the
    critics as its loss bootstraps from them, at the run's gamma and reward scale."""
    return evaluate(
        env,
        agent.actor,
        cfg.eval.episodes,
        value=lambda td: bootstrap_value(agent.loss, td),
        gamma=cfg.optim.gamma,
        reward_scale=cfg.env.reward_scale,
    )
