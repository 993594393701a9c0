"""RAVE's training update as one writes it in plain PyTorch: the eager baseline for ours.

``PlainRAVE`` does exactly the recipe's ``algorithm=rave`` update (one world-model step on
per-member bootstrap resamples, the RAVE value target with the adaptive alpha of eq. 12,
``K`` critics, the actor, fused Adam and soft target updates) with nothing but tensors:
no TensorDict inside the update, no TorchRL loss, no modules, every normaliser's standard
deviation computed once per update. It copies its starting parameters and normaliser
statistics from a recipe agent, so that the two can be checked against each other
number for number (``tests/test_benchmarks.py``), and then trains its own copies.

``benchmarks/update_throughput.py`` times it beside ours: whatever ours costs beyond it
is what TorchRL's plumbing and our own structure add; what it costs itself is what eager
PyTorch asks for this arithmetic on this machine.
"""

from __future__ import annotations

import math

import torch
from torch.nn import functional as F

_HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


def _leaf(t: torch.Tensor) -> torch.Tensor:
    return t.detach().clone().requires_grad_(True)


def _ensemble(mlp) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """``(weight [N, in, out], bias [N, 1, out])`` per layer of an ``EnsembleMLP``."""
    return [(_leaf(layer.weight), _leaf(layer.bias)) for layer in mlp.layers]


def _gaussian(g) -> dict:
    return {
        "trunk": _ensemble(g.trunk),
        "mean": (_leaf(g.mean_head.weight), _leaf(g.mean_head.bias)),
        "logvar": (_leaf(g.logvar_head.weight), _leaf(g.logvar_head.bias)),
        "max": _leaf(g.max_logvar),
        "min": _leaf(g.min_logvar),
    }


def tensors(tree) -> list[torch.Tensor]:
    """The tensors of nested dicts, lists and tuples, in order."""
    if isinstance(tree, torch.Tensor):
        return [tree]
    items = tree.values() if isinstance(tree, dict) else tree
    return [t for item in items for t in tensors(item)]


def _layers(params) -> list[str]:
    """The linear layers' names of a flat parameter TensorDict, in the network's order."""
    names = [k[: -len(".weight")] for k in params.keys() if k.endswith(".weight")]  # noqa: SIM118
    return list(dict.fromkeys(names))


def _narrow(w: torch.Tensor) -> torch.Tensor:
    """An output-major copy of a ``[N, in, out]`` weight with ``out < in`` (CPU BLAS is
    several times faster on it; benchmarks/README.md, item 11)."""
    return w.mT.contiguous().mT if w.shape[-1] < w.shape[-2] else w


def _ensemble_mlp(layers, x: torch.Tensor, shared: bool, last_activation=False) -> torch.Tensor:
    """``[M, in]`` (shared by the members) or ``[N, M, in]`` -> ``[N, M, out]``, ReLU between."""
    for n, (w, b) in enumerate(layers):
        w = _narrow(w)
        x = torch.matmul(x, w) + b if shared and n == 0 else torch.baddbmm(b, x, w)
        if n < len(layers) - 1 or last_activation:
            x = x.relu_()
    return x


def _gaussian_mlp(g: dict, x: torch.Tensor, shared: bool):
    h = _ensemble_mlp(g["trunk"], x, shared, last_activation=True)
    mean = torch.baddbmm(g["mean"][1], h, _narrow(g["mean"][0]))
    raw = torch.baddbmm(g["logvar"][1], h, _narrow(g["logvar"][0]))
    logvar = g["max"] - F.softplus(g["max"] - raw)
    return mean, g["min"] + F.softplus(logvar - g["min"])


def _nll(mean, logvar, target) -> torch.Tensor:
    """Per-member Gaussian NLL averaged over rows and features, ``[N]``."""
    nll = 0.5 * ((target - mean).pow(2) * torch.exp(-logvar) + logvar) + _HALF_LOG_2PI
    return nll.mean((1, 2))


class PlainRAVE:
    """The recipe's RAVE update in plain PyTorch, starting from ``agent``'s parameters.

    Args:
        agent: a recipe agent built with ``algorithm=rave`` (``training.make_agent``).
        cfg: its config (learning rates, ``gamma``, ``tau``, ``alpha``, ``Z``).
    """

    def __init__(self, agent, cfg) -> None:
        loss, wm = agent.loss, agent.world_model
        est = loss.value_estimator
        self.N, self.H = wm.num_models, cfg.estimator.horizon
        self.gamma, self.tau = cfg.optim.gamma, cfg.optim.tau
        self.alpha, self.Z = cfg.estimator.alpha, cfg.estimator.alpha_error_scale
        self.eps = est.variance_eps
        self.transition = _gaussian(wm.transition)
        self.reward = _gaussian(wm.reward_model)
        self.termination = _ensemble(wm.termination)
        self.norms = {
            name: (getattr(wm, name).mean.clone(), getattr(wm, name).std.clone())
            for name in ("obs_norm", "action_norm", "delta_norm", "reward_norm")
        }
        actor = loss.actor_network_params.flatten_keys()
        self.actor = [
            (_leaf(actor[f"{k}.weight"]), _leaf(actor[f"{k}.bias"])) for k in _layers(actor)
        ]
        low = next(v for k, v in actor.items() if k.endswith("action_low"))
        high = next(v for k, v in actor.items() if k.endswith("action_high"))
        self.action_low, self.action_range = low.clone(), (high - low).clone()
        critic = loss.value_network_params.flatten_keys()
        # stacked [K, out, in] as nn.Linear stores them; biases [K, 1, out] for baddbmm
        self.critic = [
            (_leaf(critic[f"{k}.weight"]), _leaf(critic[f"{k}.bias"].unsqueeze(1)))
            for k in _layers(critic)
        ]
        self.actor_target = [(w.detach().clone(), b.detach().clone()) for w, b in self.actor]
        self.critic_target = [(w.detach().clone(), b.detach().clone()) for w, b in self.critic]
        self.model = [self.transition, self.reward, self.termination]
        self.opt_model = torch.optim.Adam(tensors(self.model), lr=cfg.world_model.lr, fused=True)
        self.opt_actor = torch.optim.Adam(tensors(self.actor), lr=cfg.optim.lr_actor, fused=True)
        self.opt_critic = torch.optim.Adam(tensors(self.critic), lr=cfg.optim.lr_critic, fused=True)
        self.soft_pairs = [
            (tensors(self.actor_target), tensors(self.actor)),
            (tensors(self.critic_target), tensors(self.critic)),
        ]

    # ------------------------------------------------------------------ networks
    def _norm(self, name: str, x: torch.Tensor) -> torch.Tensor:
        mean, std = self.norms[name]
        return (x - mean) / std

    def policy(self, obs: torch.Tensor, params) -> torch.Tensor:
        x = obs
        for n, (w, b) in enumerate(params):
            x = F.linear(x, w, b)
            if n < len(params) - 1:
                x = x.relu_()
        return self.action_low + self.action_range * (x.tanh() + 1) / 2

    def critics(self, obs: torch.Tensor, action: torch.Tensor, params) -> torch.Tensor:
        """``[K, M]`` values of the ``K`` critics on shared rows ``[M, S]``, ``[M, A]``."""
        x = torch.cat([obs, action], -1)
        for n, (w, b) in enumerate(params):
            x = torch.matmul(x, w.mT) + b if n == 0 else torch.baddbmm(b, x, w.mT)
            if n < len(params) - 1:
                x = x.relu_()
        return x.squeeze(-1)

    def _step(self, s, a, shared: bool) -> torch.Tensor:
        """One sampled transition of every member (eq. 8), ``[N, M, S]``."""
        x = torch.cat([self._norm("obs_norm", s), self._norm("action_norm", a)], -1)
        mean, logvar = _gaussian_mlp(self.transition, x, shared)
        delta = mean + torch.randn_like(mean) * (0.5 * logvar).exp()
        mu, std = self.norms["delta_norm"]
        return s + (delta * std + mu)

    # -------------------------------------------------------------------- target
    @torch.no_grad()
    def target(self, obs, action, next_obs, reward, terminated) -> torch.Tensor:
        """The RAVE target ``[M]`` (eqs. 8-12) with the target actor and critics."""
        N, H, (M, S), A = self.N, self.H, obs.shape, action.shape[-1]
        norm = self._norm
        # eq. 12: the ensemble's mean one-step error on the real transition
        x = torch.cat([norm("obs_norm", obs), norm("action_norm", action)], -1)
        mean, _ = _gaussian_mlp(self.transition, x, shared=True)
        err = (mean.mean(0) - norm("delta_norm", next_obs - obs)).pow(2).sum(-1)
        alpha = (self.alpha * (1.0 - err / self.Z)).clamp_min(0.0)
        s, a = next_obs, self.policy(next_obs, self.actor_target)
        states, actions = [s.expand(N, M, S)], [a.expand(N, M, A)]
        for h in range(H):
            s = self._step(s, a, shared=h == 0)
            a = self.policy(s, self.actor_target)
            states.append(s)
            actions.append(a)
        states, actions = torch.stack(states, -2), torch.stack(actions, -2)  # [N, M, H+1, F]
        s0, a0, s1 = states[:, :, :-1], actions[:, :, :-1], states[:, :, 1:]
        x = torch.cat([norm("obs_norm", s0), norm("action_norm", a0), norm("obs_norm", s1)], -1)
        mean, logvar = _gaussian_mlp(self.reward, x.reshape(-1, 2 * S + A), shared=True)
        mu, std = self.norms["reward_norm"]
        rewards = (mean + torch.randn_like(mean) * (0.5 * logvar).exp()) * std + mu
        rewards = rewards.reshape(N, N, M, H).transpose(0, 1)  # [Ni, Nj, M, H]
        logits = _ensemble_mlp(self.termination, norm("obs_norm", s1).reshape(N, M * H, S), False)
        done = torch.sigmoid(logits).reshape(N, M, H)
        q = self.critics(
            torch.cat([states[0, :, 0], s1.reshape(-1, S)]),
            torch.cat([actions[0, :, 0], actions[:, :, 1:].reshape(-1, A)]),
            self.critic_target,
        )
        K = q.shape[0]
        q0 = q[:, :M].reshape(K, 1, M, 1).expand(K, N, M, 1)
        values = torch.cat([q0, q[:, M:].reshape(K, N, M, H)], -1).transpose(0, 1)
        first = (1.0 - terminated).expand(N, M).unsqueeze(-1)  # [Ni, M, 1]
        cont = torch.cat([first, torch.cumprod(1.0 - done, -1) * first], -1)  # [Ni, M, H+1]
        discount = torch.full((H + 1,), self.gamma).cumprod(0)  # gamma^1 .. gamma^(H+1)
        terms = rewards * (discount[:H] * cont[..., :H]).unsqueeze(1)
        sums = torch.cat([terms.new_zeros(N, N, M, 1), terms.cumsum(-1)], -1)
        bootstrap = (discount * cont).unsqueeze(1) * values  # [Ni, K, M, H+1]
        candidates = reward.unsqueeze(-1) + sums.unsqueeze(2) + bootstrap.unsqueeze(1)
        var, mean = torch.var_mean(candidates, dim=(0, 1, 2), correction=0)  # [M, H+1]
        weights = 1.0 / (var + self.eps)
        weights = weights / weights.sum(-1, keepdim=True)
        return (weights * (mean - alpha.unsqueeze(-1) * var.sqrt())).sum(-1)

    # -------------------------------------------------------------------- losses
    def model_loss(self, obs, action, next_obs, reward, terminated) -> torch.Tensor:
        """Transition and reward NLL, termination cross-entropy and the log-variance bound
        penalty, each member on its own bootstrap resample."""
        M, norm = obs.shape[0], self._norm
        idx = torch.randint(M, (self.N, M))
        obs, action, next_obs = obs[idx], action[idx], next_obs[idx]
        reward, terminated = reward[idx].unsqueeze(-1), terminated[idx].unsqueeze(-1)
        x = torch.cat([norm("obs_norm", obs), norm("action_norm", action)], -1)
        mean, logvar = _gaussian_mlp(self.transition, x, shared=False)
        loss = _nll(mean, logvar, norm("delta_norm", next_obs - obs)).sum()
        xr = torch.cat([x, norm("obs_norm", next_obs)], -1)
        mean, logvar = _gaussian_mlp(self.reward, xr, shared=False)
        loss = loss + _nll(mean, logvar, norm("reward_norm", reward)).sum()
        logits = _ensemble_mlp(self.termination, norm("obs_norm", next_obs), False)
        bce = F.binary_cross_entropy_with_logits(logits, terminated, reduction="none")
        penalty = sum(g["max"].sum() - g["min"].sum() for g in (self.transition, self.reward))
        return loss + bce.mean((1, 2)).sum() + 0.01 * penalty

    def agent_losses(self, obs, action, next_obs, reward, terminated):
        """``(critic loss, actor loss)``: every critic regresses onto the RAVE target; the
        actor ascends the mean of the (detached) critics."""
        y = self.target(obs, action, next_obs, reward, terminated)
        critic_loss = (self.critics(obs, action, self.critic) - y).pow(2).sum(0).mean()
        detached = [(w.detach(), b.detach()) for w, b in self.critic]
        q = self.critics(obs, self.policy(obs, self.actor), detached)
        return critic_loss, -q.mean(0).mean()

    # -------------------------------------------------------------------- update
    @staticmethod
    def read(batch):
        """``(obs, action, next_obs, reward [M], terminated [M] as floats)`` of a batch."""
        terminated = batch["next", "terminated"].reshape(-1).to(batch["observation"].dtype)
        return (
            batch["observation"],
            batch["action"],
            batch["next", "observation"],
            batch["next", "reward"].reshape(-1),
            terminated,
        )

    def update(self, batch) -> None:
        """One world-model step, then one critic and actor step and the soft target update."""
        data = self.read(batch)
        model_loss = self.model_loss(*data)
        self.opt_model.zero_grad()
        model_loss.backward()
        self.opt_model.step()
        critic_loss, actor_loss = self.agent_losses(*data)
        self.opt_critic.zero_grad()
        self.opt_actor.zero_grad()
        (critic_loss + actor_loss).backward()
        self.opt_critic.step()
        self.opt_actor.step()
        with torch.no_grad():
            for targets, sources in self.soft_pairs:
                torch._foreach_lerp_(targets, sources, self.tau)
