"""Environments: the paper's 1-D toy study (registered with gymnasium as ``RAVEToy-v0``),
actuator noise that makes any continuous-control task stochastic, the episode record that
lets a resumed run continue its episode, and the optional families (PyBullet; osim-rl's ``LearnToRun-v0``) registered on demand."""

from torchrl_rave.envs.action_noise import ActuatorNoise
from torchrl_rave.envs.episode_replay import EpisodeReplay, EpisodeReplayError
from torchrl_rave.envs.families import BULLET_IDS, OSIM_IDS, import_env_family
from torchrl_rave.envs.toy import ENV_ID, ToyEnv, deterministic_q, ground_truth_q

__all__ = [
    "ActuatorNoise",
    "BULLET_IDS",
    "ENV_ID",
    "EpisodeReplay",
    "EpisodeReplayError",
    "OSIM_IDS",
    "ToyEnv",
    "deterministic_q",
    "ground_truth_q",
    "import_env_family",
]
