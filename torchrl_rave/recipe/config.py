"""The recipe's configuration: the algorithm table, and every check made before work starts."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import torch
from omegaconf import DictConfig, OmegaConf

from torchrl_rave.envs.families import BULLET_IDS, OSIM_IDS, import_env_family
from torchrl_rave.recipe import memory

__all__ = [
    "ALGORITHMS",
    "COMPILE_MODES",
    "FIXED_ON_RESUME",
    "Algorithm",
    "check_config",
    "check_resumable",
    "num_critics",
    "replay_buffer_size",
    "resolve_config",
]

COMPILE_MODES = [None, "default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs"]


@dataclass(frozen=True)
class Algorithm:
    """What ``algorithm=<name>`` selects: the TorchRL loss, the target estimator, K."""

    loss: str  # "ensemble_ddpg" | "td3" | "sac" | "ppo"
    estimator: str | None  # value-expansion estimator name; None: TD(0) (GAE for ppo)
    num_critics: int
    adaptive_alpha: bool = True

    @property
    def model_based(self) -> bool:
        return self.estimator is not None

    @property
    def on_policy(self) -> bool:
        """Learns from each batch it collects, then drops it (PPO); the others replay."""
        return self.loss == "ppo"


ALGORITHMS = {
    "ddpg": Algorithm("ensemble_ddpg", None, 1),
    "mve": Algorithm("ensemble_ddpg", "mve", 4),
    "steve": Algorithm("ensemble_ddpg", "steve", 4),
    "rave": Algorithm("ensemble_ddpg", "rave", 4, adaptive_alpha=True),
    "rave_constant": Algorithm("ensemble_ddpg", "rave", 4, adaptive_alpha=False),
    "td3": Algorithm("td3", None, 2),
    "sac": Algorithm("sac", None, 2),
    "ppo": Algorithm("ppo", None, 1),
}
PPO_SCHEDULES = ["linear", "constant"]
# the keys that size the world model: checked as positive, fixed on resume
WORLD_MODEL_SIZES = ["world_model.num_models"] + [
    f"world_model.{part}_{dim}"
    for part in ("transition", "reward", "termination")
    for dim in ("cells", "layers")
]
LOGGER_BACKENDS = {"": None, "csv": None, "tensorboard": "tensorboard", "wandb": "wandb"}
COLLECTOR_BACKENDS = {
    "direct": "one collector in the learner process",
    "process": "MultiSyncCollector: num_workers env processes",
    "ray": "RayCollector: num_workers Ray actors, on this machine or a cluster (ray.address)",
}


def _require(ok: bool, key: str, value, expected: str) -> None:
    if not ok:
        raise ValueError(f"config key {key}={value!r} is invalid: expected {expected}")


def check_config(cfg: DictConfig) -> Algorithm:
    """Rejects bad settings before anything is built; returns the selected algorithm."""
    import gymnasium as gym

    _require(cfg.algorithm in ALGORITHMS, "algorithm", cfg.algorithm, f"one of {list(ALGORITHMS)}")
    if cfg.algorithm == "ppo":
        check_ppo_config(cfg)
        cfg = resolve_config(cfg)  # the checks below see what runs
    _require(
        cfg.threads is None
        or (
            isinstance(cfg.threads, int) and not isinstance(cfg.threads, bool) and cfg.threads >= 1
        ),
        "threads",
        cfg.threads,
        "null or an integer >= 1",
    )
    _require(
        isinstance(cfg.keep_freed_memory, bool),
        "keep_freed_memory",
        cfg.keep_freed_memory,
        "true or false",
    )
    env_id = str(cfg.env.name)
    if ":" in env_id:  # gymnasium's "module:EnvId": importing the module registers the id
        import importlib

        module, env_id = env_id.split(":", 1)
        try:
            importlib.import_module(module)
        except ImportError as e:
            raise ValueError(
                f"config key env.name={cfg.env.name!r}: cannot import {module!r}: {e}"
            ) from e
    try:
        import_env_family(env_id)
    except ImportError as err:
        raise ValueError(f"config key env.name={cfg.env.name!r}: {err}") from None
    if env_id not in gym.registry:
        mujoco = sorted(k for k in gym.registry if k.endswith("-v5"))
        raise ValueError(
            f"config key env.name={cfg.env.name!r} is not a registered gymnasium id; "
            f"MuJoCo ids: {mujoco}; PyBullet ids (the bullet extra): {list(BULLET_IDS)}; "
            f"OpenSim ids (the osim extra): {list(OSIM_IDS)}"
        )
    positive = [
        "collector.total_frames",
        "collector.frames_per_batch",
        "replay_buffer.batch_size",
        *WORLD_MODEL_SIZES,
        "world_model.train_every",
        "network.actor_cells",
        "network.critic_cells",
        "network.num_layers",
        "td3.policy_delay",
        "eval.interval",
        "eval.episodes",
        "checkpoint.interval",
    ]
    non_negative = [
        "collector.init_random_frames",
        "world_model.pretrain_frames",
        "world_model.pretrain_updates",
        "estimator.horizon",
    ]
    for key in positive + non_negative:
        value = OmegaConf.select(cfg, key)
        low = 1 if key in positive else 0
        _require(
            isinstance(value, int) and not isinstance(value, bool) and value >= low,
            key,
            value,
            f"an integer >= {low}",
        )
    for key in ["optim.lr_actor", "optim.lr_critic", "optim.lr_alpha", "world_model.lr"]:
        value = OmegaConf.select(cfg, key)
        _require(float(value) > 0, key, value, "a number > 0")
    _require(float(cfg.optim.utd_ratio) > 0, "optim.utd_ratio", cfg.optim.utd_ratio, "> 0")
    _require(float(cfg.env.reward_scale) > 0, "env.reward_scale", cfg.env.reward_scale, "> 0")
    noise = cfg.env.get("action_noise", 0.0)
    _require(
        isinstance(noise, (int, float))
        and not isinstance(noise, bool)
        and math.isfinite(noise)
        and noise >= 0,
        "env.action_noise",
        noise,
        "a finite number >= 0 (the actuator noise's std in half action ranges; 0: none)",
    )
    _require(0 <= float(cfg.optim.gamma) <= 1, "optim.gamma", cfg.optim.gamma, "in [0, 1]")
    _require(0 < float(cfg.optim.tau) <= 1, "optim.tau", cfg.optim.tau, "in (0, 1]")
    _require(float(cfg.estimator.alpha) >= 0, "estimator.alpha", cfg.estimator.alpha, ">= 0")
    _require(
        float(cfg.estimator.alpha_error_scale) > 0,
        "estimator.alpha_error_scale",
        cfg.estimator.alpha_error_scale,
        "> 0",
    )
    _require(0 <= float(cfg.exploration.epsilon) <= 1, "exploration.epsilon",
             cfg.exploration.epsilon, "in [0, 1]")  # fmt: skip
    _require(float(cfg.exploration.sigma) >= 0, "exploration.sigma", cfg.exploration.sigma, ">= 0")
    _require(
        cfg.network.num_critics is None
        or (isinstance(cfg.network.num_critics, int) and cfg.network.num_critics >= 1),
        "network.num_critics",
        cfg.network.num_critics,
        "null or an integer >= 1",
    )
    _require(
        cfg.collector.backend in COLLECTOR_BACKENDS,
        "collector.backend",
        cfg.collector.backend,
        f"one of {list(COLLECTOR_BACKENDS)}",
    )
    workers = cfg.collector.num_workers
    _require(
        isinstance(workers, int) and not isinstance(workers, bool) and workers >= 1,
        "collector.num_workers",
        workers,
        "an integer >= 1",
    )
    _require(
        isinstance(cfg.collector.weight_sync_every, int) and cfg.collector.weight_sync_every >= 1,
        "collector.weight_sync_every",
        cfg.collector.weight_sync_every,
        "an integer >= 1 (updates between two weight pushes)",
    )
    timeout = cfg.collector.get("timeout_s")
    _require(
        timeout is None
        or (isinstance(timeout, (int, float)) and not isinstance(timeout, bool) and timeout > 0),
        "collector.timeout_s",
        timeout,
        "a number of seconds > 0, or null (wait for a batch forever)",
    )
    if cfg.collector.backend == "direct":
        _require(workers == 1, "collector.num_workers", workers,
                 "1 with collector.backend=direct (use collector.backend=process or ray for more)")  # fmt: skip
    else:
        _require(
            cfg.collector.frames_per_batch % workers == 0,
            "collector.frames_per_batch",
            cfg.collector.frames_per_batch,
            f"a multiple of collector.num_workers ({workers}): each worker collects an equal share",
        )
    if cfg.collector.backend == "ray":
        check_ray_config(cfg)
    _require(isinstance(cfg.compile.enabled, bool), "compile.enabled", cfg.compile.enabled,
             "true or false")  # fmt: skip
    _require(cfg.compile.mode in COMPILE_MODES, "compile.mode", cfg.compile.mode,
             f"one of {COMPILE_MODES} (null: torch.compile's default)")  # fmt: skip
    total = cfg.collector.total_frames
    _require(
        cfg.collector.frames_per_batch <= total,
        "collector.frames_per_batch",
        cfg.collector.frames_per_batch,
        f"<= collector.total_frames ({total})",
    )
    size = replay_buffer_size(cfg)
    _require(size >= 1, "replay_buffer.size", cfg.replay_buffer.size, "null or an integer >= 1")
    _require(
        cfg.replay_buffer.batch_size <= size,
        "replay_buffer.batch_size",
        cfg.replay_buffer.batch_size,
        f"<= the replay buffer size ({size})",
    )
    _require(
        cfg.logger.backend in LOGGER_BACKENDS,
        "logger.backend",
        cfg.logger.backend,
        f"one of {list(LOGGER_BACKENDS)}",
    )
    package = LOGGER_BACKENDS[cfg.logger.backend]
    if package is not None:
        try:
            __import__(package)
        except ImportError as err:
            raise ValueError(
                f"logger.backend={cfg.logger.backend!r} needs the {package!r} package: "
                f"pip install {package}"
            ) from err
    if cfg.collector.device is not None:
        try:
            torch.device(cfg.collector.device)
        except RuntimeError as err:
            raise ValueError(
                f"config key collector.device={cfg.collector.device!r}: {err}"
            ) from err
    return ALGORITHMS[cfg.algorithm]


def check_ppo_config(cfg: DictConfig) -> None:
    """The ``ppo.*`` keys (``algorithm=ppo``)."""
    p = cfg.ppo
    for key in ("rollout_frames", "epochs", "minibatch_size"):
        value = p[key]
        _require(isinstance(value, int) and not isinstance(value, bool) and value >= 1,
                 f"ppo.{key}", value, "an integer >= 1")  # fmt: skip
    _require(p.minibatch_size <= p.rollout_frames, "ppo.minibatch_size", p.minibatch_size,
             f"<= ppo.rollout_frames ({p.rollout_frames})")  # fmt: skip
    _require(0 < float(p.clip_epsilon) < 1, "ppo.clip_epsilon", p.clip_epsilon, "in (0, 1)")
    _require(0 <= float(p.gae_lambda) <= 1, "ppo.gae_lambda", p.gae_lambda, "in [0, 1]")
    _require(float(p.lr) > 0, "ppo.lr", p.lr, "a number > 0")
    for key in ("entropy_coef", "critic_coef"):
        _require(float(p[key]) >= 0, f"ppo.{key}", p[key], "a number >= 0")
    _require(p.max_grad_norm is None or float(p.max_grad_norm) > 0, "ppo.max_grad_norm",
             p.max_grad_norm, "null (no clipping) or a number > 0")  # fmt: skip
    _require(p.lr_schedule in PPO_SCHEDULES, "ppo.lr_schedule", p.lr_schedule,
             f"one of {PPO_SCHEDULES}")  # fmt: skip
    _require(not cfg.logger.q_points, "logger.q_points", cfg.logger.q_points,
             "null with algorithm=ppo (its critic is V(s), there is no Q(s, a) to log)")  # fmt: skip
    _require(not cfg.compile.enabled, "compile.enabled", cfg.compile.enabled,
             "false with algorithm=ppo (its update is not compiled)")  # fmt: skip


def resolve_config(cfg: DictConfig) -> DictConfig:
    """The settings a run actually uses: with ``algorithm=ppo`` the collector gathers
    ``ppo.rollout_frames`` per batch from the first frame on (no random warm-up), and the
    rollout buffer holds one batch, read in minibatches of ``ppo.minibatch_size``. Other
    algorithms are returned as they are."""
    if cfg.algorithm != "ppo":
        return cfg
    cfg = cfg.copy()
    cfg.collector.frames_per_batch = min(cfg.ppo.rollout_frames, cfg.collector.total_frames)
    cfg.collector.init_random_frames = 0
    cfg.replay_buffer.size = cfg.collector.frames_per_batch
    cfg.replay_buffer.batch_size = min(cfg.ppo.minibatch_size, cfg.replay_buffer.size)
    return cfg


def check_ray_config(cfg: DictConfig) -> None:
    """The ``ray.*`` keys, and Ray itself, checked before anything starts."""
    import importlib.util

    if importlib.util.find_spec("ray") is None:
        raise ValueError(
            "config key collector.backend='ray' needs the 'ray' package: "
            "pip install 'torchrl-rave[ray]' (or pip install ray)"
        )
    r = cfg.ray
    _require(r.address is None or isinstance(r.address, str), "ray.address", r.address,
             "null (a local instance), 'auto' or a cluster address")  # fmt: skip
    _require(r.num_cpus is None or (isinstance(r.num_cpus, int) and r.num_cpus >= 1),
             "ray.num_cpus", r.num_cpus, "null or an integer >= 1")  # fmt: skip
    _require(isinstance(r.worker_cpus, (int, float)) and r.worker_cpus > 0,
             "ray.worker_cpus", r.worker_cpus, "a number > 0")  # fmt: skip
    _require(r.worker_memory is None or (isinstance(r.worker_memory, int) and r.worker_memory > 0),
             "ray.worker_memory", r.worker_memory, "null or a number of bytes > 0")  # fmt: skip
    resources = r.worker_resources or {}
    _require(all(isinstance(v, (int, float)) and v > 0 for v in resources.values()),
             "ray.worker_resources", resources, "a mapping of resource name to an amount > 0")  # fmt: skip
    import ray

    if ray.is_initialized():
        check_ray_fits(cfg, ray.cluster_resources(), "the running Ray instance")
    elif r.address is None:
        local = {"CPU": r.num_cpus or os.cpu_count(), "memory": float("inf")}
        check_ray_fits(cfg, local, "a local Ray instance (ray.num_cpus)")
    # a cluster (ray.address) is checked by make_ray_collector once connected


def check_ray_fits(cfg: DictConfig, total: dict, where: str) -> None:
    """Refuses collector actors that Ray resources ``total`` cannot hold all at once: the
    ones left over would wait for resources forever, and the run with them."""
    workers, r = cfg.collector.num_workers, cfg.ray
    needs = [("CPU", "ray.worker_cpus", r.worker_cpus)]
    if r.worker_memory is not None:
        needs.append(("memory", "ray.worker_memory", r.worker_memory))
    needs += [
        (name, f"ray.worker_resources.{name}", n) for name, n in (r.worker_resources or {}).items()
    ]
    for name, key, amount in needs:
        have = total.get(name, 0)
        _require(
            workers * amount <= have,
            key,
            amount,
            f"collector.num_workers x {amount:g} = {workers * amount:g} {name} <= the {have:g} "
            f"{name} of {where}; lower it (fractions are fine), use fewer workers or add nodes",
        )


def apply_process_settings(cfg: DictConfig) -> None:
    """The learner process's own settings: ``threads`` (torch's thread count) and
    ``keep_freed_memory`` (:func:`~torchrl_rave.recipe.memory.keep_freed_memory`)."""
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    if cfg.keep_freed_memory:
        memory.keep_freed_memory()


def replay_buffer_size(cfg: DictConfig) -> int:
    size = cfg.replay_buffer.size
    return min(1_000_000, cfg.collector.total_frames) if size is None else int(size)


def num_critics(cfg: DictConfig, algo: Algorithm) -> int:
    return algo.num_critics if cfg.network.num_critics is None else cfg.network.num_critics


# Keys that shape the saved modules, buffers or algorithm: a resumed run cannot change them.
FIXED_ON_RESUME = [
    "algorithm",
    "env.name",
    "env.action_noise",
    "network",
    *WORLD_MODEL_SIZES,
    "ppo.rollout_frames",
    "estimator.horizon",
]


def check_resumable(cfg: DictConfig, saved: DictConfig) -> None:
    for key in FIXED_ON_RESUME:
        new, old = OmegaConf.select(cfg, key), OmegaConf.select(saved, key)
        if new != old:
            raise ValueError(
                f"resume={cfg.resume!r}: config key {key} is {new!r} but the run was "
                f"started with {old!r}; it cannot change on resume"
            )
