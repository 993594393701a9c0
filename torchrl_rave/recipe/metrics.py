"""Every metric the recipe logs, with its meaning: the one list that the documentation
renders and that the tests hold the logged metrics to.

A name may hold one ``{H}`` (a horizon, 0 to ``estimator.horizon``) or ``{name}`` (a key of
``logger.q_points``). Metrics are logged once per collector batch, at step = frames
collected; ``train/*`` are means over the batch's updates, ``eval/*`` come from the
deterministic-policy evaluations (every ``eval.interval`` frames and once at the end).

Examples:
    >>> describe("train/horizon_weight_h2").startswith("mean normalised weight")
    True
    >>> describe("train/made_up") is None
    True
"""

from __future__ import annotations

import re

import torch

__all__ = [
    "METRICS",
    "WORLD_MODEL_METRICS",
    "batch_metrics",
    "describe",
    "record_update",
    "update_means",
]

#: metric name (with ``{H}`` or ``{name}`` where it varies) -> its meaning
METRICS: dict[str, str] = {
    "train/episode_reward": "mean return of the training episodes that ended in the batch",
    "train/loss_critic": "critic loss (for ppo, the value loss)",
    "train/loss_actor": "actor loss (for ppo, the clipped objective)",
    "train/sac_temperature": "sac: the entropy temperature (SACLoss's ``alpha``)",
    "train/ppo_kl_approx": "ppo: approximate KL divergence to the collecting policy",
    "train/ppo_clip_fraction": "ppo: fraction of probability ratios that were clipped",
    "train/ppo_entropy": "ppo: policy entropy (logged with an entropy bonus only)",
    "train/lr": "ppo: the learning rate used for the batch",
    "train/wm_transition_nll": "world model: transition Gaussian NLL (normalised units)",
    "train/wm_transition_mse": "world model: transition mean squared error (normalised units)",
    "train/wm_reward_nll": "world model: reward Gaussian NLL (normalised units)",
    "train/wm_reward_mse": "world model: reward mean squared error (normalised units)",
    "train/wm_termination_bce": "world model: termination cross-entropy",
    "train/rave_alpha": (
        "mean confidence factor alpha(s, a) of the targets (eq. 12; the constant for "
        "rave_constant, 0 for mve and steve)"
    ),
    "train/horizon_weight_h{H}": "mean normalised weight w_H of the horizon-H candidates",
    "train/candidate_variance_h{H}": "mean variance V_H of the horizon-H candidate targets",
    "train/reward_weight_{name}": (
        "with ``reward.weights`` or ``reward.delayed``: the weight of reward term ``name`` "
        "the batch's updates relabelled with"
    ),
    "train/curriculum_stage": "with ``curriculum.kwarg``: the stage the batch was collected in (from 0)",
    "time/collect_s": "seconds spent collecting the batch",
    "time/update_s": "seconds spent updating on the batch (agent and world model)",
    "time/eval_s": "seconds spent evaluating (batches that end with an evaluation)",
    "time/updates_per_s": "agent updates, with their world-model steps, per second",
    "time/fps": "frames per wall-clock second since the run's (re)start",
    "eval/return": "deterministic-policy return, mean over ``eval.episodes``",
    "eval/return_std": "its standard deviation over the episodes",
    "eval/episode_length": "mean evaluation episode length",
    "eval/falling_rate": (
        "fraction of evaluation episodes ended by termination before the time limit"
    ),
    "eval/q_bias": (
        "mean of the critics' estimate of Q(s_t, pi(s_t)) minus the discounted Monte-Carlo "
        "return from s_t (``optim.gamma``, env reward units). The estimate is what each loss "
        "bootstraps from: the mean over the K critics (ddpg, mve, steve, rave), the minimum "
        "of the two (td3, and sac, steve_sac and rave_sac, whose critics also hold the entropy "
        "bonus of later steps), V(s_t) "
        "(ppo). States counted: every state of an episode that terminated and, of one cut "
        "by the time limit, those with gamma^(T - t) < 0.01"
    ),
    "eval/q_rmse": (
        "root mean square of the same error (on a stochastic task one episode's return is "
        "one sample, so this includes its spread)"
    ),
    "eval/q_corr": "Pearson correlation of the estimates with the Monte-Carlo returns",
    "eval/q_states": "the number of states the value error was measured on",
    "q/{name}": (
        "with ``logger.q_points``: after every batch, the critics' mean Q at that "
        "(observation, action) point, in reward units"
    ),
}

_PATTERNS = [
    (re.compile("^" + re.escape(name).replace(r"\{H\}", r"\d+").replace(r"\{name\}", r"[^/]+") + "$"),
     meaning)
    for name, meaning in METRICS.items()
]  # fmt: skip


def describe(name: str) -> str | None:
    """The meaning of a logged metric ``name`` (e.g. ``"train/horizon_weight_h2"``), or
    None for a name the recipe does not log."""
    for pattern, meaning in _PATTERNS:
        if pattern.match(name):
            return meaning
    return None


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


def update_means(acc: dict) -> dict:
    """The means of a batch's updates' ``acc`` (each key's recorded values)."""
    return {k: torch.stack(v).mean().item() for k, v in acc.items()}


def batch_metrics(acc: dict, data, collect_s: float, update_s: float, fps: float) -> dict:
    """One collected batch's logged metrics: the means of its updates' ``acc``, the return
    of the training episodes that ended in ``data``, and its timings."""
    metrics = update_means(acc)
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
