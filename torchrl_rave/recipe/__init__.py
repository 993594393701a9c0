"""The application layer: the recipe's config schema, the builder of every algorithm's
agent, its training loop, collectors, evaluation, checkpoints and the run reader; what
``recipes/rave_mujoco.py`` and ``torchrl-rave-train`` run, usable from any script. The
reusable layers (``modules``, ``objectives``, ``trainers``, ``transforms``, ``envs``)
never import it.

- :mod:`~torchrl_rave.recipe.schema`: the typed config schema (defaults: the CPU preset),
  the presets, :func:`default_config`.
- :mod:`~torchrl_rave.recipe.config`: the ``algorithm=`` table and :func:`check_config`
  (every problem at once, as one :class:`ConfigError`).
- :mod:`~torchrl_rave.recipe.agent`: :func:`make_agent` (the one builder of any
  algorithm's agent), :func:`load_policy` / :func:`load_agent` from a run directory.
- :mod:`~torchrl_rave.recipe.loop`: :func:`train`, one resumable run.
- :mod:`~torchrl_rave.recipe.update`: the agent's update step, optionally compiled.
- :mod:`~torchrl_rave.recipe.collect`: direct, process and Ray collectors, weight pushes,
  failure handling.
- :mod:`~torchrl_rave.recipe.evaluate`: evaluation episodes (return, falling rate, value
  error) and the logger.
- :mod:`~torchrl_rave.recipe.checkpoint`: ``torchrl.checkpoint`` run checkpoints.
- :mod:`~torchrl_rave.recipe.runs`: the run-directory reader and the grid launcher.
- :mod:`~torchrl_rave.recipe.memory`: :func:`keep_freed_memory`, malloc reuse for CPU
  training processes (opt-in: it changes the whole process).

Examples:
    >>> from torchrl_rave.recipe import default_config, make_agent, make_env
    >>> cfg = default_config(algorithm="rave", env_name="Hopper-v5")
    >>> agent = make_agent(cfg, make_env(cfg, "cpu"))
    >>> agent.loss.value_estimator.alpha_mode, len(agent.loss.value_network_params)
    ('adaptive', 4)
"""

from torchrl_rave.recipe import _requires  # noqa: F401  (first: names a missing extra)
from torchrl_rave.recipe.agent import Agent, load_agent, load_policy, make_agent, make_env
from torchrl_rave.recipe.checkpoint import RunCheckpoint
from torchrl_rave.recipe.config import ALGORITHMS, ConfigError, check_config
from torchrl_rave.recipe.loop import train
from torchrl_rave.recipe.memory import keep_freed_memory
from torchrl_rave.recipe.runs import (
    Cell,
    GridStopped,
    launch_grid,
    read_scalar,
    relogged,
    train_seconds,
)
from torchrl_rave.recipe.schema import RecipeConfig, default_config

__all__ = [
    "ALGORITHMS",
    "Agent",
    "Cell",
    "ConfigError",
    "GridStopped",
    "RunCheckpoint",
    "RecipeConfig",
    "check_config",
    "default_config",
    "keep_freed_memory",
    "launch_grid",
    "load_agent",
    "load_policy",
    "make_agent",
    "make_env",
    "read_scalar",
    "relogged",
    "train",
    "train_seconds",
]
