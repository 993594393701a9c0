"""Environments: the paper's 1-D toy study (registered with gymnasium as ``RAVEToy-v0``)."""

from torchrl_rave.envs.toy import ENV_ID, ToyEnv, deterministic_q, ground_truth_q

__all__ = ["ENV_ID", "ToyEnv", "deterministic_q", "ground_truth_q"]
