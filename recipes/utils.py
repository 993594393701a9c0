"""Factories (``make_*``), config checks, evaluation and checkpoints for ``rave_mujoco.py``."""

from __future__ import annotations

import functools
import os
import random
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import (
    DoubleToFloat,
    GymEnv,
    RewardScaling,
    RewardSum,
    StepCounter,
    TransformedEnv,
)
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, ProbabilisticActor, TanhModule, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss, TD3Loss, ValueEstimators
from torchrl.record.loggers import Logger, get_logger

from torchrl_rave import (
    EnsembleDDPGLoss,
    EpsilonGaussianModule,
    ForeachSoftUpdate,
    WorldModelEnsemble,
    WorldModelLoss,
    make_value_expansion_estimator,
)


@dataclass(frozen=True)
class Algorithm:
    """What ``algorithm=<name>`` selects: the TorchRL loss, the target estimator, K."""

    loss: str  # "ensemble_ddpg" | "td3" | "sac"
    estimator: str | None  # value-expansion estimator name; None: TD(0)
    num_critics: int
    adaptive_alpha: bool = True

    @property
    def model_based(self) -> bool:
        return self.estimator is not None


ALGORITHMS = {
    "ddpg": Algorithm("ensemble_ddpg", None, 1),
    "mve": Algorithm("ensemble_ddpg", "mve", 4),
    "steve": Algorithm("ensemble_ddpg", "steve", 4),
    "rave": Algorithm("ensemble_ddpg", "rave", 4, adaptive_alpha=True),
    "rave_constant": Algorithm("ensemble_ddpg", "rave", 4, adaptive_alpha=False),
    "td3": Algorithm("td3", None, 2),
    "sac": Algorithm("sac", None, 2),
}
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


# --------------------------------------------------------------------------- config checks
def _require(ok: bool, key: str, value, expected: str) -> None:
    if not ok:
        raise ValueError(f"config key {key}={value!r} is invalid: expected {expected}")


def check_config(cfg: DictConfig) -> Algorithm:
    """Rejects bad settings before anything is built; returns the selected algorithm."""
    import gymnasium as gym

    _require(cfg.algorithm in ALGORITHMS, "algorithm", cfg.algorithm, f"one of {list(ALGORITHMS)}")
    _require(
        cfg.threads is None
        or (
            isinstance(cfg.threads, int) and not isinstance(cfg.threads, bool) and cfg.threads >= 1
        ),
        "threads",
        cfg.threads,
        "null or an integer >= 1",
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
    if env_id not in gym.registry:
        mujoco = sorted(k for k in gym.registry if k.endswith("-v5"))
        raise ValueError(
            f"config key env.name={cfg.env.name!r} is not a registered gymnasium id; "
            f"MuJoCo ids: {mujoco}"
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


def replay_buffer_size(cfg: DictConfig) -> int:
    size = cfg.replay_buffer.size
    return min(1_000_000, cfg.collector.total_frames) if size is None else int(size)


def num_critics(cfg: DictConfig, algo: Algorithm) -> int:
    return algo.num_critics if cfg.network.num_critics is None else cfg.network.num_critics


# --------------------------------------------------------------------------- factories
def make_env(cfg: DictConfig, device: torch.device) -> TransformedEnv:
    env = TransformedEnv(
        GymEnv(cfg.env.name, device=device, **(cfg.env.kwargs or {})), DoubleToFloat()
    )
    env.append_transform(StepCounter())
    env.append_transform(RewardSum())  # before the scaling: returns stay in env units
    if cfg.env.reward_scale != 1.0:
        env.append_transform(RewardScaling(loc=0.0, scale=cfg.env.reward_scale))
    return env


def _mlp(cfg: DictConfig, in_features: int, out_features: int, cells: int) -> MLP:
    # num_layers counts FC layers with the output layer (paper appendix A: 4)
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=[cells] * (cfg.network.num_layers - 1),
        activation_class=nn.ReLU,
    )


def make_actor(cfg: DictConfig, env, algo: Algorithm):
    """The policy and the exploration policy the collector runs.

    Deterministic policies end in :class:`~torchrl.modules.TanhModule`, which maps onto the
    action box; SAC's policy is a tanh-Gaussian and explores by sampling.
    """
    spec = env.action_spec
    S, A = env.observation_spec["observation"].shape[-1], spec.shape[-1]
    if algo.loss == "sac":
        net = nn.Sequential(_mlp(cfg, S, 2 * A, cfg.network.actor_cells), NormalParamExtractor())
        actor = ProbabilisticActor(
            TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
            in_keys=["loc", "scale"],
            spec=spec,
            distribution_class=TanhNormal,
            distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
            default_interaction_type=ExplorationType.RANDOM,
        )
        return actor, actor
    actor = TensorDictSequential(
        TensorDictModule(
            _mlp(cfg, S, A, cfg.network.actor_cells), in_keys=["observation"], out_keys=["param"]
        ),
        TanhModule(in_keys=["param"], out_keys=["action"], spec=spec),
    )
    noise = EpsilonGaussianModule(
        spec, sigma=cfg.exploration.sigma, epsilon=cfg.exploration.epsilon
    )
    return actor, TensorDictSequential(actor, noise)


def make_critic(cfg: DictConfig, env) -> ValueOperator:
    S = env.observation_spec["observation"].shape[-1]
    A = env.action_spec.shape[-1]
    return ValueOperator(
        _mlp(cfg, S + A, 1, cfg.network.critic_cells), in_keys=["observation", "action"]
    )


def make_world_model(cfg: DictConfig, env) -> WorldModelEnsemble:
    w = cfg.world_model
    return WorldModelEnsemble.from_specs(
        env.observation_spec,
        env.action_spec,
        num_models=w.num_models,
        transition_cells=w.transition_cells,
        transition_layers=w.transition_layers,
        reward_cells=w.reward_cells,
        reward_layers=w.reward_layers,
        termination_cells=w.termination_cells,
        termination_layers=w.termination_layers,
    )


def make_loss(cfg: DictConfig, env, algo: Algorithm, actor, critic, world_model):
    """The TorchRL loss with its target estimator, and the soft target updater."""
    K = num_critics(cfg, algo)
    if algo.loss == "sac":
        loss = SACLoss(
            actor, critic, num_qvalue_nets=K, loss_function="l2", action_spec=env.action_spec
        )
    elif algo.loss == "td3":
        loss = TD3Loss(
            actor,
            critic,
            action_spec=env.action_spec,
            num_qvalue_nets=K,
            policy_noise=cfg.td3.policy_noise,
            noise_clip=cfg.td3.noise_clip,
            loss_function="l2",
        )
    else:
        loss = EnsembleDDPGLoss(actor, critic, action_spec=env.action_spec, num_qvalue_nets=K)
    if algo.estimator is None:
        loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.optim.gamma)
    else:
        e = cfg.estimator
        # check_inputs=False: batches were checked for NaN/inf on their way into the buffer
        kwargs = dict(
            world_model=world_model, gamma=cfg.optim.gamma, horizon=e.horizon, check_inputs=False
        )
        if algo.estimator == "rave":
            kwargs.update(
                alpha=e.alpha,
                adaptive_alpha=algo.adaptive_alpha,
                alpha_error_scale=e.alpha_error_scale,
            )
        loss.make_value_estimator(make_value_expansion_estimator(algo.estimator, loss, **kwargs))
    return loss, ForeachSoftUpdate(loss, tau=cfg.optim.tau)


def make_optimizers(cfg: DictConfig, loss, world_model) -> dict[str, torch.optim.Optimizer]:
    # fused Adam: one kernel per step instead of a Python loop over tensors (3x on CPU)
    def adam(params, lr):
        return torch.optim.Adam(list(params), lr=lr, fused=True)

    optimizers = {
        "actor": adam(loss.actor_network_params.values(True, True), cfg.optim.lr_actor),
        "critic": adam(loss.qvalue_network_params.values(True, True), cfg.optim.lr_critic),
    }
    if isinstance(loss, SACLoss):
        optimizers["alpha"] = adam([loss.log_alpha], cfg.optim.lr_alpha)
    if world_model is not None:
        optimizers["world_model"] = adam(world_model.parameters(), cfg.world_model.lr)
    return optimizers


def make_world_model_loss(world_model: WorldModelEnsemble | None) -> WorldModelLoss | None:
    # the collector's batches are checked for NaN/inf before they reach the buffer
    return None if world_model is None else WorldModelLoss(world_model, check_finite=False)


def world_model_update(wm_loss: WorldModelLoss, optimizer, batch: TensorDictBase):
    """One world-model step (transition + reward + termination); returns the loss outputs."""
    out = wm_loss(batch)
    optimizer.zero_grad()
    (out["loss_transition"] + out["loss_reward"] + out["loss_termination"]).backward()
    optimizer.step()
    return out


def agent_update(loss, optimizers: dict, target_updater, batch: TensorDictBase, step_actor=True):
    """One agent step: critic (and, with ``step_actor``, actor, SAC temperature and the
    soft target update); returns the loss outputs."""
    out = loss(batch)
    for name in ("actor", "critic", "alpha"):
        if name in optimizers:
            optimizers[name].zero_grad()
    # Each loss sees the other networks detached (and targets carry no gradient), so one
    # backward over the sum gives every network exactly its own gradient.
    sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    optimizers["critic"].step()
    if step_actor:
        optimizers["actor"].step()
        if "alpha" in optimizers:
            optimizers["alpha"].step()
        target_updater.step()
    return out


COMPILE_MODES = [None, "default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs"]


def make_update_steps(cfg: DictConfig, loss, wm_loss, optimizers: dict, target_updater):
    """The recipe's two update steps on a batch: ``world_model_step(batch)`` and
    ``agent_step(batch, step_actor)``; with ``compile.enabled`` both go through
    ``torch.compile`` (``compile.mode``). Compiling happens at the first call of each, and
    again once for ``step_actor=False`` under TD3's policy delay."""

    def world_model_step(batch):
        return world_model_update(wm_loss, optimizers["world_model"], batch)

    def agent_step(batch, step_actor=True):
        return agent_update(loss, optimizers, target_updater, batch, step_actor)

    if cfg.compile.enabled:
        world_model_step = torch.compile(world_model_step, mode=cfg.compile.mode)
        agent_step = torch.compile(agent_step, mode=cfg.compile.mode)
    return world_model_step, agent_step


def make_collector(cfg: DictConfig, env, policy, device, frames_done: int = 0):
    """A collector for the frames still to go (``frames_done`` > 0 when resuming).

    ``collector.backend=direct`` steps ``env`` in this process. ``process`` runs
    ``collector.num_workers`` env processes through TorchRL's ``MultiSyncCollector``, and
    ``ray`` as many Ray actors through TorchRL's ``RayCollector`` (see
    :func:`make_ray_collector`). Workers build their own env from the config, run the
    exploration policy on the CPU and collect ``frames_per_batch / num_workers`` frames per
    batch; the batch holds every worker's share, so the learner's update-to-data ratio is
    exact. :func:`push_policy_weights` sends the learner's weights to the workers.
    """
    remaining = cfg.collector.total_frames - frames_done
    common = dict(
        frames_per_batch=min(cfg.collector.frames_per_batch, remaining),
        total_frames=remaining,
        init_random_frames=max(0, cfg.collector.init_random_frames - frames_done),
    )
    if cfg.collector.backend == "direct":
        return Collector(
            env,
            policy,
            device=device,
            auto_register_policy_transforms=False,  # our policies keep no recurrent state
            **common,
        )
    workers = cfg.collector.num_workers
    common["frames_per_batch"] -= common["frames_per_batch"] % workers
    cpu = torch.device("cpu")
    if cfg.collector.backend == "ray":
        collector = make_ray_collector(cfg, common)
    else:
        collector = MultiSyncCollector(
            [functools.partial(make_env, cfg, cpu)] * workers,
            policy,
            device=cpu,  # actors run the exploration policy on the CPU
            storing_device=cpu,
            cat_results="stack",
            **common,
        )
    # distinct, reproducible streams per worker; a resumed run does not replay old episodes
    collector.set_seed(cfg.env.seed + frames_done)
    push_policy_weights(collector, policy)
    return collector


def worker_policy(cfg: DictConfig):
    """The exploration policy of a Ray collector worker, built on its CPU from the config;
    its weights come from the learner (:func:`push_policy_weights`)."""
    torch.set_num_threads(max(1, int(cfg.ray.worker_cpus)))
    env = make_env(cfg, torch.device("cpu"))
    try:
        return make_actor(cfg, env, ALGORITHMS[cfg.algorithm])[1]
    finally:
        env.close()


class RayWorkerCollector(Collector):
    """TorchRL's ``Collector`` with a one-line repr: Ray prefixes every line a worker logs
    with its actor's repr, which for a ``Collector`` spans the whole env and policy."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}(worker={getattr(self, 'worker_idx', '?')})"


def make_ray_collector(cfg: DictConfig, common: dict):
    """TorchRL's ``RayCollector``: ``collector.num_workers`` Ray actors, each a CPU
    ``Collector`` with its own env and exploration policy, collecting in lockstep.

    With Ray not yet started in this process, ``ray.address=null`` starts a local instance
    (``ray.num_cpus`` CPUs) and ``auto`` or a cluster address joins one. Each actor reserves
    ``ray.worker_cpus`` CPUs, ``ray.worker_memory`` bytes and ``ray.worker_resources``.
    Weights travel by TorchRL's Ray weight-sync scheme. Every node needs torchrl-rave and
    the env's packages installed; this module's factories travel with the actors by value.
    """
    import sys
    import warnings

    import ray
    import ray.cloudpickle
    from torchrl.collectors.distributed import RayCollector

    # the env and policy factories live in this recipe module, which Ray workers cannot
    # import by name: pickle them by value
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    r = cfg.ray
    ray_init = {"num_cpus": r.num_cpus, "include_dashboard": False}
    if r.address is not None and not ray.is_initialized():
        # join the cluster here (a driver connection, dropped when this process exits) so
        # that its resources are checked before any actor waits for them
        ray.init(address=r.address)
        check_ray_fits(cfg, ray.cluster_resources(), f"the Ray cluster at {r.address}")
    remote = {"num_cpus": r.worker_cpus, "num_gpus": 0}  # actors explore on the CPU
    if r.worker_memory is not None:
        remote["memory"] = r.worker_memory
    if r.worker_resources:
        remote["resources"] = dict(r.worker_resources)
    cpu = torch.device("cpu")
    with warnings.catch_warnings():
        # the policy comes from a factory; its weights are pushed explicitly
        warnings.filterwarnings("ignore", message="The policy is not an nn.Module")
        return RayCollector(
            [functools.partial(make_env, cfg, cpu)] * cfg.collector.num_workers,
            policy_factory=functools.partial(worker_policy, cfg),
            collector_class=RayWorkerCollector,
            sync=True,  # one share from every worker per batch
            device=cpu,
            storing_device=cpu,
            ray_init_config=ray_init,
            remote_configs=remote,
            collector_kwargs={"auto_register_policy_transforms": False},
            **common,
        )


def push_policy_weights(collector, policy) -> None:
    """Sends ``policy``'s current weights to every collector worker (TorchRL's weight-sync
    schemes; a no-op for the direct backend, which runs ``policy`` itself)."""
    if isinstance(collector, Collector):
        return
    collector.update_policy_weights_(TensorDict.from_module(policy).data)


def make_replay_buffer(cfg: DictConfig, device) -> TensorDictReplayBuffer:
    return TensorDictReplayBuffer(
        storage=LazyTensorStorage(replay_buffer_size(cfg), device=device),
        batch_size=cfg.replay_buffer.batch_size,
    )


def make_logger(cfg: DictConfig, run_dir: str, state: dict | None = None) -> Logger | None:
    if not cfg.logger.backend:
        return None
    return get_logger(
        cfg.logger.backend,
        logger_name=str(run_dir),
        experiment_name=cfg.logger.exp_name or cfg.algorithm,
        state_dict=state,
        wandb_kwargs={"project": cfg.logger.project, "config": OmegaConf.to_container(cfg)},
    )


# --------------------------------------------------------------------------- evaluation
@torch.no_grad()
def evaluate(env, actor, episodes: int) -> dict[str, float]:
    """Deterministic-policy episodes: return mean/std, length, and the falling rate."""
    returns, lengths, falls = [], [], []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(episodes):
            rollout = env.rollout(1_000_000, actor, break_when_any_done=True)
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


def critic_mean(loss, td: TensorDictBase) -> torch.Tensor:
    """``Q(s, a)`` ``[*B]`` averaged over the loss's stacked critics (``[K, ...]`` params)."""
    params = loss.qvalue_network_params
    values = []
    for k in range(params.batch_size[0]):
        with params[k].to_module(loss.qvalue_network):
            values.append(loss.qvalue_network(td.clone())["state_action_value"].squeeze(-1))
    return torch.stack(values).mean(0)


class CollectorFailure(RuntimeError):
    """A collector worker raised or died; the run stopped with a checkpoint."""


class NonFiniteEnvOutput(RuntimeError):
    """The environment produced NaN or infinite observations or rewards."""


def check_finite(data: TensorDictBase) -> str | None:
    """Names the first collected entry holding NaN/inf, or ``None`` when all are finite."""
    for key in ("observation", ("next", "observation"), ("next", "reward")):
        if not bool(torch.isfinite(data[key]).all()):
            return str(key)
    return None


# --------------------------------------------------------------------------- checkpoints
def rng_state() -> dict:
    state = {
        "torch": torch.get_rng_state(),
        "numpy": np.random.get_state(),
        "python": random.getstate(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


class Checkpointer:
    """Writes ``<run_dir>/checkpoints/<frames>/`` (``state.pt`` + the replay buffer dumped with
    TorchRL's ``ReplayBuffer.dumps``) and then points ``checkpoints/latest`` at it.

    The pointer file is replaced atomically after the new checkpoint is complete, so a kill
    at any moment leaves the previous checkpoint valid; older checkpoints are removed once the
    pointer has moved.
    """

    def __init__(self, run_dir: str | os.PathLike) -> None:
        self.root = Path(run_dir) / "checkpoints"

    def latest(self) -> Path | None:
        pointer = self.root / "latest"
        if not pointer.exists():
            return None
        return self.root / pointer.read_text().strip()

    def save(self, state: dict, replay_buffer: TensorDictReplayBuffer) -> Path:
        name = f"{state['counters']['frames']:012d}"
        path = self.root / name
        if path.exists():  # a stale, incomplete write from a killed run
            shutil.rmtree(path)
        path.mkdir(parents=True)
        torch.save(state, path / "state.pt")
        replay_buffer.dumps(path / "replay_buffer")
        tmp = self.root / "latest.tmp"
        tmp.write_text(name)
        os.replace(tmp, self.root / "latest")
        for old in self.root.iterdir():
            if old.is_dir() and old.name != name:
                shutil.rmtree(old)
        return path

    def load(self, replay_buffer: TensorDictReplayBuffer) -> dict:
        path = self.latest()
        if path is None:
            raise FileNotFoundError(f"no checkpoint under {self.root} (resume needs one)")
        replay_buffer.loads(path / "replay_buffer")
        return torch.load(path / "state.pt", weights_only=False)


def saved_config(run_dir: str) -> DictConfig:
    """The config stored in a run's latest checkpoint."""
    path = Checkpointer(run_dir).latest()
    if path is None:
        raise FileNotFoundError(
            f"resume={run_dir!r}: no checkpoint found under {run_dir}/checkpoints"
        )
    saved = OmegaConf.create(torch.load(path / "state.pt", weights_only=False)["config"])
    # keys added to config.yaml after the run started take their defaults
    base = OmegaConf.load(Path(__file__).with_name("config.yaml"))
    base.pop("defaults")
    return OmegaConf.merge(base, saved)


# Keys that shape the saved modules, buffers or algorithm: a resumed run cannot change them.
FIXED_ON_RESUME = [
    "algorithm",
    "env.name",
    "network",
    *WORLD_MODEL_SIZES,
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


def config_for_resume(run_dir: str, overrides: list[str]) -> DictConfig:
    """The config a run was saved with, with command-line ``overrides`` applied on top."""
    saved = saved_config(run_dir)
    keep = [o for o in overrides if o.split("=", 1)[0].lstrip("+~") not in ("resume", "preset")]
    cfg = OmegaConf.merge(saved, OmegaConf.from_dotlist(keep))
    cfg.resume = str(run_dir)
    return cfg
