"""The recipe's configuration: the algorithm table, and every check made before work starts.

:func:`check_config` reads a config against the schema (:mod:`~torchrl_rave.recipe.schema`:
each key's type and range rule) and the cross-key rules below, and reports every problem
at once in one :class:`ConfigError`, before any env is built.
"""

from __future__ import annotations

import difflib
import importlib
import importlib.util
import math
import os
import re
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from torchrl_rave.envs.families import BULLET_IDS, OSIM_IDS, import_env_family
from torchrl_rave.modules.world_model import WORLD_MODEL_SIZES
from torchrl_rave.recipe import memory
from torchrl_rave.recipe.metrics import METRICS
from torchrl_rave.recipe.schema import PRESETS, RecipeConfig, default_config, schema_fields

__all__ = [
    "ALGORITHMS",
    "FIXED_ON_RESUME",
    "Algorithm",
    "ConfigError",
    "GROUP_ALGORITHMS",
    "NoUpdatesWarning",
    "check_command_line",
    "check_config",
    "check_group",
    "check_resumable",
    "num_critics",
    "replay_buffer_size",
    "learning_start",
    "resolve_config",
    "warn_if_no_updates",
    "world_model_sizes",
]


@dataclass(frozen=True)
class Algorithm:
    """What ``algorithm=<name>`` selects: the TorchRL loss, the target estimator, K."""

    loss: str  # "ensemble_ddpg" | "td3" | "sac" | "ppo"
    estimator: str | None  # value-expansion estimator name; None: TD(0) (GAE for ppo)
    num_critics: int
    alpha_mode: str | None = None  # rave: RAVEValueEstimator's alpha_mode

    @property
    def model_based(self) -> bool:
        return self.estimator is not None

    @property
    def on_policy(self) -> bool:
        """Learns from each batch it collects, then drops it (PPO); the others replay."""
        return self.loss == "ppo"


#: ``algorithm=`` name -> its ``Algorithm`` (loss, value estimator, critics K)
ALGORITHMS = {
    "ddpg": Algorithm("ensemble_ddpg", None, 1),
    "mve": Algorithm("ensemble_ddpg", "mve", 4),
    "steve": Algorithm("ensemble_ddpg", "steve", 4),
    "rave": Algorithm("ensemble_ddpg", "rave", 4, alpha_mode="adaptive"),
    "rave_constant": Algorithm("ensemble_ddpg", "rave", 4, alpha_mode="constant"),
    "td3": Algorithm("td3", None, 2),
    "sac": Algorithm("sac", None, 2),
    "steve_sac": Algorithm("sac", "steve", 2),
    "rave_sac": Algorithm("sac", "rave", 2, alpha_mode="adaptive"),
    "ppo": Algorithm("ppo", None, 1),
}
# the package a logger backend needs
LOGGER_PACKAGES = {"tensorboard": ["tensorboard"], "wandb": ["wandb"],
                   "mlflow": ["mlflow", "sqlalchemy", "alembic"]}  # fmt: skip
_SCHEMA = dict(schema_fields())


class ConfigError(ValueError):
    """Every problem found in a config, one per line of its message."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        n = len(self.problems)
        super().__init__(
            f"{n} problem{'s' if n > 1 else ''} in the config:\n  " + "\n  ".join(self.problems)
        )


def _invalid(key: str, value, expected: str) -> str:
    return f"config key {key}={value!r} is invalid: expected {expected}"


def _check_keys(cfg: DictConfig, problems: list[str]) -> set[str]:
    """Types (the schema's) and ranges (each key's rule) of every key, and unknown keys;
    a value of another type that converts (``"100"`` for an integer) is converted in
    ``cfg``. Returns the keys that failed."""
    typed = OmegaConf.structured(RecipeConfig)
    bad = set()
    for key, f in _SCHEMA.items():
        value = OmegaConf.select(cfg, key, default=KeyError)
        if value is KeyError:
            problems.append(f"config key {key} is missing")
            bad.add(key)
            continue
        if isinstance(value, DictConfig):
            value = OmegaConf.to_container(value)
        if f.type == "bool" and not isinstance(value, bool):  # not OmegaConf's "yes", "on", 1
            problems.append(_invalid(key, value, "true or false"))
            bad.add(key)
            continue
        try:
            OmegaConf.update(typed, key, value, merge=False)
        except OmegaConfBaseException:
            kind = getattr(f.type, "__name__", str(f.type))
            problems.append(_invalid(key, value, f"a value of type {kind}"))
            bad.add(key)
            continue
        coerced = OmegaConf.select(typed, key)
        if isinstance(coerced, DictConfig):
            coerced = OmegaConf.to_container(coerced)
        rule = f.metadata.get("rule")
        if rule is not None and not rule.holds(coerced):
            problems.append(_invalid(key, value, rule.expected))
            bad.add(key)
        elif coerced != value or type(coerced) is not type(value):
            OmegaConf.update(cfg, key, coerced, merge=False)
    groups = {k.rsplit(".", 1)[0] for k in _SCHEMA if "." in k}

    def unknown(node: DictConfig, prefix: str) -> None:
        for name in node:
            full = f"{prefix}{name}"
            if full in _SCHEMA:
                continue
            if full in groups and isinstance(node[name], DictConfig):
                unknown(node[name], f"{full}.")
            else:
                problems.append(_unknown_key(full))

    unknown(cfg, "")
    return bad


def _unknown_key(key: str) -> str:
    """The problem of a key the schema does not have, with the nearest known keys: those
    of the same last name first (``optim.batch_size`` -> ``replay_buffer.batch_size``),
    then the closest spellings."""
    same_leaf = [k for k in _SCHEMA if k.rsplit(".", 1)[-1] == key.rsplit(".", 1)[-1]]
    close = same_leaf or difflib.get_close_matches(key, list(_SCHEMA), n=3, cutoff=0.8)
    hint = f"; did you mean {' or '.join(close)}?" if close else ""
    return f"config key {key} is not a key of the recipe{hint} (--help lists every key)"


#: the algorithms a seed group trains (ppo runs one seed per process)
GROUP_ALGORITHMS = tuple(name for name, algo in ALGORITHMS.items() if not algo.on_policy)


def check_group(cfg: DictConfig) -> list[str]:
    """The problems of ``seeds=`` with the rest of ``cfg`` (empty when it can run)."""
    seeds = list(cfg.seeds)
    problems = []
    if not seeds or len(set(seeds)) != len(seeds):
        problems.append(f"config key seeds={seeds}: expected a list of distinct seeds")
    if cfg.algorithm not in GROUP_ALGORITHMS:
        problems.append(
            f"config key seeds={seeds}: a seed group trains {', '.join(GROUP_ALGORITHMS)}; "
            f"algorithm={cfg.algorithm} runs one seed per process (leave seeds unset)"
        )
    if cfg.get("curriculum") is not None and cfg.curriculum.kwarg is not None:
        problems.append("config key seeds: a seed group does not run a curriculum")
    reward = cfg.get("reward")
    if reward is not None and (reward.weights is not None or reward.delayed is not None):
        problems.append("config key seeds: a seed group does not relabel reward terms")
    if cfg.compile.enabled:
        problems.append("config key seeds: a seed group's update is not compiled; set "
                        "compile.enabled=false")  # fmt: skip
    return problems


def check_config(cfg: DictConfig) -> Algorithm:
    """Rejects bad settings before anything is built; returns the selected algorithm.

    Every problem is collected, then all are raised together as a :class:`ConfigError`:
    each key's type and range (the schema), unknown keys, and the rules between keys.
    """
    problems: list[str] = []
    bad = _check_keys(cfg, problems)

    def rule(keys: tuple[str, ...], ok, key: str, expected: str) -> None:
        if not bad & set(keys) and not ok():
            problems.append(_invalid(key, OmegaConf.select(cfg, key), expected))

    if "algorithm" not in bad and cfg.algorithm == "ppo":
        _check_ppo(cfg, rule)
        cfg = resolve_config(cfg)  # the checks below see what runs
    if "env.name" not in bad:
        problem = _check_env_id(str(cfg.env.name))
        if problem:
            problems.append(problem)
    c = cfg.collector
    if c.backend == "direct":
        rule(("collector.num_workers",), lambda: c.num_workers == 1, "collector.num_workers",
             "1 with collector.backend=direct (use collector.backend=process or ray for more)")  # fmt: skip
    else:
        rule(
            ("collector.frames_per_batch", "collector.num_workers"),
            lambda: c.frames_per_batch % c.num_workers == 0,
            "collector.frames_per_batch",
            f"a multiple of collector.num_workers ({c.num_workers}): each worker collects "
            "an equal share",
        )
    rule(("collector.frames_per_batch", "collector.total_frames"),
         lambda: c.frames_per_batch <= c.total_frames, "collector.frames_per_batch",
         f"<= collector.total_frames ({c.total_frames})")  # fmt: skip
    keys = ("replay_buffer.size", "collector.total_frames", "replay_buffer.batch_size")
    if not bad & set(keys):
        size = replay_buffer_size(cfg)
        rule(keys, lambda: cfg.replay_buffer.batch_size <= size, "replay_buffer.batch_size",
             f"<= the replay buffer size ({size})")  # fmt: skip
    if "world_model.size" not in bad:
        for name, value in world_model_sizes(cfg).items():
            key = f"world_model.{name}"
            if key not in bad and name.endswith("_layers"):
                rule((key,), lambda v=value: v >= 2, key, "an integer >= 2 (hidden + output)")
    exp_name = cfg.logger.exp_name
    if exp_name is not None and not _plain_name(str(exp_name)):
        problems.append(
            _invalid("logger.exp_name", exp_name, "a plain directory name (letters, digits, "
                     "'_', '-', '+', '.'; not starting with '.'): the run's metrics go under it")
        )  # fmt: skip
    backend = cfg.logger.backend
    missing = [p for p in LOGGER_PACKAGES.get(backend, []) if importlib.util.find_spec(p) is None]
    if "logger.backend" not in bad and missing:
        problems.append(
            f"config key logger.backend={backend!r} needs the {', '.join(map(repr, missing))} "
            "package(s): pip install 'torchrl-rave[logging]'"
        )
    if "collector.device" not in bad and c.device is not None:
        problem = _check_device(str(c.device))
        if problem:
            problems.append(problem)
    if "collector.backend" not in bad and c.backend == "ray":
        _check_ray(cfg, problems)
    _check_reward(cfg, bad, problems)
    _check_curriculum(cfg, bad, problems)
    if "seeds" not in bad and cfg.get("seeds") is not None:
        problems += check_group(cfg)
    if problems:
        raise ConfigError(problems)
    return ALGORITHMS[cfg.algorithm]


def _check_reward(cfg: DictConfig, bad: set, problems: list[str]) -> None:
    """The ``reward`` keys: weights are numbers; the delayed term has a start condition
    (frames, or a metric with its threshold); only off-policy algorithms relabel."""
    r = cfg.get("reward")
    if r is None or bad & {k for k in _SCHEMA if k.startswith("reward.")}:
        return
    weights = dict(r.weights or {})
    for name, value in weights.items():
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float))
            or not math.isfinite(value)
        ):
            problems.append(_invalid(f"reward.weights.{name}", value, "a finite number"))
    if r.delayed is None:
        for k in ("delay_frames", "delay_metric", "delay_threshold"):
            if r[k] is not None:
                problems.append(
                    _invalid(f"reward.{k}", r[k], "null unless reward.delayed names a term")
                )
    else:
        if r.delay_frames is None and r.delay_metric is None:
            problems.append(_invalid("reward.delayed", r.delayed, "a term with reward.delay_frames, "
                                     "or reward.delay_metric and reward.delay_threshold, to start it"))  # fmt: skip
        if (r.delay_metric is None) != (r.delay_threshold is None):
            problems.append(_invalid("reward.delay_metric", r.delay_metric,
                                     "set together with reward.delay_threshold"))  # fmt: skip
        evals = sorted(k for k in METRICS if k.startswith("eval/"))
        if r.delay_metric is not None and r.delay_metric not in evals:
            problems.append(_invalid("reward.delay_metric", r.delay_metric, f"one of {evals}"))
    if (
        (weights or r.delayed is not None)
        and "algorithm" not in bad
        and ALGORITHMS[cfg.algorithm].on_policy
    ):
        problems.append(_invalid("algorithm", cfg.algorithm, "an off-policy algorithm with reward.weights "
                                 "or reward.delayed (the relabelling is a replay-buffer transform)"))  # fmt: skip


def _check_curriculum(cfg: DictConfig, bad: set, problems: list[str]) -> None:
    """The ``curriculum`` keys: stages with one threshold between each two, and an
    evaluation metric."""
    c = cfg.get("curriculum")
    if c is None or bad & {k for k in _SCHEMA if k.startswith("curriculum.")}:
        return
    if c.kwarg is None:
        for k in ("stages", "thresholds"):
            if c[k] is not None:
                problems.append(
                    _invalid(f"curriculum.{k}", c[k], "null unless curriculum.kwarg is set")
                )
        return
    values, thresholds = list(c.stages or []), list(c.thresholds or [])
    if not values:
        problems.append(_invalid("curriculum.stages", c.stages, "a list of the stages' values"))
    if len(thresholds) != max(0, len(values) - 1) or not all(
        isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t)
        for t in thresholds
    ):
        problems.append(_invalid("curriculum.thresholds", c.thresholds,
                                 f"{max(0, len(values) - 1)} finite numbers, one per stage but the last"))  # fmt: skip
    evals = sorted(k for k in METRICS if k.startswith("eval/"))
    if c.metric not in evals:
        problems.append(_invalid("curriculum.metric", c.metric, f"one of {evals}"))


def preset_of(overrides: list[str]) -> str:
    """The preset a command line's ``overrides`` choose (``cpu`` when none does)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(overrides)
    return next((o.value() for o in parsed if o.key_or_group == "preset"), "cpu")


def override_keys(overrides: list[str]) -> list[str]:
    """The dotted keys a hydra command line's ``overrides`` set (``a.b=1`` -> ``a.b``)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return [o.key_or_group for o in OverridesParser.create().parse_overrides(overrides)]


def check_command_line(overrides: list[str]) -> None:
    """The recipe's command-line overrides, checked before hydra composes them: unknown
    keys and every problem :func:`check_config` finds in the config they give, raised
    together as one :class:`ConfigError` (hydra itself would stop at the first unknown
    key). With ``resume=`` only the keys are checked here; the resumed config is checked
    in full once merged with the saved one."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except HydraException:
        return  # a syntax error: hydra's own message names it
    dict_keys = [k for k, f in _SCHEMA.items() if "dict" in str(f.type)]
    problems, values, preset, resume = [], {}, "cpu", False
    for o in parsed:
        key = o.key_or_group
        if key.split(".")[0] == "hydra" or o.is_delete():
            continue
        if key == "preset":
            preset = o.value()
            if preset not in PRESETS:
                problems.append(_invalid("preset", preset, f"one of {list(PRESETS)}"))
            continue
        if key not in _SCHEMA and not any(key.startswith(f"{d}.") for d in dict_keys):
            problems.append(_unknown_key(key))
        elif key in _SCHEMA and not o.is_sweep_override():  # a -m sweep's values: hydra's
            resume = resume or (key == "resume" and o.value() is not None)
            values[key] = o.value()
    if values.get("seeds") is not None and "env.seed" in values:
        # a group sets each run's env.seed from seeds: the given one would be ignored
        problems.append(
            f"config keys seeds={values['seeds']} and env.seed={values['env.seed']} are both "
            "given: each run of a seed group takes its env.seed from seeds; drop env.seed="
        )
    if not resume and preset in PRESETS:
        algorithm = values.get("algorithm")
        cfg = default_config(
            preset=preset, algorithm=algorithm if isinstance(algorithm, str) else None
        )
        OmegaConf.set_struct(cfg, False)
        for key, value in values.items():
            OmegaConf.update(cfg, key, value, merge=False)
        try:
            check_config(cfg)
        except ConfigError as err:
            problems += err.problems
    if problems:
        raise ConfigError(problems)


def _plain_name(name: str) -> bool:
    """A name that stays one directory level below where it is joined: no separators, no
    ``..``, nothing hidden."""
    return re.fullmatch(r"[A-Za-z0-9_+\-][A-Za-z0-9_.+\-]*", name) is not None


def _check_env_id(env_name: str) -> str | None:
    """Whether ``env.name`` names a gymnasium id, once its module or family is imported."""
    import gymnasium as gym

    env_id = env_name
    if ":" in env_id:  # gymnasium's "module:EnvId": importing the module registers the id
        module, env_id = env_id.split(":", 1)
        try:
            importlib.import_module(module)
        except ImportError as e:
            return f"config key env.name={env_name!r}: cannot import {module!r}: {e}"
    try:
        import_env_family(env_id)
    except ImportError as err:
        return f"config key env.name={env_name!r}: {err}"
    if env_id not in gym.registry:
        mujoco = sorted(k for k in gym.registry if k.endswith("-v5"))
        return (
            f"config key env.name={env_name!r} is not a registered gymnasium id; MuJoCo ids: "
            f"{mujoco}; PyBullet ids (the bullet extra): {list(BULLET_IDS)}; OpenSim ids "
            f"(the osim extra): {list(OSIM_IDS)}"
        )
    return None


def _check_device(device: str) -> str | None:
    try:
        parsed = torch.device(device)
    except RuntimeError as err:
        return f"config key collector.device={device!r}: {err}"
    if parsed.type == "cuda" and not torch.cuda.is_available():
        return (
            f"config key collector.device={device!r}: this torch has no usable CUDA device "
            f"(torch {torch.__version__}, compiled with CUDA: {torch.backends.cuda.is_built()}); "
            "use collector.device=cpu or null"
        )
    return None


def _check_ppo(cfg: DictConfig, rule) -> None:
    """The rules between ``ppo.*`` and other keys (``algorithm=ppo``)."""
    p = cfg.ppo
    rule(("ppo.minibatch_size", "ppo.rollout_frames"),
         lambda: p.minibatch_size <= p.rollout_frames, "ppo.minibatch_size",
         f"<= ppo.rollout_frames ({p.rollout_frames})")  # fmt: skip
    rule(("logger.q_points",), lambda: not cfg.logger.q_points, "logger.q_points",
         "null with algorithm=ppo (its critic is V(s), there is no Q(s, a) to log)")  # fmt: skip
    rule(("compile.enabled",), lambda: not cfg.compile.enabled, "compile.enabled",
         "false with algorithm=ppo (its update is not compiled)")  # fmt: skip
    rule(("optim.critic_first",), lambda: not cfg.optim.critic_first, "optim.critic_first",
         "false with algorithm=ppo (its actor and critic share one clipped-objective step)")  # fmt: skip


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


def _check_ray(cfg: DictConfig, problems: list[str]) -> None:
    """Ray itself, and whether the local instance (or the running one) holds the workers."""
    if importlib.util.find_spec("ray") is None:
        problems.append(
            "config key collector.backend='ray' needs the 'ray' package: "
            "pip install 'torchrl-rave[ray]' (or pip install ray)"
        )
        return
    import ray

    r = cfg.ray
    if ray.is_initialized():
        problems += ray_fit_problems(cfg, ray.cluster_resources(), "the running Ray instance")
    elif r.address is None:
        local = {"CPU": r.num_cpus or os.cpu_count(), "memory": float("inf")}
        problems += ray_fit_problems(cfg, local, "a local Ray instance (ray.num_cpus)")
    # a cluster (ray.address) is checked by make_ray_collector once connected


def ray_fit_problems(cfg: DictConfig, total: dict, where: str) -> list[str]:
    """The collector actors that Ray resources ``total`` cannot hold all at once: the ones
    left over would wait for resources forever, and the run with them."""
    workers, r = cfg.collector.num_workers, cfg.ray
    needs = [("CPU", "ray.worker_cpus", r.worker_cpus)]
    if r.worker_memory is not None:
        needs.append(("memory", "ray.worker_memory", r.worker_memory))
    needs += [
        (name, f"ray.worker_resources.{name}", n) for name, n in (r.worker_resources or {}).items()
    ]
    out = []
    for name, key, amount in needs:
        have = total.get(name, 0)
        if workers * amount > have:
            out.append(_invalid(key, amount,
                f"collector.num_workers x {amount:g} = {workers * amount:g} {name} <= the "
                f"{have:g} {name} of {where}; lower it (fractions are fine), use fewer workers "
                "or add nodes"))  # fmt: skip
    return out


def check_ray_fits(cfg: DictConfig, total: dict, where: str) -> None:
    """Raises :class:`ConfigError` when Ray resources ``total`` cannot hold the workers."""
    problems = ray_fit_problems(cfg, total, where)
    if problems:
        raise ConfigError(problems)


class BusyCoresWarning(UserWarning):
    """Torch's threads outnumber the cores this process can run them on: other processes
    keep so many of its cores busy, or its cgroup's CPU quota allows fewer cores' time
    (:func:`cpu_quota`). Each parallel kernel then waits for threads that are not
    running, and a run can take several times as long (:func:`apply_process_settings`)."""


def _core_ticks(stat: str, cores: set[int]) -> dict[int, tuple[int, int]]:
    """Each listed core's (all, idle) clock ticks since boot, from the text of
    ``/proc/stat`` (idle: its ``idle`` and ``iowait`` columns; all: the first eight
    columns, which hold every tick once)."""
    out = {}
    for line in stat.splitlines():
        name, *fields = line.split() or [""]
        if name.startswith("cpu") and name[3:].isdigit() and int(name[3:]) in cores:
            ticks = [int(x) for x in fields[:8]]
            out[int(name[3:])] = (sum(ticks), ticks[3] + ticks[4])
    return out


def busy_cores(window: float = 0.2) -> tuple[float, int] | None:
    """How many of the cores this process may run on (its affinity) are busy, summed over
    cores as each one's non-idle share of the next ``window`` seconds, and how many it may
    run on. The calling thread sleeps meanwhile, so a process that runs nothing else
    measures the others. ``None`` where ``/proc/stat`` cannot be read (not Linux)."""
    try:
        cores = os.sched_getaffinity(0)
        with open("/proc/stat") as f:
            first = _core_ticks(f.read(), cores)
        time.sleep(window)
        with open("/proc/stat") as f:
            second = _core_ticks(f.read(), cores)
    except (AttributeError, OSError):
        return None
    busy = 0.0
    for core, (total, idle) in second.items():
        if core in first and total > first[core][0]:
            busy += 1.0 - (idle - first[core][1]) / (total - first[core][0])
    return busy, len(cores)


def cpu_quota(root: str | Path = "/sys/fs/cgroup", cgroups: str | None = None) -> float | None:
    """The CPU time this process's cgroups allow it, in cores: the tightest quota along
    its cgroup's path and the path's parents, from cgroup v2's ``cpu.max`` (``"<quota>
    <period>"``, ``max`` for none) or cgroup v1's ``cpu.cfs_quota_us`` and
    ``cpu.cfs_period_us`` (``-1`` for none), under ``root``. ``cgroups`` is the text of
    ``/proc/self/cgroup`` (read when ``None``). ``None`` where no quota is set or none
    can be read (not Linux). A container started with ``--cpus`` has such a quota and
    no smaller affinity, so torch's default thread count is the host's cores."""
    root = Path(root)
    try:
        if cgroups is None:
            cgroups = Path("/proc/self/cgroup").read_text()
    except OSError:
        return None
    quotas = []
    for line in cgroups.splitlines():
        hierarchy, _, rest = line.partition(":")
        controllers, _, path = rest.partition(":")
        if hierarchy == "0" and controllers == "":  # v2: one tree, cpu.max
            mounts, files = [root], ("cpu.max",)
        elif "cpu" in controllers.split(","):  # v1: the cpu controller's own tree
            mounts = [root / controllers, root / "cpu"]  # "cpu,cpuacct", or its "cpu" link
            files = ("cpu.cfs_quota_us", "cpu.cfs_period_us")
        else:
            continue
        for mount in dict.fromkeys(mounts):
            if not mount.is_dir():
                continue
            parts = Path(path.strip()).parts[1:]  # in a container the path may not exist
            for depth in range(len(parts), -1, -1):
                try:
                    text = " ".join((mount.joinpath(*parts[:depth], f)).read_text() for f in files)
                    quota, period = text.split()[:2]
                    if quota not in ("max", "-1") and float(period) > 0:
                        quotas.append(float(quota) / float(period))
                except (OSError, ValueError):  # unreadable, or not numbers: no quota known
                    continue
            break
    return min(quotas) if quotas else None


def apply_process_settings(cfg: DictConfig) -> None:
    """The learner process's own settings: ``threads`` (torch's thread count) and
    ``keep_freed_memory`` (:func:`~torchrl_rave.recipe.keep_freed_memory`). Warns
    (:class:`BusyCoresWarning`) when torch runs more threads than there are cores to run
    them: cores that other processes leave free (:func:`busy_cores`) or the cores' time
    the process's cgroup allows (:func:`cpu_quota`), both read only for more than one
    thread."""
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    threads = torch.get_num_threads()
    fits, reasons = threads, []
    measured = busy_cores() if threads > 1 else None
    if measured is not None:
        busy, cores = measured
        free = max(1, round(cores - busy))
        if threads > free:
            fits = min(fits, free)
            reasons.append(f"other processes keep {busy:.1f} of the {cores} cores it may use busy")
    quota = cpu_quota() if threads > 1 else None
    whole = None if quota is None else max(1, math.floor(quota))
    if whole is not None and threads > whole:
        fits = min(fits, whole)
        share = "1 core's" if quota == 1 else f"{quota:g} cores'"
        reasons.append(f"its cgroup's CPU quota allows it {share} time")
    if reasons:
        warnings.warn(
            f"torch runs {threads} threads in this process, and {' and '.join(reasons)}: "
            "with more threads than cores to run them each parallel kernel waits for "
            "threads that are not running, and a run can take several times as long "
            f"(docs: performance, threads); threads={fits} fits",
            BusyCoresWarning,
            stacklevel=2,
        )
    if cfg.keep_freed_memory:
        memory.keep_freed_memory()


class NoUpdatesWarning(UserWarning):
    """A run's config leaves it no frame to learn from: it would collect and make no
    update (e.g. ``collector.total_frames`` below ``collector.init_random_frames``)."""


def learning_start(cfg: DictConfig) -> tuple[int, str]:
    """The stored frames an off-policy run waits for before its first update, and the
    key that sets them: the largest of ``collector.init_random_frames``,
    ``replay_buffer.batch_size`` and, for a model-based algorithm,
    ``world_model.pretrain_frames``."""
    starts = [(cfg.collector.init_random_frames, "collector.init_random_frames"),
              (cfg.replay_buffer.batch_size, "replay_buffer.batch_size")]  # fmt: skip
    if ALGORITHMS[cfg.algorithm].model_based:
        starts.append((cfg.world_model.pretrain_frames, "world_model.pretrain_frames"))
    return max(starts, key=lambda s: s[0])


def warn_if_no_updates(cfg: DictConfig) -> None:
    """Warns (:class:`NoUpdatesWarning`, before any work) when an off-policy run would end
    before its first update: the collector gathers whole batches, and the frames past
    :func:`learning_start` each bring ``optim.utd_ratio`` updates. A warning, not an
    error: a run that only collects (a smoke test, a random-policy dataset) is allowed."""
    if ALGORITHMS[cfg.algorithm].on_policy:
        return
    c = cfg.collector
    collected = -(-c.total_frames // c.frames_per_batch) * c.frames_per_batch
    start, key = learning_start(cfg)
    if cfg.optim.utd_ratio * (collected - start) < 1:
        warnings.warn(
            f"this run makes no update: it collects {collected} frames "
            f"(collector.total_frames={c.total_frames} in batches of {c.frames_per_batch}) "
            f"and learning waits for {start} stored frames ({key}={start}); raise "
            f"collector.total_frames above {start} (or lower {key}) for a run that learns",
            NoUpdatesWarning,
            stacklevel=3,
        )


def replay_buffer_size(cfg: DictConfig) -> int:
    size = cfg.replay_buffer.size
    return min(1_000_000, cfg.collector.total_frames) if size is None else int(size)


def num_critics(cfg: DictConfig, algo: Algorithm) -> int:
    return algo.num_critics if cfg.network.num_critics is None else cfg.network.num_critics


def world_model_sizes(cfg: DictConfig) -> dict[str, int]:
    """The world model's widths and depths: ``world_model.size``'s entry of
    :data:`~torchrl_rave.modules.world_model.WORLD_MODEL_SIZES`, with every ``*_cells`` /
    ``*_layers`` key that is not null in its place."""
    w = cfg.world_model
    table = WORLD_MODEL_SIZES[w.get("size", "cpu")]
    return {k: table[k] if w.get(k) is None else w[k] for k in table}


# Keys that shape the saved modules, buffers or algorithm: a resumed run cannot change them
# (the world model's sizes are compared as resolved by world_model_sizes, and
# replay_buffer.size when it is set).
FIXED_ON_RESUME = [
    "algorithm",
    "env.name",
    "env.action_noise",
    "network",
    "world_model.num_models",
    "ppo.rollout_frames",
    "estimator.horizon",
]


def check_resumable(cfg: DictConfig, saved: DictConfig) -> None:
    changed = [
        (key, OmegaConf.select(cfg, key), OmegaConf.select(saved, key)) for key in FIXED_ON_RESUME
    ]
    new, old = world_model_sizes(cfg), world_model_sizes(saved)
    changed += [(f"world_model.{k}", new[k], old[k]) for k in new]
    # the buffer was allocated at its size when the run started; null keeps it
    size = cfg.replay_buffer.size
    if size is not None:
        changed.append(("replay_buffer.size", size, saved.replay_buffer.size))
    problems = [
        f"resume={cfg.resume!r}: config key {key} is {new_value!r} but the run was started "
        f"with {old_value!r}; it cannot change on resume"
        for key, new_value, old_value in changed
        if new_value != old_value
    ]
    if problems:
        raise ConfigError(problems)
    size, total = saved.replay_buffer.size, cfg.collector.total_frames
    if size is not None and saved.collector.total_frames <= size < total:
        warnings.warn(
            f"resume={cfg.resume!r}: the replay buffer holds {size:,} transitions, its size "
            f"at the run's first start (replay_buffer.size cannot change on resume); "
            f"training on to collector.total_frames={total:,} drops the oldest transitions "
            "once it is full, which a run started with that total would have kept",
            stacklevel=2,
        )
