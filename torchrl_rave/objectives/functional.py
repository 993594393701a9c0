"""Value-expansion math as pure tensor functions (MVE, STEVE, RAVE), and the one-step
targets of the model-free learners they are compared with.

Notation follows the paper (Zhou et al., "Efficient and Robust Reinforcement Learning
with Uncertainty-based Value Expansion"): transition members ``i`` (with their
termination models), reward members ``j``, target critics ``k``, horizon
``H = 0..H_max``. Layouts:

- ``continuation``: ``[Ni, *B, H_max + 1]``; entry ``h`` is ``c_{t,t+h+1}``.
- ``imagined_rewards``: ``[Ni, Nj, *B, H_max]``; entry ``h`` is ``r~_{t+h+1}(i, j)``.
- ``values``: ``[Ni, K, *B, H_max + 1]``; entry ``H`` is ``Q'_k(s~_{t+H+1}, a~_{t+H+1})``
  on member ``i``'s trajectory.
- candidates: ``[Ni, Nj, K, *B, H_max + 1]``.

Nothing here calls a network: the estimator computes the O(N H) transition, O(N^2 H)
reward and O(N K H) critic evaluations and these functions combine them by broadcasting.
Each function checks that its inputs have these layouts, and names the one that does not
(``ValueError``): TorchRL's own ``[*B, 1]`` reward and done entries would otherwise
broadcast, where sizes happen to match, into candidates of the right shape and the wrong
values.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import torch
from torchrl.objectives.value.functional import td0_return_estimate

from torchrl_rave._checks import NON_NEGATIVE, POSITIVE

__all__ = [
    "imagined_rollout",
    "continuation_weights",
    "discounted_reward_sums",
    "candidate_targets",
    "horizon_moments",
    "inverse_variance_weights",
    "confidence_lower_bound",
    "expansion_target",
    "value_expansion_target",
    "adaptive_alpha",
    "smoothed_target_action",
    "clipped_double_q_target",
]


def _expect(fn: str, name: str, tensor: torch.Tensor, shape, layout: str) -> None:
    if tuple(tensor.shape) != tuple(shape):
        raise ValueError(
            f"{fn}: {name} has shape {list(tensor.shape)}, expected {list(shape)} ({layout})"
        )


def _horizon_layout(fn: str, imagined_rewards: torch.Tensor, continuation: torch.Tensor):
    """``(Ni, B, H_max)`` of ``imagined_rewards [Ni, Nj, *B, H_max]``, with
    ``continuation`` checked against them."""
    if imagined_rewards.dim() < 3:
        raise ValueError(
            f"{fn}: imagined_rewards has shape {list(imagined_rewards.shape)}, expected "
            "[Ni, Nj, *B, H_max]"
        )
    Ni, B, H = (
        imagined_rewards.shape[0],
        tuple(imagined_rewards.shape[2:-1]),
        imagined_rewards.shape[-1],
    )
    _expect(fn, "continuation", continuation, (Ni, *B, H + 1),
            f"[Ni, *B, H_max + 1] with Ni={Ni}, B={list(B)}, H_max={H} from imagined_rewards")  # fmt: skip
    return Ni, B, H


def imagined_rollout(
    obs: torch.Tensor,
    policy: Callable[[torch.Tensor], torch.Tensor],
    step: Callable[[torch.Tensor, torch.Tensor, bool], torch.Tensor],
    num_members: int,
    horizon: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rolls every transition member ``horizon`` steps from the real next state (eq. 8).

    Member ``i`` starts from ``s_{t+1}`` (shared), acts with the target policy and moves
    with its own model: ``a~ = pi'(s~)``, ``s~' = step_i(s~, a~)``. Any leading dimensions
    ``*L`` of ``obs`` (a seed group's seed) lead every tensor.

    Args:
        obs (Tensor): real next observations ``s_{t+1}``, ``[*L, M, S]``.
        policy (Callable): ``[*L, *, S] -> [*L, *, A]``.
        step (Callable): ``(obs, action, per_member) -> [*L, N, M, S]``;
            ``per_member=False`` means the inputs (``[*L, M, .]``) are shared by all
            members, ``True`` that they are ``[*L, N, M, .]``.
        num_members (int): ``N``.
        horizon (int): ``H_max``.

    Returns:
        states ``[*L, N, M, H_max + 1, S]`` and actions ``[*L, N, M, H_max + 1, A]``;
        index 0 is ``(s_{t+1}, pi'(s_{t+1}))`` for every member.

    Examples:
        >>> policy = lambda s: torch.ones_like(s)
        >>> step = lambda s, a, per_member: (s + a).expand(2, *s.shape[-2:])
        >>> states, actions = imagined_rollout(torch.zeros(3, 1), policy, step, 2, 2)
        >>> states[0, 0, :, 0]
        tensor([0., 1., 2.])
    """
    if isinstance(horizon, bool) or int(horizon) != horizon or horizon < 0:
        raise ValueError(f"imagined_rollout: horizon={horizon!r} must be an integer >= 0")
    if isinstance(num_members, bool) or int(num_members) != num_members or num_members < 1:
        raise ValueError(f"imagined_rollout: num_members={num_members!r} must be an integer >= 1")
    action = policy(obs)

    def shared(x):  # [*L, M, F] -> every member's [*L, N, M, F]
        return x.unsqueeze(-3).expand(*x.shape[:-2], num_members, *x.shape[-2:])

    states, actions = [shared(obs)], [shared(action)]
    s, a = obs, action
    for h in range(horizon):
        s = step(s, a, h > 0)
        a = policy(s)
        states.append(s)
        actions.append(a)
    return torch.stack(states, -2), torch.stack(actions, -2)


def continuation_weights(terminated: torch.Tensor, termination_prob: torch.Tensor) -> torch.Tensor:
    """Continuation weights ``c_{t,t+h+1}`` for ``h = 0..H_max`` (eq. 9).

    ``c_{t,t+1} = 1 - d_{t+1}`` from the real transition, then
    ``c_{t,t'} = c_{t,t'-1} (1 - p_d,i(s~_{t'}))``.

    Args:
        terminated (Tensor): real termination flags ``d_{t+1}``, ``[*B]``.
        termination_prob (Tensor): ``p_d,i`` at imagined states ``s~_{t+2..t+H_max+1}``,
            ``[Ni, *B, H_max]``.

    Returns:
        ``[Ni, *B, H_max + 1]``.

    Examples:
        >>> continuation_weights(torch.tensor([0.0, 1.0]), torch.full((1, 2, 2), 0.5))
        tensor([[[1.0000, 0.5000, 0.2500],
                 [0.0000, 0.0000, 0.0000]]])
    """
    if termination_prob.dim() < 2:
        raise ValueError(
            f"continuation_weights: termination_prob has shape {list(termination_prob.shape)}, "
            "expected [Ni, *B, H_max]"
        )
    _expect("continuation_weights", "terminated", terminated, termination_prob.shape[1:-1],
            "[*B], the batch of termination_prob [Ni, *B, H_max]")  # fmt: skip
    first = (1.0 - terminated.to(termination_prob.dtype)).expand(termination_prob.shape[:-1])
    later = torch.cumprod(1.0 - termination_prob, dim=-1) * first.unsqueeze(-1)
    return torch.cat([first.unsqueeze(-1), later], -1)


def _gamma_powers(gamma: torch.Tensor | float, n: int, like: torch.Tensor) -> torch.Tensor:
    """``[gamma^1, ..., gamma^n]``."""
    gamma = torch.as_tensor(gamma, dtype=like.dtype, device=like.device)
    return gamma.pow(torch.arange(1, n + 1, device=like.device, dtype=like.dtype))


def discounted_reward_sums(
    imagined_rewards: torch.Tensor, continuation: torch.Tensor, gamma: torch.Tensor | float
) -> torch.Tensor:
    """Partial sums ``sum_{h=1..H} gamma^h c_{t,t+h} r~_{t+h}(i, j)`` for ``H = 0..H_max``.

    Args:
        imagined_rewards (Tensor): ``[Ni, Nj, *B, H_max]``.
        continuation (Tensor): ``[Ni, *B, H_max + 1]``.
        gamma (float or Tensor): discount.

    Returns:
        ``[Ni, Nj, *B, H_max + 1]``, entry 0 is zero.
    """
    H = _horizon_layout("discounted_reward_sums", imagined_rewards, continuation)[2]
    terms = imagined_rewards * (
        _gamma_powers(gamma, H, imagined_rewards) * continuation[..., :H]
    ).unsqueeze(1)
    zero = terms.new_zeros(*terms.shape[:-1], 1)
    return torch.cat([zero, terms.cumsum(-1)], -1)


def candidate_targets(
    reward: torch.Tensor,
    imagined_rewards: torch.Tensor,
    values: torch.Tensor,
    continuation: torch.Tensor,
    gamma: torch.Tensor | float,
) -> torch.Tensor:
    """All candidate targets ``T_H(i, j, k)`` (eq. 9 with the ensemble of appendix "Rollout Details").

    ``T_H(i,j,k) = r_t + sum_{h=1..H} gamma^h c_{t,t+h} r~_{t+h}(i,j)
    + gamma^{H+1} c_{t,t+H+1} Q'_k(s~_{t+H+1}, a~_{t+H+1})``.

    Args:
        reward (Tensor): real reward ``r_t``, ``[*B]``.
        imagined_rewards (Tensor): ``[Ni, Nj, *B, H_max]``.
        values (Tensor): ``[Ni, K, *B, H_max + 1]``.
        continuation (Tensor): ``[Ni, *B, H_max + 1]``.
        gamma (float or Tensor): discount.

    Returns:
        ``[Ni, Nj, K, *B, H_max + 1]``: ``Ni * Nj * K * (H_max + 1)`` candidates per sample.

    Examples:
        >>> T = candidate_targets(torch.zeros(5), torch.zeros(4, 4, 5, 3),
        ...                       torch.ones(4, 2, 5, 4), torch.ones(4, 5, 4), 0.5)
        >>> T.shape, T[0, 0, 0, 0]
        (torch.Size([4, 4, 2, 5, 4]), tensor([0.5000, 0.2500, 0.1250, 0.0625]))
    """
    fn = "candidate_targets"
    Ni, B, H = _horizon_layout(fn, imagined_rewards, continuation)
    _expect(fn, "reward", reward, B, f"[*B] with B={list(B)} from imagined_rewards")
    if (
        values.dim() != len(B) + 3
        or values.shape[0] != Ni
        or tuple(values.shape[2:]) != (*B, H + 1)
    ):
        raise ValueError(
            f"{fn}: values has shape {list(values.shape)}, expected [Ni, K, *B, H_max + 1] "
            f"with Ni={Ni}, B={list(B)}, H_max={H} from imagined_rewards"
        )
    H1 = values.shape[-1]
    reward_sums = discounted_reward_sums(imagined_rewards, continuation, gamma)  # [Ni, Nj, *B, H+1]
    bootstrap = (_gamma_powers(gamma, H1, values) * continuation).unsqueeze(
        1
    ) * values  # [Ni, K, *B, H+1]
    return reward.unsqueeze(-1) + reward_sums.unsqueeze(2) + bootstrap.unsqueeze(1)


def horizon_moments(
    candidates: torch.Tensor, ensemble_dims: int = 3, *, two_pass: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean ``E_H`` and (population) variance ``V_H`` over the leading ensemble dimensions.

    Args:
        candidates (Tensor): ``[Ni, Nj, K, *B, H_max + 1]``.
        ensemble_dims (int): how many leading dimensions index ensemble members.

    Keyword Args:
        two_pass (bool): the mean, then the mean of the squared deviations (which it
            overwrites in place, so not under autograd), instead of ``torch.var_mean``'s
            one-pass reduction. The same moments to float rounding, 8-9x faster on a seed
            group's candidates (``[4, 4, 4, S, 128, 4]`` at 2 threads: 1.15 -> 0.14 ms at
            S = 4, 2.16 -> 0.24 ms at S = 8), which is what
            :class:`~torchrl_rave.trainers.SeedGroup` uses. Defaults to ``False`` (the
            estimators' choice, kept so that their numbers stay as they are).

    Returns:
        ``(mean, var)``, each ``[*B, H_max + 1]``.
    """
    if not 1 <= ensemble_dims < candidates.dim():
        raise ValueError(
            f"horizon_moments: ensemble_dims={ensemble_dims!r} must lie in [1, "
            f"{candidates.dim() - 1}] for candidates of shape {list(candidates.shape)}"
        )
    if two_pass:
        flat = candidates.flatten(0, ensemble_dims - 1)
        mean = flat.mean(0)
        deviation = flat - mean
        return mean, deviation.mul_(deviation).mean(0)
    dims = tuple(range(ensemble_dims))
    var, mean = torch.var_mean(candidates, dim=dims, correction=0)
    return mean, var


def inverse_variance_weights(var: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """STEVE's horizon weights ``w_H = 1 / (V_H + eps)``, normalised to sum to one (eq. 6).

    Examples:
        >>> inverse_variance_weights(torch.tensor([[1.0, 3.0]]), eps=0.0)
        tensor([[0.7500, 0.2500]])
    """
    w = 1.0 / (var + eps)
    return w / w.sum(-1, keepdim=True)


def confidence_lower_bound(
    mean: torch.Tensor, var: torch.Tensor, alpha: torch.Tensor | float
) -> torch.Tensor:
    """``alpha``-confidence lower bound ``E_H - alpha sqrt(V_H)`` (eq. 10).

    ``alpha`` is a scalar or per-sample ``[*B]`` (broadcast over horizons).
    """
    _expect("confidence_lower_bound", "var", var, mean.shape, "[*B, H_max + 1], as mean")
    if isinstance(alpha, torch.Tensor) and alpha.dim() > 0:
        _expect("confidence_lower_bound", "alpha", alpha, mean.shape[:-1],
                "a scalar or [*B], the batch of mean [*B, H_max + 1]")  # fmt: skip
        alpha = alpha.unsqueeze(-1)
    return mean - alpha * var.sqrt()


def expansion_target(
    mean: torch.Tensor,
    var: torch.Tensor,
    *,
    mix: Literal["inverse_variance", "fixed"],
    alpha: torch.Tensor | float = 0.0,
    horizon: int | None = None,
    eps: float = 1e-8,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Combines per-horizon moments into one target.

    - ``mix="inverse_variance"``: ``sum_H w_H CLB_H / sum_H w_H`` with
      ``w_H = 1 / (V_H + eps)``:
      STEVE (eq. 6) with ``alpha = 0``, RAVE (eq. 11) otherwise.
    - ``mix="fixed"``: ``CLB_H`` at one horizon (``horizon``, default the last): MVE
      (eq. 5) with ``alpha = 0``.

    Args:
        mean (Tensor): ``E_H``, ``[*B, H_max + 1]``.
        var (Tensor): ``V_H``, ``[*B, H_max + 1]``.

    Returns:
        ``(target [*B], weights [*B, H_max + 1])``.

    Examples:
        >>> mean, var = torch.tensor([[1.0, 2.0]]), torch.tensor([[1.0, 1.0]])
        >>> expansion_target(mean, var, mix="inverse_variance")[0]
        tensor([1.5000])
        >>> expansion_target(mean, var, mix="inverse_variance", alpha=1.0)[0]
        tensor([0.5000])
        >>> expansion_target(mean, var, mix="fixed", horizon=0)[0]
        tensor([1.])
    """
    clb = confidence_lower_bound(mean, var, alpha)
    if mix == "inverse_variance":
        weights = inverse_variance_weights(var, eps)
    elif mix == "fixed":
        H = mean.shape[-1] - 1 if horizon is None else horizon
        if isinstance(H, bool) or int(H) != H or not 0 <= H < mean.shape[-1]:
            raise ValueError(
                f"expansion_target: horizon={horizon!r} must be an integer in [0, "
                f"{mean.shape[-1] - 1}] (H_max = {mean.shape[-1] - 1} here)"
            )
        weights = torch.zeros_like(mean)
        weights[..., H] = 1.0
    else:
        raise ValueError(f"mix must be 'inverse_variance' or 'fixed', got {mix!r}")
    return (weights * clb).sum(-1), weights


def value_expansion_target(
    next_obs: torch.Tensor,
    reward: torch.Tensor,
    terminated: torch.Tensor,
    *,
    policy: Callable[[torch.Tensor], torch.Tensor],
    step: Callable[[torch.Tensor, torch.Tensor, bool], torch.Tensor],
    imagined_reward: Callable[[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor],
    termination_prob: Callable[[torch.Tensor], torch.Tensor],
    critic: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    num_members: int,
    horizon: int,
    gamma: torch.Tensor | float,
    mix: Literal["inverse_variance", "fixed"],
    alpha: torch.Tensor | float = 0.0,
    eps: float = 1e-8,
    moments: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]] = horizon_moments,
    temperature: torch.Tensor | float | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The MVE / STEVE / RAVE target of a batch, from the networks as callables: the rollout
    (:func:`imagined_rollout`), every reward member on every transition member's steps, the
    termination probabilities, the critics on every imagined state (the real next state
    once), then the candidates, their moments and the mix (eqs. 5, 6, 9-11).

    Every tensor may carry leading dimensions ``*L`` (none for one learner; a seed group's
    seed), which lead the callables' inputs and outputs too; the functions above see them
    as batch dimensions beside ``M``.

    With ``temperature`` set, the policy is stochastic (SAC's): ``policy`` returns a sampled
    action and its log-probability ``(a~, log pi(a~ | s~))``, and every candidate is a soft
    return, with the entropy bonus ``-temperature * log pi(a~_{t+h} | s~_{t+h})`` of each
    imagined action beside the reward it earns and the bootstrap value it is scored with:
    ``T_H = r_t + sum_{h=1..H} gamma^h c_{t,t+h} (r~_{t+h} - temperature log pi_{t+h})
    + gamma^{H+1} c_{t,t+H+1} (Q'_k - temperature log pi_{t+H+1})``. The critics estimate
    the soft Q-function, so each horizon's candidate estimates the same quantity; at
    ``H = 0`` it is SAC's own TD(0) target ``r_t + gamma c (Q' - temperature log pi)``.

    Args:
        next_obs (Tensor): ``s_{t+1}``, ``[*L, M, S]``.
        reward (Tensor): ``r_t``, ``[*L, M]``.
        terminated (Tensor): whether ``s_{t+1}`` is terminal, ``[*L, M]``.

    Keyword Args:
        policy (Callable): as :func:`imagined_rollout` takes it.
        step (Callable): as :func:`imagined_rollout` takes it.
        imagined_reward (Callable): ``(s, a, s') -> [*L, Nj, Ni, M, H_max]`` for inputs
            ``[*L, Ni, M, H_max, .]``: each reward member on every transition member's steps.
        termination_prob (Callable): ``s' [*L, Ni, M, H_max, S] -> [*L, Ni, M, H_max]``,
            each member's own termination model on its states.
        critic (Callable): ``(s, a) [*L, R, .] -> [*L, K, R]``, the K target critics.
        num_members (int): ``N``.
        horizon (int): ``H_max``.
        gamma (float or Tensor): the discount.
        mix (str): as :func:`expansion_target` takes it.
        alpha (float or Tensor): as :func:`expansion_target` takes it (a scalar or
            ``[*L, M]``).
        eps (float): as :func:`expansion_target` takes it.
        moments (Callable): the moments of the candidates; :func:`horizon_moments`.
        temperature (float or Tensor, optional): SAC's entropy temperature (a scalar or
            ``[*L]``, one per leading index); ``None`` for a deterministic policy.

    Returns:
        ``(target [*L, M], var [*L, M, H_max + 1], weights [*L, M, H_max + 1])``.

    Examples:
        >>> out = value_expansion_target(
        ...     torch.zeros(3, 1), torch.ones(3), torch.zeros(3, dtype=torch.bool),
        ...     policy=torch.zeros_like, step=lambda s, a, per_member: s.new_zeros(2, 3, 1),
        ...     imagined_reward=lambda s, a, s2: s.new_ones(2, *s.shape[:-1]),
        ...     termination_prob=lambda s2: s2.new_zeros(s2.shape[:-1]),
        ...     critic=lambda s, a: s.new_zeros(2, s.shape[0]),
        ...     num_members=2, horizon=1, gamma=0.5, mix="fixed")
        >>> out[0]  # r_t + gamma * r~_{t+1}, both 1, the critics 0
        tensor([1.5000, 1.5000, 1.5000])
    """
    N, H = num_members, horizon
    lead, (M, D) = next_obs.shape[:-2], next_obs.shape[-2:]
    n = len(lead)
    log_probs = []  # a stochastic policy's log pi of each action it takes, in rollout order

    def acting(s):
        if temperature is None:
            return policy(s)
        action, log_prob = policy(s)
        log_probs.append(log_prob)
        return action

    states, actions = imagined_rollout(next_obs, acting, step, N, H)  # [*L, N, M, H+1, F]
    A = actions.shape[-1]
    rewards = imagined_reward(states[..., :-1, :], actions[..., :-1, :], states[..., 1:, :])
    done_prob = termination_prob(states[..., 1:, :])  # [*L, Ni, M, H]
    # Horizon 0 is the same real state for every member: evaluate it once.
    flat_s = torch.cat([states[..., 0, :, 0, :], states[..., 1:, :].reshape(*lead, -1, D)], -2)
    flat_a = torch.cat([actions[..., 0, :, 0, :], actions[..., 1:, :].reshape(*lead, -1, A)], -2)
    q = critic(flat_s, flat_a)  # [*L, K, M + N*M*H]
    K = q.shape[-2]
    q0 = q[..., :M].reshape(*lead, K, 1, M, 1).expand(*lead, K, N, M, 1)
    values = torch.cat([q0, q[..., M:].reshape(*lead, K, N, M, H)], -1)  # [*L, K, Ni, M, H+1]
    # the layouts of the functions above: the ensemble dimensions first, *L with the batch
    rewards, values = rewards.movedim((n + 1, n), (0, 1)), values.movedim((n + 1, n), (0, 1))
    if temperature is not None:  # [*L, M] at s_{t+1}, every member's [*L, N, M] after
        first = log_probs[0].unsqueeze(-2).expand(*lead, N, M)
        log_pi = torch.stack([first, *log_probs[1:]], -1).movedim(n, 0)  # [Ni, *L, M, H+1]
        t = torch.as_tensor(temperature, dtype=log_pi.dtype, device=log_pi.device)
        bonus = -t.reshape(*t.shape, 1, 1) * log_pi  # the entropy bonus of each action
        rewards = rewards + bonus[..., :H].unsqueeze(1)  # beside each reward member's reward
        values = values + bonus.unsqueeze(1)  # and each critic's value
    continuation = continuation_weights(terminated, done_prob.movedim(n, 0))
    candidates = candidate_targets(reward, rewards, values, continuation, gamma)
    mean, var = moments(candidates)
    target, weights = expansion_target(mean, var, mix=mix, alpha=alpha, horizon=H, eps=eps)
    return target, var, weights


def check_alpha_parameters(alpha, alpha_error_scale) -> tuple[float, float]:
    """The parameters of eq. 12, checked once for every user of them (the estimators,
    :class:`~torchrl_rave.transforms.AdaptiveAlpha`, the recipe's schema shares the rules):
    ``alpha`` a finite number >= 0, ``Z`` a finite number > 0."""
    return (
        float(NON_NEGATIVE.check("alpha", float(alpha))),
        float(POSITIVE.check("alpha_error_scale (Z)", float(alpha_error_scale))),
    )


def adaptive_alpha(
    prediction_error: torch.Tensor,
    alpha: torch.Tensor | float,
    alpha_error_scale: torch.Tensor | float = 1.0,
) -> torch.Tensor:
    """Per-sample confidence factor ``max(0, alpha (1 - err / Z))`` (eq. 12).

    Args:
        prediction_error (Tensor): ``||mean_i f_s,i(s_t, a_t) - s_{t+1}||^2`` in the model's
            normalised units, ``[*B]``.
        alpha (float or Tensor): the constant ``alpha``.
        alpha_error_scale (float or Tensor): ``Z``.

    Examples:
        >>> adaptive_alpha(torch.tensor([0.0, 0.5, 3.0]), 1.5, 1.0)
        tensor([1.5000, 0.7500, 0.0000])
    """
    return (alpha * (1.0 - prediction_error / alpha_error_scale)).clamp_min(0.0)


def smoothed_target_action(
    action: torch.Tensor,
    noise: torch.Tensor,
    *,
    scale: float,
    clip: float,
    low: torch.Tensor | float,
    high: torch.Tensor | float,
) -> torch.Tensor:
    """TD3's target policy smoothing: ``clip(a + clip(scale * eps, -c, c), low, high)``, with
    the operations in ``TD3Loss``'s order.

    Args:
        action (Tensor): the target policy's action ``[*S, *B, A]``.
        noise (Tensor): standard normal draws shaped as ``action``.
        scale (float): the noise's standard deviation (``policy_noise``).
        clip (float): the bound of the scaled noise (``noise_clip``).
        low, high (Tensor or float): the action box.

    Examples:
        >>> smoothed_target_action(torch.tensor([0.9, 0.0]), torch.tensor([4.0, -1.0]),
        ...                        scale=0.2, clip=0.5, low=-1.0, high=1.0)
        tensor([ 1.0000, -0.2000])
    """
    return (action + (noise * scale).clamp(-clip, clip)).clamp(low, high)


def clipped_double_q_target(
    next_q: torch.Tensor,
    reward: torch.Tensor,
    terminated: torch.Tensor,
    gamma: torch.Tensor | float,
    *,
    next_log_prob: torch.Tensor | None = None,
    temperature: torch.Tensor | float | None = None,
) -> torch.Tensor:
    """The TD(0) target of ``K`` target critics, ``r + gamma (1 - d) min_k Q'_k(s', a')``
    (TD3's and DDPG-with-K-critics'), or with ``temperature`` SAC's soft one,
    ``r + gamma (1 - d) min_k (Q'_k(s', a') - temperature log pi(a' | s'))``.

    Args:
        next_q (Tensor): the target critics' values at the next state and action,
            ``[*S, K, B]`` (any leading seed dimensions, then the critics, then the rows).
        reward (Tensor): ``[*S, B]``.
        terminated (Tensor): ``[*S, B]`` (bool or float); a terminated row does not
            bootstrap.
        gamma (float or Tensor): the discount.
        next_log_prob (Tensor, optional): ``log pi(a' | s')`` ``[*S, B]`` of a stochastic
            policy's next action; with ``temperature``.
        temperature (float or Tensor, optional): the entropy temperature, a number or a
            tensor that broadcasts against ``[*S, B]`` (one per seed: ``[S, 1]``).

    Returns:
        The target ``[*S, B]``.

    Examples:
        >>> next_q = torch.tensor([[1.0, 2.0], [3.0, 0.5]])  # K = 2 critics, B = 2 rows
        >>> clipped_double_q_target(next_q, torch.zeros(2), torch.tensor([False, True]), 0.5)
        tensor([0.5000, 0.0000])
    """
    if (next_log_prob is None) != (temperature is None):
        raise ValueError("next_log_prob and temperature come together (SAC's soft target)")
    if next_log_prob is not None:
        next_q = next_q - (temperature * next_log_prob).unsqueeze(-2)
    return td0_return_estimate(gamma, next_q.min(-2)[0], reward, terminated)
