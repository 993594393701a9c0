"""The recipe's configuration schema: typed structured configs whose defaults are the CPU
preset, shipped with the package.

Every key of ``python recipes/rave_mujoco.py`` is a field here, with its type, default,
range rule (``metadata["rule"]``, a :class:`~torchrl_rave._checks.Rule`) and a line of
help (``metadata["help"]``). :func:`default_config` gives a ready config without the
repository, e.g. for :func:`~torchrl_rave.recipe.agent.make_agent`; importing this module
registers the schema's defaults (``rave_recipe``) and the presets (group ``preset``:
``cpu``, ``paper``, ``mujoco``) with hydra's ConfigStore, which ``recipes/config.yaml``
selects; a preset's values for one algorithm (:data:`PRESET_ALGORITHMS`) are applied once
the algorithm is known (:func:`with_algorithm_preset`).

Examples:
    >>> cfg = default_config("collector.total_frames=2000", algorithm="steve")
    >>> cfg.algorithm, cfg.env.name, cfg.collector.total_frames, cfg.world_model.size
    ('steve', 'InvertedPendulum-v5', 2000, 'cpu')
    >>> default_config(preset="paper").replay_buffer.batch_size
    512
    >>> [default_config(preset="mujoco", algorithm=a).optim.lr_critic for a in ("td3", "sac")]
    [0.0003, 0.001]
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from torchrl_rave._checks import (
    FINITE,
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

__all__ = [
    "PRESETS",
    "PRESET_ALGORITHMS",
    "RecipeConfig",
    "default_config",
    "help_text",
    "preset_values",
    "schema_fields",
    "with_algorithm_preset",
]


def key(default, help: str, rule: Rule | None = None, **kw):
    """A config field: its default, a line of help, and the rule its value must meet."""
    if isinstance(default, (dict, list)):
        return field(default_factory=lambda: default, metadata={"help": help, "rule": rule}, **kw)
    return field(default=default, metadata={"help": help, "rule": rule}, **kw)


ALGORITHM_NAMES = ["ddpg", "mve", "steve", "rave", "rave_constant", "td3", "sac", "steve_sac",
                   "rave_sac", "ppo"]  # fmt: skip
COLLECTOR_BACKENDS = ["direct", "process", "ray"]
LOGGER_BACKENDS = ["", "csv", "tensorboard", "wandb", "mlflow"]
COMPILE_MODES = [None, "default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs"]


@dataclass
class EnvConfig:
    """The ``env.*`` keys (each with its default, rule and help on the recipe page)."""

    name: str = key(
        "InvertedPendulum-v5",
        (
            "gymnasium id, checked against the registry first; `module:EnvId` imports "
            "`module` first (which registers a custom env in every worker process too)"
        ),
    )
    seed: int = key(
        0,
        "seed of torch, the training env and the evaluation env (gymnasium takes seeds >= 0)",
        NON_NEGATIVE_INT,
    )
    reward_scale: float = key(
        1.0,
        (
            "the learner sees rewards times this (TorchRL `RewardScaling`); logged returns "
            "stay in env units, critic values are in scaled units"
        ),
        POSITIVE,
    )
    kwargs: dict[str, Any] | None = key(
        None, ("keyword arguments of `gymnasium.make` (e.g. `env.kwargs={k:1.0}` for `RAVEToy-v0`)")
    )
    action_noise: float = key(
        0.0,
        (
            "actuator noise that makes the task stochastic "
            "(`torchrl_rave.envs.ActuatorNoise`): the simulator applies `clip(a + sigma * "
            "eps * half_range)`, `eps ~ N(0, I)` seeded with the env, while the agent and "
            "its replay buffer see the commanded `a`; 0 builds the env exactly as without "
            "the key; fixed on resume"
        ),
        NON_NEGATIVE,
    )


@dataclass
class CollectorConfig:
    """The ``collector.*`` keys (each with its default, rule and help on the recipe page)."""

    total_frames: int = key(
        15_000,
        "environment frames in the run, rounded up to whole `collector.frames_per_batch` batches",
        POSITIVE_INT,
    )
    frames_per_batch: int = key(
        250, "frames per collector batch (the unit of logging and checkpoints)", POSITIVE_INT
    )
    init_random_frames: int = key(
        1_000, "frames collected with uniform random actions first", NON_NEGATIVE_INT
    )
    device: str | None = key(None, "the learner's device (null: CUDA when present, else CPU)")
    backend: str = key(
        "direct",
        (
            "`direct`: the learner process steps one env; `process`: TorchRL's "
            "`MultiSyncCollector` with `num_workers` env processes; `ray`: TorchRL's "
            "`RayCollector` with `num_workers` Ray actors, on this machine or a cluster. "
            "Workers run the exploration policy on the CPU and collect in lockstep, each an"
            " equal share of every batch"
        ),
        one_of(COLLECTOR_BACKENDS),
    )
    num_workers: int = key(
        1,
        ("workers of the `process` or `ray` backend; `frames_per_batch` must be a multiple"),
        POSITIVE_INT,
    )
    weight_sync_every: int = key(
        1,
        (
            "push the learner's policy weights to the workers at the end of a batch once "
            "this many updates are new since the last push"
        ),
        POSITIVE_INT,
    )
    timeout_s: float | None = key(
        300.0,
        (
            "a batch that takes longer than this many seconds means a hung worker or env: "
            "the run is checkpointed and stops with `CollectorTimeout`; null waits forever"
        ),
        optional(POSITIVE),
    )


@dataclass
class RayConfig:
    """The ``ray.*`` keys (each with its default, rule and help on the recipe page)."""

    address: str | None = key(
        None,
        (
            "null: start a local Ray instance (stopped at the end); `auto`: join the "
            "cluster this machine belongs to, or the head's `host:port`. A Ray already "
            "started in the process is used as it is"
        ),
    )
    num_cpus: int | None = key(
        None,
        (
            "CPUs of the local instance (null: all); `num_workers x worker_cpus` must fit, "
            "or the run is refused before it starts"
        ),
        optional(POSITIVE_INT),
    )
    worker_cpus: float = key(
        1.0,
        ("Ray CPUs each collector actor reserves (fractions allowed); also its torch threads"),
        POSITIVE,
    )
    worker_memory: int | None = key(
        None, "bytes of memory each actor reserves (null: none)", optional(POSITIVE_INT)
    )
    worker_resources: dict[str, float] | None = key(
        None,
        ("custom Ray resources each actor needs, e.g. `ray.worker_resources={actors:1}` "
'to keep actors on nodes started with `--resources=\'{"actors": N}\'`'),
        Rule(lambda v: v is None or all(POSITIVE.test(x) for x in v.values()),
             "null or a mapping of resource name to an amount > 0"),
    )  # fmt: skip


@dataclass
class ReplayBufferConfig:
    """The ``replay_buffer.*`` keys (each with its default, rule and help on the recipe page)."""

    size: int | None = key(
        None,
        "capacity; null: min(1e6, `collector.total_frames`), fixed when the run starts",
        optional(POSITIVE_INT),
    )
    batch_size: int = key(128, "batch of every agent and world-model update", POSITIVE_INT)


@dataclass
class WorldModelConfig:
    """The ``world_model.*`` keys (each with its default, rule and help on the recipe page)."""

    num_models: int = key(4, "ensemble size N", POSITIVE_INT)
    size: str = key(
        "cpu",
        (
            "a named size of `torchrl_rave.modules.world_model.WORLD_MODEL_SIZES` (FC "
            "layers x width, output layer included): `cpu` (4 x 64 transition, 3 x 64 reward"
            " and termination), `paper` (8 x 512 and 4 x 128, STEVE's released widths) or "
            "`mujoco` (5 x 200, an MBPO member's transition network, and 4 x 128)"
        ),
        one_of(list(WORLD_MODEL_SIZES)),
    )
    transition_cells: int | None = key(
        None,
        "width of the transition members; null: from `world_model.size`",
        optional(POSITIVE_INT),
    )
    transition_layers: int | None = key(
        None,
        (
            "FC layers of the transition members, output layer included; null: from "
            "`world_model.size`"
        ),
        optional(POSITIVE_INT),
    )
    reward_cells: int | None = key(
        None, "width of the reward members; null: from `world_model.size`", optional(POSITIVE_INT)
    )
    reward_layers: int | None = key(
        None,
        "FC layers of the reward members; null: from `world_model.size`",
        optional(POSITIVE_INT),
    )
    termination_cells: int | None = key(
        None,
        "width of the termination members; null: from `world_model.size`",
        optional(POSITIVE_INT),
    )
    termination_layers: int | None = key(
        None,
        "FC layers of the termination members; null: from `world_model.size`",
        optional(POSITIVE_INT),
    )
    pretrain_frames: int = key(
        1_000, "F: model-based updates start once this many frames are stored", NON_NEGATIVE_INT
    )
    pretrain_updates: int = key(500, "world-model steps taken once, at F", NON_NEGATIVE_INT)
    train_every: int = key(1, "one world-model step per this many agent updates", POSITIVE_INT)
    lr: float = key(3.0e-4, "world-model learning rate", POSITIVE)


@dataclass
class NetworkConfig:
    """The ``network.*`` keys (each with its default, rule and help on the recipe page)."""

    actor_cells: int = key(64, "actor hidden width", POSITIVE_INT)
    critic_cells: int = key(64, "critic hidden width", POSITIVE_INT)
    num_layers: int = key(4, "FC layers of actor and critic, output layer included", POSITIVE_INT)
    num_critics: int | None = key(
        None,
        "K; null: the algorithm's own (ddpg 1; mve, steve, rave 4; td3, sac, steve_sac, rave_sac 2)",
        optional(POSITIVE_INT),
    )
    default_policy_scale: float = key(
        1.0,
        (
            "`sac`, `steve_sac`, `rave_sac`: the policy's pre-tanh scale where its network "
            "outputs 0 (tensordict's `biased_softplus` scale mapping, as TorchRL's sota SAC "
            "script names it)"
        ),
        Rule(lambda v: v > 0.01, "> 0.01 (the mapping's floor)"),
    )
    scale_lb: float = key(
        1e-4,
        (
            "`sac`, `steve_sac`, `rave_sac`: the policy's least pre-tanh scale (the "
            "mapping's own floor, 0.01, holds below it)"
        ),
        POSITIVE,
    )


@dataclass
class EstimatorConfig:
    """The ``estimator.*`` keys (each with its default, rule and help on the recipe page)."""

    horizon: int = key(3, "H_max, the longest rollout (the fixed H of `mve`)", NON_NEGATIVE_INT)
    alpha: float = key(
        1.5, "`rave`, `rave_sac`: the alpha of eq. 12; `rave_constant`: the constant", NON_NEGATIVE
    )
    alpha_error_scale: float = key(1.0, "Z of eq. 12", POSITIVE)


@dataclass
class OptimConfig:
    """The ``optim.*`` keys (each with its default, rule and help on the recipe page)."""

    lr_actor: float = key(3.0e-4, "actor learning rate", POSITIVE)
    lr_critic: float = key(3.0e-4, "critic learning rate", POSITIVE)
    lr_alpha: float = key(3.0e-4, "`sac`: temperature learning rate", POSITIVE)
    gamma: float = key(0.99, "discount", UNIT_INTERVAL)
    tau: float = key(0.005, "soft target update rate", Rule(lambda v: 0 < v <= 1, "in (0, 1]"))
    utd_ratio: float = key(1.0, "agent updates per collected frame", POSITIVE)
    critic_first: bool = key(
        False,
        (
            "step the critics before the actor's (and `sac`'s temperature's) loss is "
            "computed, so the actor learns through the updated critics, as CleanRL's "
            "scripts and TorchRL's sota DDPG and TD3 scripts do; false: one backward pass "
            "over the summed losses from one forward pass, as TorchRL's sota SAC script "
            "does. Not for `ppo`"
        ),
    )


@dataclass
class CompileConfig:
    """The ``compile.*`` keys (each with its default, rule and help on the recipe page)."""

    enabled: bool = key(
        False,
        (
            "`torch.compile` the world-model and agent loss forwards, and with them their "
            "backward (backward calls, fused Adam and the target update stay eager); the "
            "first updates pay the compile. Not for `ppo`"
        ),
    )
    mode: str | None = key(
        None,
        (
            "`torch.compile` mode: null (its default), `reduce-overhead` (CUDA graphs on a "
            "GPU), `max-autotune`, `max-autotune-no-cudagraphs`"
        ),
        one_of(COMPILE_MODES),
    )


@dataclass
class TD3Config:
    """The ``td3.*`` keys (each with its default, rule and help on the recipe page)."""

    policy_noise: float = key(0.2, "`td3`: target policy smoothing noise", NON_NEGATIVE)
    noise_clip: float = key(0.5, "`td3`: its clip", NON_NEGATIVE)
    policy_delay: int = key(2, "`td3`: critic steps per actor step", POSITIVE_INT)


@dataclass
class PPOConfig:
    """The ``ppo.*`` keys (each with its default, rule and help on the recipe page)."""

    rollout_frames: int = key(
        2048, "`ppo`: frames collected per batch (one PPO iteration)", POSITIVE_INT
    )
    epochs: int = key(10, "`ppo`: passes over each batch", POSITIVE_INT)
    minibatch_size: int = key(
        64, "`ppo`: frames per gradient step (at most `rollout_frames`)", POSITIVE_INT
    )
    clip_epsilon: float = key(
        0.2, "`ppo`: clip range of the probability ratio", Rule(lambda v: 0 < v < 1, "in (0, 1)")
    )
    gae_lambda: float = key(0.95, "`ppo`: GAE lambda (gamma is `optim.gamma`)", UNIT_INTERVAL)
    entropy_coef: float = key(
        0.0, "`ppo`: weight of the entropy bonus (0: none, the usual MuJoCo setting)", NON_NEGATIVE
    )
    critic_coef: float = key(0.5, "`ppo`: weight of the value loss", NON_NEGATIVE)
    lr: float = key(
        3.0e-4, "`ppo`: Adam learning rate of the policy and the value network", POSITIVE
    )
    lr_schedule: str = key(
        "linear",
        "`ppo`: `linear` (annealed to 0 over `collector.total_frames`) or `constant`",
        one_of(["linear", "constant"]),
    )
    max_grad_norm: float | None = key(
        0.5, "`ppo`: global gradient-norm clip; null: none", optional(POSITIVE)
    )


@dataclass
class ExplorationConfig:
    """The ``exploration.*`` keys (each with its default, rule and help on the recipe page)."""

    sigma: float = key(
        0.1,
        ("Gaussian action noise std, in units of half the action range (all but `sac` and `ppo`)"),
        NON_NEGATIVE,
    )
    epsilon: float = key(
        1.0,
        "probability of adding the noise at a step (the paper's 0.05; 1 = always on)",
        UNIT_INTERVAL,
    )


@dataclass
class EvalConfig:
    """The ``eval.*`` keys (each with its default, rule and help on the recipe page)."""

    interval: int = key(
        5_000, "frames between deterministic evaluations (one more at the end)", POSITIVE_INT
    )
    episodes: int = key(5, "episodes per evaluation", POSITIVE_INT)


@dataclass
class RewardConfig:
    """The ``reward.*`` keys (each with its default, rule and help on the recipe page)."""

    weights: dict[str, float] | None = key(
        None,
        (
            "weights of the env's reward terms by name, for an env that reports them "
            "(`LearnToMove-v0`: alive, footstep, velocity, effort, success, target); the "
            "learner trains on the reweighted sum, relabelled at every replay-buffer sample "
            "(`torchrl_rave.transforms.ReweightRewardTerms`), while evaluation reports the "
            "env's own reward. A term not named keeps weight 1 (e.g. `reward.weights={effort:2.0}`). "
            "Off-policy algorithms"
        ),
    )
    delayed: str | None = key(
        None,
        (
            "a reward term whose weight is 0 until `reward.delay_frames` frames, or until "
            "`reward.delay_metric` reaches `reward.delay_threshold`, whichever comes first, "
            "and then ramps linearly to its weight over `reward.ramp_frames` frames "
            "(`torchrl_rave.transforms.DelayedWeight`; the paper's low-energy stage is "
            "`reward.delayed=effort`)"
        ),
    )
    delay_frames: int | None = key(
        None, "frames at which the delayed term starts", optional(NON_NEGATIVE_INT)
    )
    delay_metric: str | None = key(
        None, "an evaluation metric (e.g. `eval/return`) that starts the delayed term"
    )
    delay_threshold: float | None = key(
        None, "the value of `reward.delay_metric` that starts the delayed term", optional(FINITE)
    )
    ramp_frames: int = key(
        0, "frames over which the delayed term ramps from 0 to its weight", NON_NEGATIVE_INT
    )


@dataclass
class CurriculumConfig:
    """The ``curriculum.*`` keys (each with its default, rule and help on the recipe page)."""

    kwarg: str | None = key(
        None,
        (
            "an env keyword (of `env.kwargs`) that steps through `curriculum.stages`: the "
            "target-speed curriculum is `curriculum.kwarg=constant_speed` (or `speed_range`) "
            "on `LearnToMove-v0`. When `curriculum.metric` reaches the stage's threshold at "
            "an evaluation, the training and evaluation envs (and collector workers) are "
            "rebuilt with the next value; checkpoints keep the stage. Any algorithm"
        ),
    )
    stages: list[Any] | None = key(
        None, "the keyword's value at each stage, first to last (e.g. `[3.0,2.0,1.4]`)"
    )
    thresholds: list[float] | None = key(
        None, "the metric value that ends each stage but the last (one per stage but the last)"
    )
    metric: str = key("eval/return", "the evaluation metric the thresholds apply to")


@dataclass
class CheckpointConfig:
    """The ``checkpoint.*`` keys (each with its default, rule and help on the recipe page)."""

    interval: int = key(5_000, "frames between checkpoints (one more at the end)", POSITIVE_INT)


@dataclass
class LoggerConfig:
    """The ``logger.*`` keys (each with its default, rule and help on the recipe page)."""

    backend: str = key(
        "csv",
        (
            "`csv`, `tensorboard`, `wandb`, `mlflow` (the last three through TorchRL's "
            'loggers and the `logging` extra) or `""` (none). `mlflow` writes an SQLite '
            "store, `mlflow.db`, into the run directory. The analyses read `csv`, "
            "`tensorboard` and `mlflow` runs"
        ),
        one_of(LOGGER_BACKENDS),
    )
    exp_name: str | None = key(None, "experiment name; null: the algorithm")
    project: str = key("torchrl-rave", "W&B project")
    progress_bar: bool = key(True, "the tqdm bar")
    q_points: dict[str, Any] | None = key(
        None,
        (
            "`{name: [observation, action]}`: after every batch, log `q/<name>`, the "
            "critics' mean Q at that point in reward units"
        ),
    )


@dataclass
class RecipeConfig:
    """Everything one recipe run reads; the defaults are the CPU preset."""

    algorithm: str = key(
        "rave",
        "the learner: one of the algorithms listed under Algorithms",
        one_of(ALGORITHM_NAMES),
    )
    resume: str | None = key(
        None,
        (
            "a run directory: continue that run from its last checkpoint with its saved "
            "config; other command-line keys apply on top (e.g. a larger "
            "`collector.total_frames`)"
        ),
    )
    seeds: list[int] | None = key(
        None,
        (
            "train these seeds as one group in one process (every algorithm but `ppo`): "
            "each seed an ordinary run under "
            "`<run dir>/seed<s>/` "
            "with `env.seed` set to it, every update batched across the seeds "
            "(`torchrl_rave.trainers.SeedGroup`); null: one run of `env.seed`"
        ),
        Rule(
            lambda v: v is None or all(NON_NEGATIVE_INT.test(x) for x in v),
            "null or a list of integers >= 0",
        ),
    )
    threads: int | None = key(
        None,
        (
            "torch threads of the learner process (null: torch's default, every core). Set "
            "it when other processes share the cores (two runs side by side, collector "
            "workers) or a container limits its CPU time (--cpus): more threads than free "
            "cores make a run several times slower, and a run warns when it starts so "
            "(BusyCoresWarning)"
        ),
        optional(POSITIVE_INT),
    )
    keep_freed_memory: bool = key(
        True,
        (
            "glibc's malloc keeps freed blocks of up to 32 MiB for reuse instead of "
            "returning them to the kernel (`torchrl_rave.recipe.keep_freed_memory`), so an "
            "update does not fault its temporaries in again; the numbers are bit-for-bit "
            "the same and the process keeps its peak heap. No effect off glibc"
        ),
    )
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
    reward: RewardConfig = field(default_factory=RewardConfig)
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)


#: The presets, with what each changes from the schema's defaults (which are the CPU preset).
#: ``paper``: the paper's MuJoCo hyper-parameters (appendix table), sized for a GPU; the
#: world model's widths are STEVE's released ones (``modules.world_model.WORLD_MODEL_SIZES``).
#: ``mujoco``: the field's sizes and settings for MuJoCo tasks (2 x 256 networks, batch 256,
#: CleanRL's single-file DDPG and TD3 settings, an MBPO-sized world model); where a learner's
#: published settings differ from these, :data:`PRESET_ALGORITHMS` holds its own. The
#: recipe page's preset table cites the source of every value.
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
    "mujoco": {
        "collector": {"total_frames": 1_000_000, "init_random_frames": 25_000},
        "replay_buffer": {"batch_size": 256},
        "world_model": {"size": "mujoco", "pretrain_frames": 25_000,
                        "pretrain_updates": 10_000},
        "network": {"actor_cells": 256, "critic_cells": 256, "num_layers": 3},
        "eval": {"interval": 5_000, "episodes": 10},
        "checkpoint": {"interval": 10_000},
    },
}  # fmt: skip

_SAC_MUJOCO = {
    "collector": {"init_random_frames": 5_000},
    "optim": {"lr_critic": 1.0e-3, "lr_alpha": 1.0e-3},
}
#: A preset's values for one algorithm, over the preset's own and under the command line:
#: where the field publishes other settings for that learner (SAC's learning rates and
#: random start, PPO's network width), or where a study here chose one (TD3 steps its
#: critics first: ``docs/results/critic_first100k.md``). SAC with value expansion keeps
#: SAC's values and pretrains its world model on SAC's random start, so that it learns from
#: the same frame.
PRESET_ALGORITHMS: dict[str, dict[str, dict]] = {
    "mujoco": {
        "td3": {"optim": {"critic_first": True}},
        "sac": _SAC_MUJOCO,
        **{name: {**_SAC_MUJOCO, "world_model": {"pretrain_frames": 5_000}}
           for name in ("steve_sac", "rave_sac")},
        "ppo": {"network": {"actor_cells": 64, "critic_cells": 64}},
    },
}  # fmt: skip


def preset_values(preset: str, algorithm: str) -> DictConfig:
    """What ``preset`` changes from the schema's defaults for ``algorithm``: its values,
    then its values for that algorithm (:data:`PRESET_ALGORITHMS`)."""
    if preset not in PRESETS:
        raise ValueError(f"preset={preset!r}: expected one of {list(PRESETS)}")
    own = PRESET_ALGORITHMS.get(preset, {}).get(algorithm, {})
    return OmegaConf.merge(PRESETS[preset], own)


def with_algorithm_preset(cfg: DictConfig, preset: str, given: Iterable[str]) -> DictConfig:
    """``cfg`` (composed from the schema, ``preset`` and a command line) with the preset's
    values for ``cfg.algorithm`` (:data:`PRESET_ALGORITHMS`), except for the dotted keys
    ``given`` on the command line, which keep their values. Returns ``cfg`` itself when
    the preset has no values of its own for the algorithm."""
    own = PRESET_ALGORITHMS.get(preset, {}).get(cfg.algorithm)
    if not own:
        return cfg
    given = set(given)
    cfg = cfg.copy()
    for key, value in _leaves(own):
        if key not in given:
            OmegaConf.update(cfg, key, value, merge=False)
    return cfg


def _leaves(node: dict, prefix: str = ""):
    for k, v in node.items():
        if isinstance(v, dict):
            yield from _leaves(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


def schema_fields(cls=RecipeConfig, prefix: str = ""):
    """``(dotted key, dataclass field)`` of every leaf of the schema, in order."""
    for f in fields(cls):
        default = f.default_factory() if f.default is MISSING else f.default
        if is_dataclass(default):
            yield from schema_fields(type(default), f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f


def help_text(command: str) -> str:
    """``--help`` of the recipe's commands: every key with its default (the ``cpu``
    preset) and its help line, grouped as the schema is."""
    lines = [
        f"usage: {command} [KEY=VALUE ...]   (hydra's own flags: --hydra-help)",
        "",
        "Trains one run into outputs/<date>/<time>/ (resume=<run dir> continues one).",
        f"preset=: one of {list(PRESETS)} (default cpu), applied under the command line.",
    ]
    group = None
    for name, f in schema_fields():
        head = name.split(".")[0] if "." in name else ""
        if head != group:
            group = head
            lines += ["", f"{group}:" if group else "top level:"]
        default = f.default_factory() if f.default is MISSING else f.default
        shown = "null" if default is None else repr(default) if default == "" else default
        rule = f.metadata.get("rule")
        lines.append(f"  {name}={shown}" + (f"   ({rule.expected})" if rule else ""))
        lines.append(f"      {' '.join(f.metadata['help'].replace('`', '').split())}")
    return "\n".join(lines) + "\n"


def defaults() -> DictConfig:
    """The schema's defaults as a plain (untyped) config: what hydra composes from, so that
    bad values reach :func:`~torchrl_rave.recipe.check_config` all at once."""
    return OmegaConf.create(OmegaConf.to_container(OmegaConf.structured(RecipeConfig)))


def default_config(
    *overrides: str,
    algorithm: str | None = None,
    env_name: str | None = None,
    preset: str = "cpu",
) -> DictConfig:
    """A complete recipe config: the schema's defaults, then ``preset`` (``cpu``,
    ``paper`` or ``mujoco``) with its values for the algorithm, then ``algorithm``,
    ``env_name`` and the ``key=value`` ``overrides`` (checked by
    :func:`~torchrl_rave.recipe.check_config`, not here). The algorithm is
    ``algorithm``, else an ``algorithm=`` of ``overrides``, else the default."""
    given = OmegaConf.from_dotlist(list(overrides))
    if algorithm is None:
        algorithm = given.get("algorithm", RecipeConfig.algorithm)
    cfg = OmegaConf.merge(defaults(), preset_values(preset, algorithm))
    cfg.algorithm = algorithm
    if env_name is not None:
        cfg.env.name = env_name
    cfg = OmegaConf.merge(cfg, given)
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
