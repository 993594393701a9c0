"""Builds the agent of any ``algorithm=``: env, policies, loss, optimisers, world model."""

from __future__ import annotations

import contextlib
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import (
    AddStateIndependentNormalScale,
    NormalParamExtractor,
    TensorDictModule,
    TensorDictModuleBase,
    TensorDictSequential,
)
from torch import nn
from torchrl.data import LazyTensorStorage, SamplerWithoutReplacement, TensorDictReplayBuffer
from torchrl.envs import (
    DoubleToFloat,
    GymEnv,
    GymWrapper,
    RewardScaling,
    RewardSum,
    StepCounter,
    TransformedEnv,
)
from torchrl.envs.utils import ExplorationType
from torchrl.modules import MLP, ProbabilisticActor, TanhModule, TanhNormal, ValueOperator
from torchrl.objectives import (
    ClipPPOLoss,
    LossModule,
    SACLoss,
    SoftUpdate,
    TD3Loss,
    ValueEstimators,
)

from torchrl_rave._checks import get_checked
from torchrl_rave.envs.action_noise import ActuatorNoise
from torchrl_rave.envs.episode_replay import EpisodeReplay
from torchrl_rave.envs.families import import_env_family
from torchrl_rave.modules import EpsilonGaussianModule, WorldModelEnsemble
from torchrl_rave.objectives import (
    EnsembleDDPGLoss,
    ForeachSoftUpdate,
    WorldModelEnsembleLoss,
    make_value_expansion_estimator,
)
from torchrl_rave.recipe.checkpoint import (
    DamagedCheckpoint,
    RunCheckpoint,
    check_run_directory,
    missing_checkpoint,
)
from torchrl_rave.recipe.config import (
    ALGORITHMS,
    Algorithm,
    ConfigError,
    num_critics,
    replay_buffer_size,
    resolve_config,
    world_model_sizes,
)
from torchrl_rave.recipe.trust import check_plain_data, check_trusted
from torchrl_rave.trainers import SeedGroup, WorldModelTrainer
from torchrl_rave.transforms import RewardTermsReader

__all__ = [
    "Agent",
    "CheckedPolicy",
    "bootstrap_value",
    "critic_loss_key",
    "critic_mean",
    "critic_values",
    "load_agent",
    "load_policy",
    "make_agent",
    "make_env",
    "make_replay_buffer",
    "make_seed_group",
    "q_at_points",
]


@dataclass
class Agent:
    """Everything ``algorithm=`` selects, built by :func:`make_agent`."""

    algorithm: Algorithm
    actor: TensorDictModuleBase  # the deterministic policy (evaluation)
    policy: TensorDictModuleBase  # the exploration policy the collector runs
    loss: LossModule
    target_updater: SoftUpdate | None  # None: no target networks (ppo)
    optimizers: dict[str, torch.optim.Optimizer]
    world_model: WorldModelEnsemble | None = None
    world_model_trainer: WorldModelTrainer | None = None

    def state_components(self) -> dict:
        """The agent's checkpoint components (objects with ``state_dict``)."""
        parts = {"loss": self.loss, "policy": self.policy, "world_model": self.world_model}
        parts["world_model_trainer"] = self.world_model_trainer
        parts.update({f"optim_{name}": opt for name, opt in self.optimizers.items()})
        return {name: part for name, part in parts.items() if part is not None}

    def checkpoint_bytes(
        self, replay_capacity: int, transition: TensorDictBase, block: int = 4096
    ) -> int:
        """An upper bound on the disk space of one checkpoint, on a filesystem of ``block``-
        byte blocks: every tensor is a file of its own, rounded up to whole blocks, which
        for the many small parameters is most of the space. It counts the agent's state,
        Adam's two moments and step for every optimised parameter (the world model's too;
        they do not exist before the first step), and a replay buffer of
        ``replay_capacity`` frames like ``transition`` (TorchRL allocates the whole buffer
        at the first extend; a quarter is added for the collector's own entries), plus the
        JSON files."""

        def disk(nbytes: int) -> int:
            return -(-int(nbytes) // block) * block

        def tensors(state) -> list[torch.Tensor]:
            if isinstance(state, torch.Tensor):
                return [state]
            if isinstance(state, dict):
                state = list(state.values())
            if isinstance(state, (list, tuple)):
                return [t for item in state for t in tensors(item)]
            return []

        parts = self.state_components()
        total = 0
        for part in parts.values():  # each a directory with its metadata files
            total += sum(disk(t.numel() * t.element_size()) for t in tensors(part.state_dict()))
            total += 4 * block
        optimizers = list(self.optimizers.values())
        if self.world_model_trainer is not None:
            optimizers.append(self.world_model_trainer.optimizer)
        for opt in optimizers:
            for group in opt.param_groups:
                for p in group["params"]:
                    total += 2 * disk(p.numel() * p.element_size()) + disk(8)
        rows = [
            replay_capacity * t.numel() * t.element_size() for t in tensors(transition.to_dict())
        ]
        total += int(1.25 * sum(disk(n) for n in rows)) + 16 * block
        return total + (256 << 10)  # the RNG state, the config and the counters (JSON)


def make_agent(cfg: DictConfig, env, device: torch.device | str = "cpu") -> Agent:
    """The agent of ``cfg.algorithm`` for ``env``'s specs, on ``device``; the one builder
    the recipe, the analyses and the benchmark share."""
    algo = ALGORITHMS[cfg.algorithm]
    actor, policy = make_actor(cfg, env, algo)
    critic = make_critic(cfg, env)
    world_model = make_world_model(cfg, env).to(device) if algo.model_based else None
    loss, updater = make_loss(cfg, env, algo, actor, critic, world_model)
    loss, policy = loss.to(device), policy.to(device)
    return Agent(
        algorithm=algo,
        actor=actor,
        policy=policy,
        loss=loss,
        target_updater=updater,
        optimizers=make_optimizers(cfg, loss),
        world_model=world_model,
        world_model_trainer=make_world_model_trainer(cfg, world_model),
    )


def load_agent(
    run_dir: str | Path, device: torch.device | str = "cpu", *, trust: bool = False
) -> tuple[DictConfig, Agent]:
    """The config and the agent of a run directory's latest checkpoint. Nothing in it is
    unpickled or executed, and nothing outside it is read. A saved config that would import
    a module (``env.name="module:EnvId"``) or open a file by name (a string in
    ``env.kwargs``) raises :class:`~torchrl_rave.recipe.trust.UntrustedRunConfig` unless
    ``trust=True`` says that the run directory is trusted (:mod:`torchrl_rave.recipe.trust`)."""
    check_run_directory(run_dir)
    checkpoint = RunCheckpoint(run_dir)
    path = checkpoint.latest()  # the newest undamaged one
    if path is None:
        raise missing_checkpoint(run_dir)
    data = checkpoint.read("config", path)
    where = f"load_agent({str(run_dir)!r})"
    check_plain_data(data, set(), where)
    missing = [k for k in ("algorithm", "env", "network")
               if not isinstance(data, dict) or k not in data]  # fmt: skip
    if missing or data["algorithm"] not in ALGORITHMS or "name" not in (data["env"] or {}):
        raise DamagedCheckpoint(
            f"{path}: its saved config lacks {missing or 'a known algorithm or env.name'}, "
            "which decide what is built: it was not written by torchrl-rave, or was edited"
        )
    cfg = OmegaConf.create(data)
    if "ray" in cfg:
        cfg.ray.address = None  # loading a policy connects nowhere
    if not trust:
        how = "Pass trust=True if you trust the run directory."
        check_trusted(cfg, set(), where, how)
    _check_saved_sizes(cfg, checkpoint, path)
    env = make_env(cfg, torch.device(device))
    try:
        agent = make_agent(cfg, env, device)
    finally:
        env.close()
    parts = {k: v for k, v in agent.state_components().items() if not k.startswith("optim")}
    if agent.world_model_trainer is not None:
        del parts["world_model_trainer"]
    checkpoint.load(path=path, restore_rng=False, **parts)
    for name, module in parts.items():
        for key, value in module.state_dict().items():
            if torch.is_tensor(value) and value.is_floating_point() and not value.isfinite().all():
                raise DamagedCheckpoint(
                    f"{path}: {name}'s {key} holds NaN or inf; the run diverged before this "
                    "checkpoint, or it was edited: load an earlier one"
                )
    return cfg, agent


def _check_saved_sizes(cfg: DictConfig, checkpoint, path: Path) -> None:
    """Before anything is allocated: every width and ensemble size a saved config asks
    for is a size of some tensor the checkpoint holds, and every depth at most their
    number, so an edited config cannot make :func:`load_agent` allocate networks far
    larger than the run trained (the sizes then fail to load anyway, after the memory
    was taken). Raises :class:`DamagedCheckpoint` naming the key."""
    from torchrl.checkpoint import Checkpoint

    skip = ("config", "counters", "logger", "episode", "rng", "replay_buffer",
            "world_model_trainer")  # fmt: skip
    names = [n for n in Checkpoint.manifest(path)["components"]
             if n not in skip and not n.startswith("optim")]  # fmt: skip
    sizes, count = set(), 0
    for name in names:
        state = checkpoint.read(name, path)
        stack = [state]
        while stack:
            item = stack.pop()
            if torch.is_tensor(item):
                sizes.update(item.shape)
                count += 1
            elif isinstance(item, dict):
                stack += list(item.values())
            elif isinstance(item, (list, tuple)):
                stack += list(item)
    algorithm = ALGORITHMS[cfg.algorithm]
    widths = {"network.actor_cells": cfg.network.actor_cells,
              "network.critic_cells": cfg.network.critic_cells,
              "network.num_critics": cfg.network.get("num_critics")}  # fmt: skip
    depths = {"network.num_layers": cfg.network.num_layers}
    if algorithm.model_based:
        widths["world_model.num_models"] = cfg.world_model.num_models
        for key, value in world_model_sizes(cfg).items():
            (depths if key.endswith("_layers") else widths)[f"world_model.{key}"] = value
    problems = [
        f"{key}={value!r} is the size of no tensor of the checkpoint"
        for key, value in widths.items()
        if value is not None and not (isinstance(value, int) and (value <= 1 or value in sizes))
    ] + [
        f"{key}={value!r} is more layers than the checkpoint has tensors ({count})"
        for key, value in depths.items()
        if not (isinstance(value, int) and value <= count)
    ]
    if problems:
        raise DamagedCheckpoint(
            f"{path}: its saved config does not match its tensors: {'; '.join(problems)}; "
            "the config was edited (building those networks could take any amount of memory)"
        )


def load_policy(
    run_dir: str | Path,
    device: torch.device | str = "cpu",
    *,
    explore: bool = False,
    trust: bool = False,
) -> TensorDictModuleBase:
    """A ready TorchRL policy from a run directory: the trained deterministic actor (or,
    with ``explore=True``, the exploration policy the run collected with), in a
    :class:`~torchrl_rave.recipe.agent.CheckedPolicy` that names observations of the wrong width or dtype, and NaN.
    ``trust`` as for :func:`load_agent`.

    Examples:
        >>> policy = load_policy("outputs/2026-11-23/10-00-00")  # doctest: +SKIP
        >>> env.rollout(1000, policy)  # doctest: +SKIP
    """
    _, agent = load_agent(run_dir, device, trust=trust)
    return CheckedPolicy(agent.policy if explore else agent.actor)


class CheckedPolicy(TensorDictModuleBase):
    """A policy that names bad input before acting: a missing observation entry, one of
    another width than the policy was trained on, an integer or other-precision tensor,
    NaN or inf (each a ``ValueError`` naming the entry, as the losses raise). Otherwise it
    is ``policy`` itself: the same keys, parameters and outputs.
    :func:`~torchrl_rave.recipe.load_policy` returns one, so that a loaded policy fed the wrong env's
    observations says so instead of failing inside a matrix product.

    Args:
        policy (TensorDictModuleBase): a policy reading ``"observation"``, whose first
            ``nn.Linear`` reads the observation (the recipe's actors).
    """

    def __init__(self, policy: TensorDictModuleBase) -> None:
        super().__init__()
        self.policy = policy
        self.in_keys, self.out_keys = list(policy.in_keys), list(policy.out_keys)
        first = next(m for m in policy.modules() if isinstance(m, nn.Linear))
        self.width, self.dtype = first.in_features, first.weight.dtype

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        get_checked(tensordict, "observation", self.width, dtype=self.dtype, floating=True)
        return self.policy(tensordict)


def _check_spaces(name: str, env):
    """``env`` itself, or a :class:`ConfigError` (the env closed) when the recipe's learners
    cannot drive it: they act in a bounded 1-D box and read a flat observation vector."""
    from gymnasium import spaces

    act, obs = env.action_space, env.observation_space
    problems = []
    if not (
        isinstance(act, spaces.Box)
        and len(act.shape) == 1
        and np.isfinite(act.low).all()
        and np.isfinite(act.high).all()
    ):
        problems.append(
            f"config key env.name={name!r}: its action space is {act}, and the recipe's "
            "learners act in a continuous 1-D box with finite bounds"
        )
    if not (isinstance(obs, spaces.Box) and len(obs.shape) == 1):
        problems.append(
            f"config key env.name={name!r}: its observation space is {obs}, and the "
            "recipe's networks read a flat observation vector (a 1-D box)"
        )
    if problems:
        env.close()
        raise ConfigError(problems)
    return env


@contextlib.contextmanager
def _named_kwargs_error(name: str, kwargs: dict):
    """A keyword the env does not take, as a :class:`ConfigError` naming it (gymnasium
    names it inside a long message)."""
    try:
        yield
    except TypeError as err:
        unknown = re.search(r"unexpected keyword argument '[^']+'", str(err))
        if not kwargs or unknown is None:
            raise
        raise ConfigError(
            [f"config key env.kwargs={kwargs}: {name} got an {unknown.group(0)}"]
        ) from None


def check_env(cfg: DictConfig) -> None:
    """Builds ``cfg``'s env once (the gymnasium env, without TorchRL's wrapper), checks
    the keywords it takes and the spaces the learners need, and closes it; a
    :class:`ConfigError` names a problem. A grid runs it once per distinct env before any
    cell starts (:func:`~torchrl_rave.recipe.runs.check_cells`)."""
    import gymnasium as gym

    import_env_family(cfg.env.name.split(":")[-1])
    kwargs = dict(cfg.env.kwargs or {})
    with _named_kwargs_error(cfg.env.name, kwargs):
        env = gym.make(cfg.env.name, **kwargs)
    _check_spaces(cfg.env.name, env).close()


def make_env(
    cfg: DictConfig, device: torch.device, *, record_episode: bool = False
) -> TransformedEnv:
    """The training (or evaluation) env: float32, step counter, episode return, reward
    scaling; with ``env.action_noise > 0`` its transitions are made stochastic by
    :class:`~torchrl_rave.envs.ActuatorNoise`. An env that names its reward terms
    (``reward_term_names``, e.g. ``LearnToMove-v0``) gets them as ``("next",
    "reward_terms", name)`` entries (:class:`~torchrl_rave.transforms.RewardTermsReader`).
    ``record_episode`` wraps the gymnasium env in :class:`~torchrl_rave.envs.EpisodeReplay`
    (outermost), so that a checkpoint can keep the episode in progress.
    Optional families (PyBullet ids) are registered first, here as in workers."""
    import gymnasium as gym

    import_env_family(cfg.env.name.split(":")[-1])
    kwargs = dict(cfg.env.kwargs or {})
    noise = float(cfg.env.get("action_noise", 0.0))  # runs saved before the key: none
    with _named_kwargs_error(cfg.env.name, kwargs):
        if noise > 0 or record_episode:
            raw = _check_spaces(cfg.env.name, gym.make(cfg.env.name, **kwargs))
            if noise > 0:
                raw = ActuatorNoise(raw, noise)
            if record_episode:
                raw = EpisodeReplay(raw)
            base = GymWrapper(raw, device=device)
        else:  # an evaluation env, or one in a collector's worker process
            base = GymEnv(cfg.env.name, device=device, **kwargs)
            _check_spaces(cfg.env.name, base._env)
    try:
        terms = base._env.get_wrapper_attr("reward_term_names")
    except AttributeError:
        terms = None
    if terms:  # an env whose reward is a sum of named terms: they reach the replay buffer
        base.set_info_dict_reader(RewardTermsReader(terms))
    env = TransformedEnv(base, DoubleToFloat())
    env.append_transform(StepCounter())
    env.append_transform(RewardSum())  # before the scaling: returns stay in env units
    if cfg.env.reward_scale != 1.0:
        env.append_transform(RewardScaling(loc=0.0, scale=cfg.env.reward_scale))
    return env


def _mlp(cfg: DictConfig, in_features: int, out_features: int, cells: int) -> MLP:
    # num_layers counts FC layers with the output layer (paper appendix A: 4); PPO keeps
    # the tanh hidden units of its usual MuJoCo networks
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=[cells] * (cfg.network.num_layers - 1),
        activation_class=nn.Tanh if cfg.algorithm == "ppo" else nn.ReLU,
    )


def make_actor(cfg: DictConfig, env, algo: Algorithm):
    """The policy and the exploration policy the collector runs.

    Deterministic policies end in :class:`~torchrl.modules.TanhModule`, which maps onto the
    action box; SAC's policy is a tanh-Gaussian and explores by sampling, and so is PPO's,
    with a state-independent scale and the log-probability of each action it takes.
    """
    spec = env.action_spec
    S, A = env.observation_spec["observation"].shape[-1], spec.shape[-1]
    if algo.loss in ("sac", "ppo"):
        if algo.loss == "sac":  # scale from the network
            extractor = NormalParamExtractor(
                scale_mapping=f"biased_softplus_{float(cfg.network.default_policy_scale)}",
                scale_lb=cfg.network.scale_lb,
            )
            head = [_mlp(cfg, S, 2 * A, cfg.network.actor_cells), extractor]
        else:  # a learned scale that does not depend on the state
            head = [_mlp(cfg, S, A, cfg.network.actor_cells), AddStateIndependentNormalScale(A)]
        actor = ProbabilisticActor(
            TensorDictModule(
                nn.Sequential(*head), in_keys=["observation"], out_keys=["loc", "scale"]
            ),
            in_keys=["loc", "scale"],
            spec=spec,
            distribution_class=TanhNormal,
            distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
            default_interaction_type=ExplorationType.RANDOM,
            return_log_prob=algo.loss == "ppo",  # PPO's ratio needs the collecting policy's
        )
        return actor, actor
    actor = TensorDictSequential(
        TensorDictModule(
            _mlp(cfg, S, A, cfg.network.actor_cells), in_keys=["observation"], out_keys=["param"]
        ),
        TanhModule(in_keys=["param"], out_keys=["action"], spec=spec),
    )
    noise = EpsilonGaussianModule(
        spec, sigma=cfg.exploration.sigma, epsilon=cfg.exploration.epsilon
    )
    return actor, TensorDictSequential(actor, noise)


def make_critic(cfg: DictConfig, env) -> ValueOperator:
    """``Q(s, a)``; for ppo the state value ``V(s)``."""
    S = env.observation_spec["observation"].shape[-1]
    A = env.action_spec.shape[-1]
    if cfg.algorithm == "ppo":
        return ValueOperator(_mlp(cfg, S, 1, cfg.network.critic_cells), in_keys=["observation"])
    return ValueOperator(
        _mlp(cfg, S + A, 1, cfg.network.critic_cells), in_keys=["observation", "action"]
    )


def make_world_model(cfg: DictConfig, env) -> WorldModelEnsemble:
    """The world model of ``world_model.size`` with its per-key overrides
    (:func:`~torchrl_rave.recipe.config.world_model_sizes`)."""
    return WorldModelEnsemble.from_specs(
        env.observation_spec,
        env.action_spec,
        num_models=cfg.world_model.num_models,
        **world_model_sizes(cfg),
    )


def make_loss(cfg: DictConfig, env, algo: Algorithm, actor, critic, world_model):
    """The TorchRL loss with its target estimator, and the soft target updater (``None``
    for ppo, which has no target networks)."""
    K = num_critics(cfg, algo)
    if algo.loss == "ppo":
        p = cfg.ppo
        loss = ClipPPOLoss(
            actor,
            critic,
            clip_epsilon=p.clip_epsilon,
            entropy_bonus=p.entropy_coef > 0,
            entropy_coeff=p.entropy_coef,
            critic_coeff=p.critic_coef,
            loss_critic_type="l2",
            normalize_advantage=True,
        )
        loss.make_value_estimator(ValueEstimators.GAE, gamma=cfg.optim.gamma, lmbda=p.gae_lambda)
        return loss, None
    if algo.loss == "sac":
        loss = SACLoss(
            actor, critic, num_qvalue_nets=K, loss_function="l2", action_spec=env.action_spec
        )
    elif algo.loss == "td3":
        loss = TD3Loss(
            actor,
            critic,
            action_spec=env.action_spec,
            num_qvalue_nets=K,
            policy_noise=cfg.td3.policy_noise,
            noise_clip=cfg.td3.noise_clip,
            loss_function="l2",
        )
    else:
        # batches were checked for NaN/inf on their way into the buffer
        loss = EnsembleDDPGLoss(actor, critic, num_value_nets=K, check_inputs=False)
    if algo.estimator is None:
        loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.optim.gamma)
    else:
        e = cfg.estimator
        # check_inputs=False: batches were checked for NaN/inf on their way into the buffer
        kwargs = dict(
            world_model=world_model, gamma=cfg.optim.gamma, horizon=e.horizon, check_inputs=False
        )
        if algo.estimator == "rave":
            kwargs.update(
                alpha=e.alpha, alpha_mode=algo.alpha_mode, alpha_error_scale=e.alpha_error_scale
            )
        loss.make_value_estimator(make_value_expansion_estimator(algo.estimator, loss, **kwargs))
    return loss, ForeachSoftUpdate(loss, tau=cfg.optim.tau)


def critic_params(loss):
    """The critics' parameters: ``value_network`` (EnsembleDDPGLoss) or ``qvalue_network``."""
    if isinstance(loss, EnsembleDDPGLoss):
        return loss.value_network_params, loss.value_network
    if isinstance(loss, ClipPPOLoss):
        return loss.critic_network_params, loss.critic_network
    return loss.qvalue_network_params, loss.qvalue_network


def critic_loss_key(loss) -> str:
    if isinstance(loss, ClipPPOLoss):
        return "loss_critic"
    return "loss_value" if isinstance(loss, EnsembleDDPGLoss) else "loss_qvalue"


def make_optimizers(cfg: DictConfig, loss) -> dict[str, torch.optim.Optimizer]:
    # fused Adam: one kernel per step instead of a Python loop over tensors (3x on CPU)
    def adam(params, lr, **kwargs):
        return torch.optim.Adam(list(params), lr=lr, fused=True, **kwargs)

    if isinstance(loss, ClipPPOLoss):  # one learning rate, annealed by the update
        return {
            "actor": adam(loss.actor_network_params.values(True, True), cfg.ppo.lr, eps=1e-5),
            "critic": adam(critic_params(loss)[0].values(True, True), cfg.ppo.lr, eps=1e-5),
        }
    optimizers = {
        "actor": adam(loss.actor_network_params.values(True, True), cfg.optim.lr_actor),
        "critic": adam(critic_params(loss)[0].values(True, True), cfg.optim.lr_critic),
    }
    if isinstance(loss, SACLoss):
        optimizers["alpha"] = adam([loss.log_alpha], cfg.optim.lr_alpha)
    return optimizers


def make_world_model_trainer(
    cfg: DictConfig, world_model: WorldModelEnsemble | None
) -> WorldModelTrainer | None:
    """The world model's loss, optimiser and pretraining schedule (model-based algorithms)."""
    if world_model is None:
        return None
    w = cfg.world_model
    trainer = WorldModelTrainer(
        world_model,
        lr=w.lr,
        pretrain_updates=w.pretrain_updates,
        train_every=w.train_every,
        # the collector's batches are checked for NaN/inf before they reach the buffer
        loss=WorldModelEnsembleLoss(world_model, check_finite=False),
    )
    if cfg.compile.enabled:
        trainer.compile(cfg.compile.mode)
    return trainer


def make_seed_group(cfg: DictConfig, agents: list[Agent], **kwargs):
    """One :class:`~torchrl_rave.trainers.SeedGroup` of ``agents`` (built by
    :func:`~torchrl_rave.recipe.make_agent` from ``cfg``, one per seed), with ``cfg``'s learning rates and ``tau``
    (``kwargs``: its other keyword arguments). From then on the agents' parameters are
    views of the group's tensors."""
    model_based = agents[0].world_model is not None
    return SeedGroup(
        [a.loss for a in agents],
        lr_actor=cfg.optim.lr_actor,
        lr_critic=cfg.optim.lr_critic,
        tau=cfg.optim.tau,
        world_model_losses=[a.world_model_trainer.loss for a in agents] if model_based else None,
        lr_world_model=cfg.world_model.lr if model_based else None,
        lr_alpha=cfg.optim.lr_alpha if ALGORITHMS[cfg.algorithm].loss == "sac" else None,
        critic_first=cfg.optim.critic_first,
        **kwargs,
    )


def make_replay_buffer(cfg: DictConfig, device) -> TensorDictReplayBuffer:
    """The replay buffer; for ppo the rollout buffer of one batch, read in minibatches
    without replacement (see :func:`~torchrl_rave.recipe.config.resolve_config`)."""
    cfg = resolve_config(cfg)
    sampler = SamplerWithoutReplacement() if cfg.algorithm == "ppo" else None
    return TensorDictReplayBuffer(
        storage=LazyTensorStorage(replay_buffer_size(cfg), device=device),
        sampler=sampler,
        batch_size=cfg.replay_buffer.batch_size,
    )


def critic_values(loss, td: TensorDictBase) -> torch.Tensor:
    """``Q_k(s, a)`` ``[K, *B]`` of each of the loss's stacked critics (``[K, ...]``
    params) at ``td``'s observation and action; for ppo ``V(s)`` ``[1, *B]``."""
    params, network = critic_params(loss)
    if isinstance(loss, ClipPPOLoss):
        with params.to_module(network):
            return network(td.clone())["state_value"].squeeze(-1).unsqueeze(0)
    values = []
    for k in range(params.batch_size[0]):
        with params[k].to_module(network):
            values.append(network(td.clone())["state_action_value"].squeeze(-1))
    return torch.stack(values)


def critic_mean(loss, td: TensorDictBase) -> torch.Tensor:
    """``Q(s, a)`` ``[*B]`` averaged over the loss's stacked critics (``[K, ...]`` params)."""
    return critic_values(loss, td).mean(0)


def bootstrap_value(loss, td: TensorDictBase) -> torch.Tensor:
    """The critics' estimate ``[*B]`` of the return from ``td``'s state and action, read the
    way each loss reads its critics when it bootstraps: the mean over the K critics for the
    K-critic DDPG loss (the value-expansion candidates average them; K = 1 for ddpg), the
    minimum over the critics for TD3 and SAC (clipped double Q; SAC's critics also carry
    the entropy bonus of later steps, which a return of rewards does not), and ``V(s)``
    for PPO (the value of its stochastic policy)."""
    values = critic_values(loss, td)
    return values.min(0)[0] if isinstance(loss, (TD3Loss, SACLoss)) else values.mean(0)


@torch.no_grad()
def q_at_points(loss, points, reward_scale: float = 1.0) -> dict[str, float]:
    """``q/<name>``: the critics' mean Q at each of ``points`` (``{name: [observation,
    action]}``, the recipe's ``logger.q_points``), in environment reward units."""
    out = {}
    device = loss.actor_network_params.device
    for name, (obs, action) in (points or {}).items():
        td = TensorDict(
            observation=torch.tensor([list(obs)], dtype=torch.float32),
            action=torch.tensor([list(action)], dtype=torch.float32),
            batch_size=[1],
            device=device,
        )
        out[f"q/{name}"] = critic_mean(loss, td).item() / reward_scale
    return out
