"""Factories for the RAVE recipe (``make_*``), kept apart from the training loop."""

from __future__ import annotations

import torch
from omegaconf import DictConfig
from tensordict.nn import TensorDictSequential
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import DoubleToFloat, GymEnv, RewardSum, StepCounter, TransformedEnv
from torchrl.modules import MLP, Actor, AdditiveGaussianModule, ValueOperator
from torchrl.objectives import SoftUpdate, TD3Loss

from torchrl_rave import WorldModelEnsemble, WorldModelLoss, make_value_expansion_estimator


def make_env(cfg: DictConfig, device: torch.device) -> TransformedEnv:
    import gymnasium as gym

    if cfg.env.name not in gym.registry:
        mujoco = sorted(k for k in gym.registry if k.endswith("-v5"))
        raise ValueError(
            f"env.name={cfg.env.name!r} is not a registered gymnasium id; MuJoCo ids: {mujoco}"
        )
    env = TransformedEnv(GymEnv(cfg.env.name, device=device), DoubleToFloat())
    env.append_transform(StepCounter())
    env.append_transform(RewardSum())
    env.set_seed(cfg.env.seed)
    return env


def make_actor_critic(cfg: DictConfig, env) -> tuple[Actor, ValueOperator, TensorDictSequential]:
    S = env.observation_spec["observation"].shape[-1]
    A = env.action_spec.shape[-1]
    hidden = cfg.network.num_layers - 1  # paper: 4 FC layers including the output layer
    actor = Actor(
        nn.Sequential(
            MLP(
                in_features=S,
                out_features=A,
                num_cells=[cfg.network.actor_cells] * hidden,
                activation_class=nn.ReLU,
            ),
            nn.Tanh(),
        ),
        spec=env.action_spec,
    )
    critic = ValueOperator(
        MLP(
            in_features=S + A,
            out_features=1,
            num_cells=[cfg.network.critic_cells] * hidden,
            activation_class=nn.ReLU,
        ),
        in_keys=["observation", "action"],
    )
    exploration = TensorDictSequential(
        actor,
        AdditiveGaussianModule(
            spec=env.action_spec,
            sigma_init=cfg.exploration.sigma,
            sigma_end=cfg.exploration.sigma,
            annealing_num_steps=1,
        ),
    )
    return actor, critic, exploration


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


def make_losses(cfg: DictConfig, env, actor, critic, world_model):
    # TD3Loss holds K stacked critics; without target smoothing noise it is DDPG on a
    # K-critic ensemble, and the RAVE estimator replaces its target.
    loss = TD3Loss(
        actor,
        critic,
        action_spec=env.action_spec,
        num_qvalue_nets=cfg.network.num_critics,
        policy_noise=0.0,
        noise_clip=0.0,
        loss_function="l2",
    )
    updater = SoftUpdate(loss, tau=cfg.optim.tau)
    e = cfg.estimator
    kwargs = dict(world_model=world_model, gamma=cfg.optim.gamma, horizon=e.horizon)
    if e.name == "rave":
        kwargs.update(
            alpha=e.alpha, adaptive_alpha=e.adaptive_alpha, alpha_error_scale=e.alpha_error_scale
        )
    loss.make_value_estimator(make_value_expansion_estimator(e.name, loss, **kwargs))
    return loss, updater, WorldModelLoss(world_model)


def make_collector(cfg: DictConfig, env, policy, device) -> Collector:
    return Collector(
        env,
        policy,
        frames_per_batch=cfg.collector.frames_per_batch,
        total_frames=cfg.collector.total_frames,
        init_random_frames=cfg.collector.init_random_frames,
        device=device,
    )


def make_replay_buffer(cfg: DictConfig, device) -> TensorDictReplayBuffer:
    return TensorDictReplayBuffer(
        storage=LazyTensorStorage(cfg.replay_buffer.size, device=device),
        batch_size=cfg.replay_buffer.batch_size,
    )


@torch.no_grad()
def evaluate(env, actor, episodes: int) -> dict[str, float]:
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    returns, lengths = [], []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(episodes):
            rollout = env.rollout(10_000, actor, break_when_any_done=True)
            returns.append(rollout["next", "episode_reward"][-1].item())
            lengths.append(rollout["next", "step_count"][-1].item())
    r = torch.tensor(returns)
    return {
        "eval/return": r.mean().item(),
        "eval/return_std": r.std(unbiased=False).item(),
        "eval/episode_length": sum(lengths) / len(lengths),
    }
