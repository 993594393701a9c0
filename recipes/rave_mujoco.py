"""Train RAVE, or one of the paper's baselines, on a gymnasium MuJoCo task.

python recipes/rave_mujoco.py                                  # RAVE, InvertedPendulum-v5, CPU
python recipes/rave_mujoco.py env.name=Hopper-v5 algorithm=steve collector.total_frames=100000
python recipes/rave_mujoco.py preset=paper env.name=HalfCheetah-v5           # paper settings
python recipes/rave_mujoco.py resume=outputs/2026-11-22/10-00-00             # continue a run

``algorithm`` picks ddpg | mve | steve | rave | rave_constant (the estimator settings of one
K-critic DDPG learner), td3 | sac | ppo (TorchRL's losses; ppo learns on-policy) or
steve_sac | rave_sac (SAC with a value-expansion target). The pieces come from
``torchrl_rave.recipe`` (the loop is ``torchrl_rave.recipe.loop.train``, which the installed
``torchrl-rave-train`` command runs too); this file reads ``config.yaml`` beside it. See
recipes/README.md for every key and metric.
"""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from torchrl_rave.recipe.cli import exit_on_bad_command_line, run_job
from torchrl_rave.recipe.loop import train  # noqa: F401 (scripts and tests call recipe.train)


@hydra.main(config_path=".", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float:
    return run_job(cfg)


if __name__ == "__main__":
    exit_on_bad_command_line(sys.argv[1:], "python recipes/rave_mujoco.py")
    main()
