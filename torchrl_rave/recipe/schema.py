"""The recipe's configuration schema: typed structured configs whose defaults are the CPU
preset, shipped with the package.

Every key of ``python recipes/rave_mujoco.py`` is a field here, with its type, default,
range rule (``metadata["rule"]``, a :class:`~torchrl_rave._checks.Rule`) and a line of
help (``metadata["help"]``). :func:`default_config` gives a ready config without the
repository, e.g. for :func:`~torchrl_rave.recipe.agent.make_agent`; importing this module
registers the schema's defaults (``rave_recipe``) and the presets (group ``preset``:
``cpu``, ``paper``) with hydra's ConfigStore, which ``recipes/config.yaml`` selects.

Examples:
    >>> cfg = default_config("collector.total_frames=2000", algorithm="steve")
    >>> cfg.algorithm, cfg.env.name, cfg.collector.total_frames, cfg.world_model.size
    ('steve', 'InvertedPendulum-v5', 2000, 'cpu')
    >>> default_config(preset="paper").replay_buffer.batch_size
    512
"""

from __future__ import annotations

from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from torchrl_rave._checks import (
    NON_NEGATIVE,
    NON_NEGATIVE_INT,
    POSITIVE,
    POSITIVE_INT,
    UNIT_INTERVAL,
    Rule,
    one_of,
    optional,
)
from torchrl_rave.modules.world_model import WORLD_MODEL_SIZES

__all__ = ["PRESETS", "RecipeConfig", "default_config", "schema_fields"]


def key(default, help: str, rule: Rule | None = None, **kw):
    """A config field: its default, a line of help, and the rule its value must meet."""
    if isinstance(default, (dict, list)):
        return field(default_factory=lambda: default, metadata={"help": help, "rule": rule}, **kw)
    return field(default=default, metadata={"help": help, "rule": rule}, **kw)


ALGORITHM_NAMES = ["ddpg", "mve", "steve", "rave", "rave_constant", "td3", "sac", "ppo"]
COLLECTOR_BACKENDS = ["direct", "process", "ray"]
LOGGER_BACKENDS = ["", "csv", "tensorboard", "wandb", "mlflow"]
COMPILE_MODES = [None, "default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs"]


@dataclass
class EnvConfig:
    name: str = key("InvertedPendulum-v5", "gymnasium id; `module:EnvId` imports `module` first")
    seed: int = key(0, "seed of torch, the training env and the evaluation env")
    reward_scale: float = key(1.0, "the learner's rewards are multiplied by this", POSITIVE)
    kwargs: dict[str, Any] | None = key(None, "keyword arguments of gymnasium.make")
    action_noise: float = key(
        0.0, "actuator noise std in half action ranges (envs.ActuatorNoise; 0: none)", NON_NEGATIVE
    )


@dataclass
class CollectorConfig:
    total_frames: int = key(15_000, "environment frames in the run", POSITIVE_INT)
    frames_per_batch: int = key(250, "frames per collector batch", POSITIVE_INT)
    init_random_frames: int = key(1_000, "uniform random actions first", NON_NEGATIVE_INT)
    device: str | None = key(None, "the learner's device (null: CUDA when present, else CPU)")
    backend: str = key("direct", "direct | process | ray", one_of(COLLECTOR_BACKENDS))
    num_workers: int = key(1, "collector workers (process, ray)", POSITIVE_INT)
    weight_sync_every: int = key(1, "push the policy once this many updates are new", POSITIVE_INT)
    timeout_s: float | None = key(
        300.0, "a batch this late means a hung worker (null: wait)", optional(POSITIVE)
    )


@dataclass
class RayConfig:
    address: str | None = key(None, "null: a local Ray instance | auto | a cluster address")
    num_cpus: int | None = key(None, "CPUs of the local instance", optional(POSITIVE_INT))
    worker_cpus: float = key(1.0, "Ray CPUs reserved per collector worker", POSITIVE)
    worker_memory: int | None = key(None, "bytes reserved per worker", optional(POSITIVE_INT))
    worker_resources: dict[str, float] | None = key(
        None,
        "custom Ray resources per worker",
        Rule(lambda v: v is None or all(POSITIVE.test(x) for x in v.values()),
             "null or a mapping of resource name to an amount > 0"),
    )  # fmt: skip


@dataclass
class ReplayBufferConfig:
    size: int | None = key(None, "null: min(1e6, total_frames)", optional(POSITIVE_INT))
    batch_size: int = key(128, "batch of every agent and world-model update", POSITIVE_INT)


@dataclass
class WorldModelConfig:
    num_models: int = key(4, "ensemble size N", POSITIVE_INT)
    size: str = key(
        "cpu",
        "named sizes of modules.world_model.WORLD_MODEL_SIZES",
        one_of(list(WORLD_MODEL_SIZES)),
    )
    transition_cells: int | None = key(None, "width; null: from size", optional(POSITIVE_INT))
    transition_layers: int | None = key(None, "FC layers; null: from size", optional(POSITIVE_INT))
    reward_cells: int | None = key(None, "width; null: from size", optional(POSITIVE_INT))
    reward_layers: int | None = key(None, "FC layers; null: from size", optional(POSITIVE_INT))
    termination_cells: int | None = key(None, "width; null: from size", optional(POSITIVE_INT))
    termination_layers: int | None = key(None, "FC layers; null: from size", optional(POSITIVE_INT))
    pretrain_frames: int = key(
        1_000, "F: agent updates start at this many frames", NON_NEGATIVE_INT
    )
    pretrain_updates: int = key(500, "world-model steps taken once, at F", NON_NEGATIVE_INT)
    train_every: int = key(1, "one world-model step per this many agent updates", POSITIVE_INT)
    lr: float = key(3.0e-4, "world-model learning rate", POSITIVE)


@dataclass
class NetworkConfig:
    actor_cells: int = key(64, "actor hidden width", POSITIVE_INT)
    critic_cells: int = key(64, "critic hidden width", POSITIVE_INT)
    num_layers: int = key(4, "FC layers, output layer included", POSITIVE_INT)
    num_critics: int | None = key(None, "K; null: the algorithm's", optional(POSITIVE_INT))


@dataclass
class EstimatorConfig:
    horizon: int = key(3, "H_max (the fixed H of mve)", NON_NEGATIVE_INT)
    alpha: float = key(1.5, "rave: the alpha of eq. 12; rave_constant: the constant", NON_NEGATIVE)
    alpha_error_scale: float = key(1.0, "Z of eq. 12", POSITIVE)


@dataclass
class OptimConfig:
    lr_actor: float = key(3.0e-4, "actor learning rate", POSITIVE)
    lr_critic: float = key(3.0e-4, "critic learning rate", POSITIVE)
    lr_alpha: float = key(3.0e-4, "SAC temperature learning rate", POSITIVE)
    gamma: float = key(0.99, "discount", UNIT_INTERVAL)
    tau: float = key(0.005, "soft target update rate", Rule(lambda v: 0 < v <= 1, "in (0, 1]"))
    utd_ratio: float = key(1.0, "agent updates per collected frame", POSITIVE)


@dataclass
class CompileConfig:
    enabled: bool = key(False, "torch.compile the world-model and agent loss forwards")
    mode: str | None = key(None, "torch.compile mode", one_of(COMPILE_MODES))


@dataclass
class TD3Config:
    policy_noise: float = key(0.2, "target policy smoothing noise", NON_NEGATIVE)
    noise_clip: float = key(0.5, "its clip", NON_NEGATIVE)
    policy_delay: int = key(2, "critic steps per actor step", POSITIVE_INT)


@dataclass
class PPOConfig:
    rollout_frames: int = key(2048, "frames per batch (one PPO iteration)", POSITIVE_INT)
    epochs: int = key(10, "passes over each batch", POSITIVE_INT)
    minibatch_size: int = key(64, "frames per gradient step", POSITIVE_INT)
    clip_epsilon: float = key(
        0.2, "clip range of the ratio", Rule(lambda v: 0 < v < 1, "in (0, 1)")
    )
    gae_lambda: float = key(0.95, "GAE lambda", UNIT_INTERVAL)
    entropy_coef: float = key(0.0, "entropy bonus weight", NON_NEGATIVE)
    critic_coef: float = key(0.5, "value loss weight", NON_NEGATIVE)
    lr: float = key(3.0e-4, "Adam learning rate (policy and value)", POSITIVE)
    lr_schedule: str = key("linear", "linear | constant", one_of(["linear", "constant"]))
    max_grad_norm: float | None = key(0.5, "gradient-norm clip; null: none", optional(POSITIVE))


@dataclass
class ExplorationConfig:
    sigma: float = key(0.1, "action noise std in half action ranges", NON_NEGATIVE)
    epsilon: float = key(1.0, "probability of noise per step (paper 0.05)", UNIT_INTERVAL)


@dataclass
class EvalConfig:
    interval: int = key(5_000, "frames between evaluations (one more at the end)", POSITIVE_INT)
    episodes: int = key(5, "episodes per evaluation", POSITIVE_INT)


@dataclass
class CheckpointConfig:
    interval: int = key(5_000, "frames between checkpoints (one more at the end)", POSITIVE_INT)


@dataclass
class LoggerConfig:
    backend: str = key("csv", "csv | tensorboard | wandb | mlflow | \"\" (none)",
                       one_of(LOGGER_BACKENDS))  # fmt: skip
    exp_name: str | None = key(None, "experiment name; null: the algorithm's")
    project: str = key("torchrl-rave", "wandb project")
    progress_bar: bool = key(True, "the tqdm bar")
    q_points: dict[str, Any] | None = key(None, "{name: [observation, action]}: log q/<name>")


@dataclass
class RecipeConfig:
    """Everything one recipe run reads; the defaults are the CPU preset."""

    algorithm: str = key("rave", " | ".join(ALGORITHM_NAMES), one_of(ALGORITHM_NAMES))
    resume: str | None = key(None, "a run directory: continue it from its last checkpoint")
    threads: int | None = key(None, "torch threads (null: torch's default)", optional(POSITIVE_INT))
    keep_freed_memory: bool = key(True, "glibc: reuse freed memory (same numbers)")
    env: EnvConfig = field(default_factory=EnvConfig)
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    ray: RayConfig = field(default_factory=RayConfig)
    replay_buffer: ReplayBufferConfig = field(default_factory=ReplayBufferConfig)
    world_model: WorldModelConfig = field(default_factory=WorldModelConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    compile: CompileConfig = field(default_factory=CompileConfig)
    td3: TD3Config = field(default_factory=TD3Config)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)


# The presets: what each changes from the schema's defaults (which are the CPU preset).
# paper: the paper's MuJoCo hyper-parameters (appendix table), sized for a GPU; the world
# model's widths are STEVE's released configuration (modules.world_model.WORLD_MODEL_SIZES).
PRESETS: dict[str, dict] = {
    "cpu": {},
    "paper": {
        "collector": {"total_frames": 1_000_000, "frames_per_batch": 1_000,
                      "init_random_frames": 10_000},
        "replay_buffer": {"size": 1_000_000, "batch_size": 512},
        "world_model": {"size": "paper", "pretrain_frames": 10_000, "pretrain_updates": 10_000},
        "network": {"actor_cells": 128, "critic_cells": 128},
        "exploration": {"sigma": 0.3, "epsilon": 0.05},
        "eval": {"interval": 10_000, "episodes": 10},
        "checkpoint": {"interval": 50_000},
    },
}  # fmt: skip


def schema_fields(cls=RecipeConfig, prefix: str = ""):
    """``(dotted key, dataclass field)`` of every leaf of the schema, in order."""
    for f in fields(cls):
        default = f.default_factory() if f.default is MISSING else f.default
        if is_dataclass(default):
            yield from schema_fields(type(default), f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f


def defaults() -> DictConfig:
    """The schema's defaults as a plain (untyped) config: what hydra composes from, so that
    bad values reach :func:`~torchrl_rave.recipe.config.check_config` all at once."""
    return OmegaConf.create(OmegaConf.to_container(OmegaConf.structured(RecipeConfig)))


def default_config(
    *overrides: str,
    algorithm: str | None = None,
    env_name: str | None = None,
    preset: str = "cpu",
) -> DictConfig:
    """A complete recipe config: the schema's defaults, then ``preset`` (``cpu`` or
    ``paper``), then ``algorithm``, ``env_name`` and the ``key=value`` ``overrides``
    (checked by :func:`~torchrl_rave.recipe.config.check_config`, not here)."""
    if preset not in PRESETS:
        raise ValueError(f"preset={preset!r}: expected one of {list(PRESETS)}")
    cfg = OmegaConf.merge(defaults(), PRESETS[preset])
    if algorithm is not None:
        cfg.algorithm = algorithm
    if env_name is not None:
        cfg.env.name = env_name
    cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(overrides)))
    OmegaConf.set_struct(cfg, True)
    return cfg


def register() -> None:
    """Stores the schema's defaults (``rave_recipe``) and the presets (group ``preset``)
    in hydra's ConfigStore, for ``recipes/config.yaml`` to select."""
    store = ConfigStore.instance()
    store.store(name="rave_recipe", node=OmegaConf.to_container(defaults()))
    for name, node in PRESETS.items():
        store.store(group="preset", name=name, node=node, package="_global_")


register()
