"""The recipe's ``reward`` keys: an env's reward terms reweighted by the learner, one of
them started late (:mod:`torchrl_rave.transforms.reward_terms`)."""

from __future__ import annotations

from omegaconf import DictConfig

from torchrl_rave.transforms.reward_terms import TERMS_KEY, DelayedWeight, ReweightRewardTerms

__all__ = ["make_reward_relabelling", "update_reward_weights"]


def make_reward_relabelling(
    cfg: DictConfig, env
) -> tuple[ReweightRewardTerms | None, DelayedWeight | None]:
    """The replay-buffer transform that relabels the reward from ``env``'s terms with
    ``reward.weights``, and the schedule of ``reward.delayed``; ``(None, None)`` when no
    ``reward`` key is set. Raises before anything else is built when the env reports no
    terms or lacks a named one."""
    r = cfg.get("reward")
    weights = dict(r.weights or {}) if r is not None else {}
    if not weights and (r is None or r.delayed is None):
        return None, None
    spec = env.observation_spec
    names = list(spec[TERMS_KEY].keys()) if TERMS_KEY in spec.keys() else []  # noqa: SIM118 (a Composite)
    if not names:
        raise ValueError(
            f"reward.weights and reward.delayed reweight an env's reward terms, and "
            f"{cfg.env.name} reports none (an env names them in `reward_term_names` and "
            f"returns them in info['reward_terms'], as LearnToMove-v0 does)"
        )
    asked = set(weights) | ({r.delayed} if r.delayed is not None else set())
    unknown = sorted(asked - set(names))
    if unknown:
        raise ValueError(f"{cfg.env.name} has no reward term {unknown}; its terms are {names}")
    delayed = None
    if r.delayed is not None:
        delayed = DelayedWeight(
            float(weights.get(r.delayed, 1.0)),
            start_frames=r.delay_frames,
            metric=r.delay_metric,
            threshold=r.delay_threshold,
            ramp_frames=int(r.ramp_frames),
        )
        weights[r.delayed] = 0.0  # until it starts
    return ReweightRewardTerms(names, weights, scale=float(cfg.env.reward_scale)), delayed


def update_reward_weights(
    cfg: DictConfig,
    relabel: ReweightRewardTerms,
    delayed: DelayedWeight | None,
    counters: dict,
    metrics: dict,
) -> dict[str, float]:
    """Sets the delayed term's weight for the frames collected so far and the latest
    evaluation ``metrics``; its start frame lives in ``counters["reward_delay_from"]``, so
    a checkpoint keeps it. Returns ``train/reward_weight_<term>`` of every named term."""
    if delayed is not None:
        delayed.started_at = counters.get("reward_delay_from")
        weight = delayed.update(counters["frames"], metrics)
        counters["reward_delay_from"] = delayed.started_at
        relabel.set_weights({cfg.reward.delayed: weight})
    named = [*(cfg.reward.weights or {}), *([cfg.reward.delayed] if delayed is not None else [])]
    return {f"train/reward_weight_{n}": relabel.weights[n] for n in dict.fromkeys(named)}
