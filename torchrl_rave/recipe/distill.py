"""Noisy-target distillation (the paper's supplement, Learn to Move): fit a fresh policy
on a trained one's (observation, action) pairs with the target part of the observation
replaced by uniform noise over its range, so that the new policy reproduces the old gait
whatever the target says and later training can make it follow the target.

:func:`distill_actor` is the fitting, on any TorchRL actor; :func:`distill_run` is what
``python recipes/distill.py`` runs: a run directory in, a run directory out, whose
checkpoint is the source's with the actor (and its target copy) replaced, so that
``resume=<out>`` trains on from it.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from torchrl_rave.recipe.agent import make_actor, make_agent, make_env, make_replay_buffer
from torchrl_rave.recipe.checkpoint import RunCheckpoint, missing_checkpoint, saved_config
from torchrl_rave.recipe.curriculum import make_curriculum, stage_config
from torchrl_rave.recipe.episode import EpisodeCheckpoint
from torchrl_rave.recipe.schema import defaults
from torchrl_rave.recipe.trust import check_trusted

__all__ = ["collect_pairs", "distill_actor", "distill_run"]


@torch.no_grad()
def collect_pairs(
    env, actor: TensorDictModuleBase, frames: int, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """``frames`` (observation, action) pairs ``[frames, obs]``, ``[frames, act]`` of
    ``actor``'s deterministic policy in ``env``, episode after episode from ``seed``."""
    observations, actions = [], []
    env.set_seed(seed)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        while sum(len(o) for o in observations) < frames:
            rollout = env.rollout(frames, actor, break_when_any_done=True)
            observations.append(rollout["observation"])
            actions.append(rollout["action"])
    return torch.cat(observations)[:frames], torch.cat(actions)[:frames]


def distill_actor(
    student: TensorDictModuleBase,
    observations: torch.Tensor,
    actions: torch.Tensor,
    target: slice,
    low: torch.Tensor | float,
    high: torch.Tensor | float,
    *,
    steps: int = 2000,
    batch_size: int = 256,
    lr: float = 1e-3,
    generator: torch.Generator | None = None,
) -> list[float]:
    """Fits ``student``'s deterministic action to ``actions`` (mean squared error, Adam),
    each minibatch's ``observations[:, target]`` replaced by uniform noise in
    ``[low, high]`` (per entry, or one number). Returns the loss of every step.

    Examples:
        >>> from torchrl.modules import MLP
        >>> from tensordict.nn import TensorDictModule
        >>> student = TensorDictModule(MLP(in_features=3, out_features=1, num_cells=[16]),
        ...                            in_keys=["observation"], out_keys=["action"])
        >>> obs = torch.randn(512, 3)
        >>> act = 0.5 * obs[:, :1]  # the teacher reads the first entry; the rest is target
        >>> losses = distill_actor(student, obs, act, slice(1, 3), -1.0, 1.0, steps=300)
        >>> losses[-1] < 0.05 * losses[0]
        True
    """
    if observations.shape[0] != actions.shape[0] or observations.shape[0] == 0:
        raise ValueError(
            f"distill_actor needs as many actions as observations, and some: got "
            f"{observations.shape[0]} observations and {actions.shape[0]} actions"
        )
    width = len(range(*target.indices(observations.shape[-1])))
    if width == 0:
        raise ValueError(f"the target slice {target} selects nothing of {observations.shape[-1]}")
    low = torch.as_tensor(low, dtype=observations.dtype).expand(width)
    high = torch.as_tensor(high, dtype=observations.dtype).expand(width)
    if not bool((low <= high).all()):
        raise ValueError("the target range must have low <= high")
    optimizer = torch.optim.Adam(student.parameters(), lr=lr)
    losses = []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(steps):
            pick = torch.randint(0, observations.shape[0], (batch_size,), generator=generator)
            obs = observations[pick].clone()
            noise = torch.rand(batch_size, width, generator=generator, dtype=obs.dtype)
            obs[:, target] = low + (high - low) * noise
            predicted = student(TensorDict(observation=obs, batch_size=[batch_size]))["action"]
            loss = torch.nn.functional.mse_loss(predicted, actions[pick])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(loss.item())
    return losses


def distill_run(
    run_dir: str | Path,
    out_dir: str | Path,
    target: slice | None = None,
    *,
    frames: int = 10_000,
    low: float | None = None,
    high: float | None = None,
    steps: int = 2000,
    seed: int = 0,
    trust: bool = False,
) -> dict:
    """Collects ``frames`` pairs from ``run_dir``'s latest policy, fits a freshly built
    actor of the same config on them (:func:`distill_actor`; ``target`` is the slice of
    the observation to noise, by default the env's ``target_observation``; its range is
    ``[low, high]``, by default the env's ``target_range``, or for a slice of the caller's
    each entry's range in the pairs), and writes ``out_dir``:
    a run directory whose checkpoint is ``run_dir``'s with the actor, its target copy and
    the exploration policy replaced by the fitted one. Nothing of ``run_dir`` changes.
    ``trust`` as for :func:`~torchrl_rave.recipe.load_agent`.

    The pairs are collected in the env of the curriculum stage the run had reached (a
    ``curriculum.kwarg`` run's stage speed), recorded under ``collected_with`` and in the
    new run's saved ``env.kwargs``. With the
    env's own target part, the noise covers every value the task can produce there (the
    env's ``target_range``: for ``LearnToMove-v0``, ``[-v, v]`` with ``v`` its largest
    target speed), not only those seen in the pairs, which on a task with a constant
    target are one value. Returns, and writes to ``out_dir/distill.json``, the source, the
    number of pairs, the env keywords they were collected with, the target slice, the
    noise's range and the fit's first and last losses."""
    problems = [f"{name}={value}: expected an integer >= 1"
                for name, value in (("frames", frames), ("steps", steps)) if value < 1]  # fmt: skip
    infinite = [f"{name}={value}: expected a finite number (the noise is uniform over "
                "[low, high])" for name, value in (("low", low), ("high", high))
                if value is not None and not math.isfinite(value)]  # fmt: skip
    problems += infinite
    if not infinite and low is not None and high is not None and not low <= high:
        problems.append(f"low={low}, high={high}: the target range must have low <= high")
    if problems:  # before the run is read or any pair collected
        raise ValueError("; ".join(problems))
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} exists and is not empty: distillation writes a new run")
    source = RunCheckpoint(run_dir)
    path = source.latest()
    if path is None:
        raise missing_checkpoint(run_dir)
    cfg = saved_config(run_dir, defaults())
    if not trust:
        check_trusted(
            cfg, set(), f"distill_run({str(run_dir)!r})", "Pass trust=True if you trust it."
        )
    if "ray" in cfg:
        cfg.ray.address = None
    # the pairs come from the env of the curriculum stage the run had reached
    counters_saved = source.read("counters", path)
    curriculum, env_cfg = make_curriculum(cfg), cfg
    if curriculum is not None:
        curriculum.load_state_dict({"stage": counters_saved.get("curriculum_stage", 0)})
        env_cfg = stage_config(cfg, curriculum)
    env = make_env(env_cfg, torch.device("cpu"))
    agent = make_agent(cfg, env)
    rb = make_replay_buffer(cfg, torch.device("cpu"))
    counters: dict = {}
    logger: dict = {}
    source.load(
        path=path,
        restore_rng=False,
        counters=counters,
        replay_buffer=rb,
        logger=logger,
        **agent.state_components(),
    )
    task_range = None
    if target is None:  # the env's own target part (LearnToMove-v0's target field)
        try:
            target = env.base_env._env.get_wrapper_attr("target_observation")
            task_range = env.base_env._env.get_wrapper_attr("target_range")
        except AttributeError:
            env.close()
            raise ValueError(
                f"{cfg.env.name} names no target part of its observation: pass a target slice"
            ) from None
    observations, actions = collect_pairs(env, agent.actor, frames, seed)
    picked = observations[:, target]
    if task_range is not None:  # every value the task can produce at this stage
        low_t = task_range[0] if low is None else low
        high_t = task_range[1] if high is None else high
    else:  # a slice of the caller's: the range seen in the pairs
        low_t = picked.min(0).values if low is None else low
        high_t = picked.max(0).values if high is None else high
        spread = float(torch.as_tensor(high_t - low_t).max())
        if spread < 1e-6:
            env.close()
            raise ValueError(
                f"the target entries {target.start}:{target.stop} take one value in the "
                f"{frames} pairs (range {spread:.2g}): noise over it would be none, and the "
                "fit plain behaviour cloning; pass the range the task can produce "
                "(low=, high=; --low/--high)"
            )
    torch.manual_seed(seed)
    student = make_actor(cfg, env, agent.algorithm)[0]
    generator = torch.Generator().manual_seed(seed)
    losses = distill_actor(
        student, observations, actions, target, low_t, high_t, steps=steps, generator=generator
    )
    with torch.no_grad():
        for mine, fitted in zip(agent.actor.parameters(), student.parameters(), strict=True):
            mine.copy_(fitted)
        targets = getattr(agent.loss, "target_actor_network_params", None)
        if targets is not None:
            targets.update_(agent.loss.actor_network_params.detach())
    env.close()
    out.mkdir(parents=True, exist_ok=True)
    RunCheckpoint(out).save(
        int(counters["frames"]),
        # the stage's env keywords, which the pairs were collected with, are the saved
        # config's: a resumed curriculum sets the same value for the same stage
        config=OmegaConf.to_container(env_cfg, resolve=True),
        counters=counters,
        replay_buffer=rb,
        logger={},
        episode=EpisodeCheckpoint(),  # none kept: the distilled policy starts new episodes
        **agent.state_components(),
    )
    noise = [torch.as_tensor(v, dtype=torch.float64) for v in (low_t, high_t)]
    kwargs = env_cfg.env.kwargs
    result = {"source": str(run_dir), "frames": int(counters["frames"]), "pairs": len(observations),
              "collected_with": None if kwargs is None else OmegaConf.to_container(kwargs),
              "target": [target.start, target.stop],
              "noise": [float(noise[0].min()), float(noise[1].max())],
              "steps": steps, "seed": seed,
              "first_loss": losses[0], "last_loss": losses[-1]}  # fmt: skip
    (out / "distill.json").write_text(json.dumps(result, indent=1) + "\n")
    return result
