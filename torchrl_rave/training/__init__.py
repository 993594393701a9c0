"""The training plumbing of ``recipes/rave_mujoco.py``, usable from any script.

- :mod:`~torchrl_rave.training.config`: ``algorithm=`` table and every config check.
- :mod:`~torchrl_rave.training.agent`: :func:`make_agent` (the one builder of any
  algorithm's agent), :func:`load_policy` / :func:`load_agent` from a run directory.
- :mod:`~torchrl_rave.training.update`: the agent's update step, optionally compiled.
- :mod:`~torchrl_rave.training.collect`: direct, process and Ray collectors, weight pushes,
  failure handling.
- :mod:`~torchrl_rave.training.evaluate`: evaluation episodes and the logger.
- :mod:`~torchrl_rave.training.checkpoint`: ``torchrl.checkpoint`` run checkpoints.
- :mod:`~torchrl_rave.training.runs`: the run-directory reader and the grid launcher.
- :mod:`~torchrl_rave.training.memory`: :func:`keep_freed_memory`, malloc reuse for CPU
  training processes (opt-in: it changes the whole process).

These take the recipe's hydra config (``recipes/config.yaml``).
"""

from torchrl_rave.training.agent import Agent, load_agent, load_policy, make_agent
from torchrl_rave.training.checkpoint import RunCheckpoint
from torchrl_rave.training.config import ALGORITHMS, check_config
from torchrl_rave.training.memory import keep_freed_memory
from torchrl_rave.training.runs import Cell, GridStopped, launch_grid, read_scalar, train_seconds

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
