"""The application layer: everything ``recipes/rave_mujoco.py`` is made of, usable from any
script. The reusable layers (``modules``, ``objectives``, ``trainers``, ``transforms``,
``envs``) never import it.

- :mod:`~torchrl_rave.recipe.config`: ``algorithm=`` table and every config check.
- :mod:`~torchrl_rave.recipe.agent`: :func:`make_agent` (the one builder of any
  algorithm's agent), :func:`load_policy` / :func:`load_agent` from a run directory.
- :mod:`~torchrl_rave.recipe.update`: the agent's update step, optionally compiled.
- :mod:`~torchrl_rave.recipe.collect`: direct, process and Ray collectors, weight pushes,
  failure handling.
- :mod:`~torchrl_rave.recipe.evaluate`: evaluation episodes and the logger.
- :mod:`~torchrl_rave.recipe.checkpoint`: ``torchrl.checkpoint`` run checkpoints.
- :mod:`~torchrl_rave.recipe.runs`: the run-directory reader and the grid launcher.
- :mod:`~torchrl_rave.recipe.memory`: :func:`keep_freed_memory`, malloc reuse for CPU
  training processes (opt-in: it changes the whole process).

These take the recipe's hydra config (``recipes/config.yaml``).
"""

from torchrl_rave.recipe.agent import Agent, load_agent, load_policy, make_agent
from torchrl_rave.recipe.checkpoint import RunCheckpoint
from torchrl_rave.recipe.config import ALGORITHMS, check_config
from torchrl_rave.recipe.memory import keep_freed_memory
from torchrl_rave.recipe.runs import Cell, GridStopped, launch_grid, read_scalar, train_seconds

__all__ = [
    "ALGORITHMS",
    "Agent",
    "Cell",
    "GridStopped",
    "RunCheckpoint",
    "check_config",
    "keep_freed_memory",
    "launch_grid",
    "load_agent",
    "load_policy",
    "make_agent",
    "read_scalar",
    "train_seconds",
]
