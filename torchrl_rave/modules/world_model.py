"""Probabilistic world-model ensemble: transition, reward and termination members."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import Literal

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import InteractionType, TensorDictModuleBase
from tensordict.nn.probabilistic import interaction_type
from tensordict.utils import NestedKey
from torch import nn

from torchrl_rave._checks import first_param_dtype, get_checked
from torchrl_rave.modules.ensemble import EnsembleMLP, GaussianEnsembleMLP
from torchrl_rave.modules.normalizer import RunningNormalizer

__all__ = ["WorldModelEnsemble", "WORLD_MODEL_SIZES", "network_sizes"]


# Named sizes: ``cpu`` trains at a few ms per step on a laptop core; ``paper`` has the
# paper's depths (appendix A) with the widths of STEVE's released configuration; ``mujoco``
# has an MBPO member's transition network (4 hidden layers of 200) and the paper's reward and
# termination depths at STEVE's width, the smallest sizes either justifies.
def network_sizes(
    transition: tuple[int, int], reward: tuple[int, int], termination: tuple[int, int]
) -> dict[str, int]:
    """``WorldModelEnsemble`` keyword arguments from ``(cells, layers)`` per network."""
    out = {}
    for name, (cells, layers) in zip(
        ("transition", "reward", "termination"), (transition, reward, termination), strict=True
    ):
        out[f"{name}_cells"], out[f"{name}_layers"] = cells, layers
    return out


#: The named world-model sizes, ``cpu`` (the default), ``paper`` (STEVE's released widths)
#: and ``mujoco`` (an MBPO member's transition network)
WORLD_MODEL_SIZES: dict[str, dict[str, int]] = {
    "cpu": network_sizes(transition=(64, 4), reward=(64, 3), termination=(64, 3)),
    "paper": network_sizes(transition=(512, 8), reward=(128, 4), termination=(128, 4)),
    "mujoco": network_sizes(transition=(200, 5), reward=(128, 4), termination=(128, 4)),
}


def _cells(width: int | Sequence[int], num_layers: int, name: str) -> list[int]:
    """Hidden widths for a network of ``num_layers`` FC layers (output layer included)."""
    if isinstance(width, int):
        if num_layers < 2:
            raise ValueError(f"{name}_layers must be >= 2 (hidden + output), got {num_layers}")
        if width < 1:
            raise ValueError(f"{name}_cells must be >= 1, got {width}")
        return [width] * (num_layers - 1)
    cells = list(width)
    if not cells or min(cells) < 1:
        raise ValueError(f"{name}_cells must be a non-empty list of positive widths, got {cells}")
    return cells


def _draw(mean: torch.Tensor, logvar: torch.Tensor, sample: bool) -> torch.Tensor:
    """A draw from ``N(mean, exp(logvar))`` when ``sample``, else the mean."""
    if not sample:
        return mean
    return mean + torch.randn_like(mean) * (0.5 * logvar).exp()


class WorldModelEnsemble(TensorDictModuleBase):
    """An ensemble of ``N`` probabilistic environment models (paper section 3.2 and 5.1).

    Member ``i`` has a transition model ``f_s,i`` and a termination model ``f_d,i`` (bound
    to the same index, appendix "Rollout Details"); the ``N`` reward models ``f_r,j`` are
    a separate ensemble. All members of a kind are evaluated in one batched-matmul call.

    - Transition: ``(s, a) -> N(mean, var)`` of the *normalised* change ``(s' - s - mu) / sigma``.
    - Reward: ``(s, a, s') -> N(mean, var)`` of the normalised reward.
    - Termination: ``s' -> p(done)`` through a sigmoid.

    Inputs are normalised with running statistics kept as buffers
    (:meth:`update_normalizers`), so they are saved in ``state_dict``.

    Modes: with ``sample=False`` (or under ``set_interaction_type("deterministic")``)
    every member returns its Gaussian mean; with ``sample=True`` (or
    ``set_interaction_type("random")``) each member draws from its own Gaussian.

    Tensor layouts of the hot-path methods (:meth:`step`, :meth:`reward`,
    :meth:`termination_prob`): inputs ``[*B, F]`` are shared by all members, inputs
    ``[N, *B, F]`` with ``per_member=True`` give member ``i`` the slice ``i``; outputs
    are always ``[N, *B, F']``.

    Stacked seeds: a :class:`~torchrl_rave.trainers.SeedGroup` holds the world models of
    its ``S`` seeds as one such module whose parameters and statistics lead with the seed
    (``[S, N, ...]``, ``[S, F]``); the same methods then take ``[S, *B, F]`` (shared) or
    ``[S, N, *B, F]`` (per member) and return ``[S, N, *B, F']``, with each seed's own
    weights and statistics. Its ``draw`` attribute, ``(mean, logvar, sample) -> tensor``,
    replaces the ``randn`` draw where set (the group draws each seed from its own stream).

    Sizes come by name: ``size="cpu"`` (the default: 4 x 64 transition, 3 x 64 reward
    and termination networks, a few ms per training step on one CPU core) or
    ``size="paper"`` (the paper's depths, appendix A: 8 FC layers for the transition model,
    4 for reward and termination, with the widths of STEVE's released configuration, 512
    and 128, which the paper does not state; sized for a GPU). Any ``*_cells`` /
    ``*_layers`` argument overrides its entry.

    The normalisers must see the data (:meth:`update_normalizers_from` on every batch that
    enters the replay buffer, as :class:`~torchrl_rave.trainers.WorldModelTrainer` does);
    training a model whose normalisers never saw any data is refused.

    Args:
        observation_dim (int): size of the observation vector ``S``.
        action_dim (int): size of the action vector ``A``.

    Keyword Args:
        num_models (int): ensemble size ``N``. Defaults to 4.
        size (str): ``"cpu"`` or ``"paper"``, the defaults of the six size arguments below.
            Defaults to ``"cpu"``.
        transition_cells (int or Sequence[int], optional): width of the transition model,
            or its list of hidden widths.
        transition_layers (int, optional): FC layers of the transition model including
            the output layer (ignored when ``transition_cells`` is a list).
        reward_cells (int or Sequence[int], optional): the same for the reward model.
        reward_layers (int, optional): the same for the reward model.
        termination_cells (int or Sequence[int], optional): the same for the termination
            model.
        termination_layers (int, optional): the same for the termination model.
        activation (type[nn.Module]): hidden activation. Defaults to ReLU.
        observation_key (NestedKey): observation entry for :meth:`forward`.
        action_key (NestedKey): action entry for :meth:`forward`.

    Examples:
        >>> wm = WorldModelEnsemble(3, 1, num_models=4, transition_cells=16, reward_cells=16,
        ...                         termination_cells=16)
        >>> obs, act = torch.randn(5, 3), torch.rand(5, 1)
        >>> wm.step(obs, act, sample=False).shape        # every member from the same input
        torch.Size([4, 5, 3])
        >>> nxt = wm.step(obs, act, sample=True)
        >>> wm.step(nxt, act.expand(4, 5, 1), sample=True, per_member=True).shape
        torch.Size([4, 5, 3])
        >>> wm.reward(obs, act, obs, sample=False).shape
        torch.Size([4, 5, 1])
        >>> td = wm(TensorDict(observation=obs, action=act, batch_size=[5]))
        >>> td
        TensorDict(
            fields={
                action: Tensor(shape=torch.Size([4, 5, 1]), device=cpu, dtype=torch.float32, is_shared=False),
                next: TensorDict(
                    fields={
                        observation: Tensor(shape=torch.Size([4, 5, 3]), device=cpu, dtype=torch.float32, is_shared=False),
                        reward: Tensor(shape=torch.Size([4, 5, 1]), device=cpu, dtype=torch.float32, is_shared=False),
                        termination_prob: Tensor(shape=torch.Size([4, 5, 1]), device=cpu, dtype=torch.float32, is_shared=False)},
                    batch_size=torch.Size([4, 5]),
                    device=None,
                    is_shared=False),
                observation: Tensor(shape=torch.Size([4, 5, 3]), device=cpu, dtype=torch.float32, is_shared=False)},
            batch_size=torch.Size([4, 5]),
            device=None,
            is_shared=False)
    """

    default_interaction_type = InteractionType.DETERMINISTIC

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        *,
        num_models: int = 4,
        size: Literal["cpu", "paper"] = "cpu",
        transition_cells: int | Sequence[int] | None = None,
        transition_layers: int | None = None,
        reward_cells: int | Sequence[int] | None = None,
        reward_layers: int | None = None,
        termination_cells: int | Sequence[int] | None = None,
        termination_layers: int | None = None,
        activation: type[nn.Module] = nn.ReLU,
        observation_key: NestedKey = "observation",
        action_key: NestedKey = "action",
    ) -> None:
        super().__init__()
        for name, value in (
            ("num_models", num_models),
            ("observation_dim", observation_dim),
            ("action_dim", action_dim),
        ):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if size not in WORLD_MODEL_SIZES:
            raise ValueError(f"size must be one of {list(WORLD_MODEL_SIZES)}, got {size!r}")
        given = dict(
            transition_cells=transition_cells,
            transition_layers=transition_layers,
            reward_cells=reward_cells,
            reward_layers=reward_layers,
            termination_cells=termination_cells,
            termination_layers=termination_layers,
        )
        sizes = {k: WORLD_MODEL_SIZES[size][k] if v is None else v for k, v in given.items()}
        self.num_models = num_models
        self.observation_dim = observation_dim
        self.action_dim = action_dim
        S, A = observation_dim, action_dim
        self.transition = GaussianEnsembleMLP(
            num_models,
            S + A,
            S,
            _cells(sizes["transition_cells"], sizes["transition_layers"], "transition"),
            activation,
        )
        self.reward_model = GaussianEnsembleMLP(
            num_models,
            2 * S + A,
            1,
            _cells(sizes["reward_cells"], sizes["reward_layers"], "reward"),
            activation,
        )
        self.termination = EnsembleMLP(
            num_models,
            S,
            1,
            _cells(sizes["termination_cells"], sizes["termination_layers"], "termination"),
            activation,
        )
        self.obs_norm = RunningNormalizer(S)
        self.action_norm = RunningNormalizer(A)
        self.delta_norm = RunningNormalizer(S)
        self.reward_norm = RunningNormalizer(1)
        self._normalizers_fitted = False
        self.draw: Callable[[torch.Tensor, torch.Tensor, bool], torch.Tensor] | None = None
        self.observation_key = observation_key
        self.action_key = action_key
        self.in_keys = [observation_key, action_key]
        self.out_keys = [
            ("next", observation_key),
            ("next", "reward"),
            ("next", "termination_prob"),
        ]

    @classmethod
    def from_specs(
        cls,
        observation_spec,
        action_spec,
        *,
        observation_key: NestedKey = "observation",
        **kwargs,
    ) -> WorldModelEnsemble:
        """Builds the ensemble from TorchRL specs (e.g. ``env.observation_spec``, ``env.action_spec``).

        ``observation_spec`` may be a ``Composite`` holding ``observation_key`` or the leaf
        spec itself.

        Examples:
            >>> from torchrl.data import Bounded, Composite, Unbounded
            >>> obs_spec = Composite(observation=Unbounded(shape=(11,)))
            >>> wm = WorldModelEnsemble.from_specs(obs_spec, Bounded(-1, 1, shape=(3,)),
            ...                                    transition_cells=8, reward_cells=8,
            ...                                    termination_cells=8)
            >>> wm.observation_dim, wm.action_dim, wm.num_models
            (11, 3, 4)
        """
        from torchrl.data import Composite

        if isinstance(observation_spec, Composite):
            if observation_key not in observation_spec.keys(True, True):
                raise ValueError(
                    f"observation_key {observation_key!r} is not in the observation spec; "
                    f"it has {list(observation_spec.keys(True, True))}"
                )
            observation_spec = observation_spec[observation_key]
        if isinstance(action_spec, Composite):
            action_spec = action_spec[kwargs.get("action_key", "action")]
        return cls(
            int(observation_spec.shape[-1]),
            int(action_spec.shape[-1]),
            observation_key=observation_key,
            **kwargs,
        )

    # ----------------------------------------------------------------- inputs
    @property
    def seeds(self) -> int | None:
        """The number of stacked seeds (see the class docstring), ``None`` for one model."""
        return self.obs_norm.mean.shape[0] if self.obs_norm.mean.dim() == 2 else None

    def _flatten(self, x: torch.Tensor, per_member: bool, name: str, size: int):
        """``[*S, *B, F]`` -> ``[*S, R, F]`` (shared) or ``[*S, N, *B, F]`` ->
        ``[*S, N, R, F]`` (per member), with ``S`` the stacked seeds (none for one model);
        returns it and ``B``."""
        if x.shape[-1] != size:
            raise ValueError(
                f"world model expects {name} of size {size} in the last dimension, "
                f"got shape {tuple(x.shape)}"
            )
        seeds = () if self.seeds is None else (self.seeds,)
        lead = (*seeds, self.num_models) if per_member else seeds
        if x.dim() < len(lead) + 1 or tuple(x.shape[: len(lead)]) != lead:
            what = ["the number of seeds"] * len(seeds) + ["the ensemble size"] * per_member
            raise ValueError(
                f"{'per-member ' if per_member else ''}{name} must lead with "
                f"{' and '.join(what)} {list(lead)}, got shape {tuple(x.shape)}"
            )
        return x.reshape(*lead, -1, size), x.shape[len(lead) : -1]

    def _unflatten(self, y: torch.Tensor, batch_shape: torch.Size) -> torch.Tensor:
        return y.reshape(*y.shape[:-2], *batch_shape, y.shape[-1])

    def _sa_input(self, obs, action, per_member):
        obs, batch = self._flatten(obs, per_member, "observation", self.observation_dim)
        action, _ = self._flatten(action, per_member, "action", self.action_dim)
        return torch.cat(
            [self.obs_norm.normalize(obs), self.action_norm.normalize(action)], -1
        ), batch

    # ------------------------------------------------------------- transition
    def predict_transition(
        self, obs: torch.Tensor, action: torch.Tensor, *, per_member: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-variance of the normalised state change, each ``[N, *B, S]``."""
        x, batch = self._sa_input(obs, action, per_member)
        mean, logvar = self.transition(x, per_member=per_member)
        return self._unflatten(mean, batch), self._unflatten(logvar, batch)

    def step(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        *,
        sample: bool,
        per_member: bool = False,
    ) -> torch.Tensor:
        """Next observation of every member, ``[N, *B, S]``, in raw (unnormalised) units.

        With ``sample=True`` member ``i`` draws ``s' ~ N(mean_i, var_i)`` (paper eq. 8);
        otherwise it returns its mean.
        """
        delta = (self.draw or _draw)(
            *self.predict_transition(obs, action, per_member=per_member), sample
        )
        if self.seeds is not None and not per_member:  # [S, *B, F]: every member's
            obs = obs.unsqueeze(1)
        return obs + self.delta_norm.denormalize(delta)

    def target_delta(self, obs: torch.Tensor, next_obs: torch.Tensor) -> torch.Tensor:
        """The transition model's regression target: the normalised state change."""
        return self.delta_norm.normalize(next_obs - obs)

    def mean_prediction_error(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> torch.Tensor:
        """``||mean_i f_s,i(s, a) - s'||^2`` in normalised units (paper eq. 12), shape ``[*B]``."""
        mean, _ = self.predict_transition(obs, action)
        members = 0 if self.seeds is None else 1
        return (mean.mean(members) - self.target_delta(obs, next_obs)).pow(2).sum(-1)

    # ----------------------------------------------------------------- reward
    def predict_reward(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        *,
        per_member: bool = False,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-variance of the normalised reward, each ``[N, *B, 1]``."""
        x, batch = self._sa_input(obs, action, per_member)
        nxt, _ = self._flatten(next_obs, per_member, "next observation", self.observation_dim)
        x = torch.cat([x, self.obs_norm.normalize(nxt)], -1)
        mean, logvar = self.reward_model(x, per_member=per_member)
        return self._unflatten(mean, batch), self._unflatten(logvar, batch)

    def reward(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        *,
        sample: bool,
        per_member: bool = False,
    ) -> torch.Tensor:
        """Reward of every reward member, ``[N, *B, 1]``, in raw units (sampled or mean)."""
        reward = (self.draw or _draw)(
            *self.predict_reward(obs, action, next_obs, per_member=per_member), sample
        )
        return self.reward_norm.denormalize(reward)

    # ------------------------------------------------------------ termination
    def termination_logits(
        self, next_obs: torch.Tensor, *, per_member: bool = False
    ) -> torch.Tensor:
        """Logit of ``p(terminated | s')`` for every member, ``[N, *B, 1]``."""
        x, batch = self._flatten(next_obs, per_member, "next observation", self.observation_dim)
        return self._unflatten(
            self.termination(self.obs_norm.normalize(x), per_member=per_member), batch
        )

    def termination_prob(self, next_obs: torch.Tensor, *, per_member: bool = False) -> torch.Tensor:
        """``p(terminated | s')`` for every member, ``[N, *B, 1]``."""
        return torch.sigmoid(self.termination_logits(next_obs, per_member=per_member))

    # ----------------------------------------------------------- normalisers
    @property
    def normalizers_fitted(self) -> bool:
        """Whether the normalisers have seen data (updated, or loaded from a state dict)."""
        if not self._normalizers_fitted:  # a device sync only until the first data
            self._normalizers_fitted = bool((self.obs_norm.count > 0).all())
        return self._normalizers_fitted

    def check_normalizers(self) -> None:
        """Raises when the normalisers never saw data: the model would then be trained
        on raw, unscaled inputs and targets with nothing to say so."""
        if not self.normalizers_fitted:
            raise RuntimeError(
                "the WorldModelEnsemble's normalisers were never updated: call "
                "world_model.update_normalizers_from(batch) on every batch that enters the "
                "replay buffer (WorldModelTrainer.extend(batch) does it) before training"
            )

    @torch.no_grad()
    def update_normalizers(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        reward: torch.Tensor,
    ) -> None:
        """Merges a batch of real transitions into the input and target statistics.

        Call it on every batch that enters the replay buffer (or on the whole buffer).
        """
        self.obs_norm.update(obs)
        self._normalizers_fitted = self._normalizers_fitted or obs.numel() > 0
        self.action_norm.update(action)
        self.delta_norm.update(next_obs - obs)
        self.reward_norm.update(reward.reshape(-1, 1))

    def update_normalizers_from(
        self,
        tensordict: TensorDictBase,
        reward_key: NestedKey = ("next", "reward"),
    ) -> None:
        """Same as :meth:`update_normalizers`, reading a TorchRL transition batch; a
        missing entry, a wrong width, another dtype than the model's, or NaN or infinite
        values, is refused by name before any statistic changes."""
        S, A = self.observation_dim, self.action_dim
        read = functools.partial(get_checked, tensordict, dtype=self.dtype)
        self.update_normalizers(
            read(self.observation_key, S),
            read(self.action_key, A),
            read(("next", self.observation_key), S),
            read(reward_key),
        )

    @property
    def dtype(self) -> torch.dtype:
        """The dtype of the ensemble's parameters (inputs must match it)."""
        return first_param_dtype(self)

    # ------------------------------------------------------------- tensordict
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """One imagined step of every member ``i`` (transition ``i``, reward ``i``, termination ``i``).

        Reads ``observation_key`` and ``action_key`` with batch ``[*B]`` and returns a new
        TensorDict of batch ``[N, *B]`` (the ensemble dimension leading, as in
        ``tensordict.nn.EnsembleModule``). Sampled under ``interaction_type() == RANDOM``,
        means otherwise.
        """
        if self.seeds is not None:
            raise RuntimeError(
                "stacked seeds' world model runs through its methods (step, reward, "
                "termination_prob), not through forward"
            )
        mode = interaction_type() or self.default_interaction_type
        sample = mode == InteractionType.RANDOM
        read = functools.partial(get_checked, tensordict, dtype=self.dtype, floating=True,
                                 check_finite=False)  # fmt: skip
        obs = read(self.observation_key, self.observation_dim)
        action = read(self.action_key, self.action_dim)
        next_obs = self.step(obs, action, sample=sample)
        N = self.num_models
        obs_n = obs.expand(N, *obs.shape)
        act_n = action.expand(N, *action.shape)
        reward = self.reward(obs_n, act_n, next_obs, sample=sample, per_member=True)
        done_p = self.termination_prob(next_obs, per_member=True)
        out = TensorDict(batch_size=[N, *tensordict.batch_size])
        out.set(self.observation_key, obs_n)
        out.set(self.action_key, act_n)
        out.set(("next", self.observation_key), next_obs)
        out.set(("next", "reward"), reward)
        out.set(("next", "termination_prob"), done_p)
        return out

    def extra_repr(self) -> str:
        return (
            f"num_models={self.num_models}, observation_dim={self.observation_dim}, "
            f"action_dim={self.action_dim}"
        )
