"""The value-expansion math against naive Python loops over (i, j, k) and H."""

from __future__ import annotations

import math

import pytest
import torch

from torchrl_rave.objectives import functional as VF


def naive_candidates(reward, rewards, values, terminated, done_prob, gamma):
    """T_H(i,j,k) written straight from the paper, one scalar at a time.

    reward [B], rewards [Ni, Nj, B, H], values [Ni, K, B, H+1], terminated [B],
    done_prob [Ni, B, H]  ->  dict[(i, j, k, b, H)] = float
    """
    Ni, Nj, B, Hmax = rewards.shape
    K = values.shape[1]
    out = {}
    for i in range(Ni):
        for j in range(Nj):
            for k in range(K):
                for b in range(B):
                    for H in range(Hmax + 1):
                        c = 1.0 - float(terminated[b])  # c_{t,t+1}
                        total = float(reward[b])
                        for h in range(1, H + 1):
                            total += gamma**h * c * float(rewards[i, j, b, h - 1])
                            c *= 1.0 - float(done_prob[i, b, h - 1])  # c_{t,t+h+1}
                        total += gamma ** (H + 1) * c * float(values[i, k, b, H])
                        out[i, j, k, b, H] = total
    return out


def naive_moments(cands, Ni, Nj, K, B, Hmax):
    mean = torch.zeros(B, Hmax + 1, dtype=torch.float64)
    var = torch.zeros(B, Hmax + 1, dtype=torch.float64)
    n = Ni * Nj * K
    for b in range(B):
        for H in range(Hmax + 1):
            xs = [cands[i, j, k, b, H] for i in range(Ni) for j in range(Nj) for k in range(K)]
            m = sum(xs) / n
            mean[b, H] = m
            var[b, H] = sum((x - m) ** 2 for x in xs) / n
    return mean, var


def naive_mix(mean, var, alpha, eps):
    B, H1 = mean.shape
    out = torch.zeros(B, dtype=torch.float64)
    for b in range(B):
        a = float(alpha[b]) if torch.is_tensor(alpha) else alpha
        ws = [1.0 / (float(var[b, H]) + eps) for H in range(H1)]
        clbs = [float(mean[b, H]) - a * math.sqrt(float(var[b, H])) for H in range(H1)]
        out[b] = sum(w * c for w, c in zip(ws, clbs, strict=True)) / sum(ws)
    return out


def random_case(Ni, Nj, K, B, Hmax, seed):
    g = torch.Generator().manual_seed(seed)
    reward = torch.randn(B, generator=g, dtype=torch.float64)
    rewards = torch.randn(Ni, Nj, B, Hmax, generator=g, dtype=torch.float64)
    values = 10 * torch.randn(Ni, K, B, Hmax + 1, generator=g, dtype=torch.float64)
    terminated = (torch.rand(B, generator=g) < 0.3).to(torch.float64)
    done_prob = torch.rand(Ni, B, Hmax, generator=g, dtype=torch.float64) * 0.5
    return reward, rewards, values, terminated, done_prob


CASES = [
    # (Ni, Nj, K, B, Hmax)
    (1, 1, 1, 3, 0),
    (2, 3, 1, 4, 1),
    (4, 4, 4, 5, 3),
    (3, 2, 2, 2, 4),
]


class TestCandidateTargets:
    @pytest.mark.parametrize("Ni,Nj,K,B,Hmax", CASES)
    def test_candidates_equal_naive_loop(self, Ni, Nj, K, B, Hmax):
        reward, rewards, values, terminated, done_prob = random_case(
            Ni, Nj, K, B, Hmax, seed=Ni + 10 * Hmax
        )
        gamma = 0.9
        cont = VF.continuation_weights(terminated, done_prob)
        T = VF.candidate_targets(reward, rewards, values, cont, gamma)
        assert T.shape == (Ni, Nj, K, B, Hmax + 1)
        ref = naive_candidates(reward, rewards, values, terminated, done_prob, gamma)
        for idx, x in ref.items():
            assert T[idx].item() == pytest.approx(x, rel=1e-12, abs=1e-12)

    def test_extra_batch_dimensions(self):
        Ni, Nj, K, Hmax = 2, 3, 2, 2
        reward, rewards, values, terminated, done_prob = random_case(Ni, Nj, K, 12, Hmax, seed=3)
        cont = VF.continuation_weights(terminated, done_prob)
        flat = VF.candidate_targets(reward, rewards, values, cont, 0.8)
        cont2 = VF.continuation_weights(terminated.view(3, 4), done_prob.view(Ni, 3, 4, Hmax))
        shaped = VF.candidate_targets(
            reward.view(3, 4),
            rewards.view(Ni, Nj, 3, 4, Hmax),
            values.view(Ni, K, 3, 4, Hmax + 1),
            cont2,
            0.8,
        )
        torch.testing.assert_close(shaped.reshape(flat.shape), flat)

    def test_terminal_transition_gives_reward_only(self):
        reward, rewards, values, _, done_prob = random_case(3, 3, 2, 4, 3, seed=5)
        terminated = torch.ones(4, dtype=torch.float64)
        T = VF.candidate_targets(
            reward, rewards, values, VF.continuation_weights(terminated, done_prob), 0.99
        )
        torch.testing.assert_close(T, reward.view(1, 1, 1, 4, 1).expand_as(T))

    def test_certain_model_termination_cuts_later_terms(self):
        reward, rewards, values, _, _ = random_case(2, 2, 2, 3, 3, seed=6)
        terminated = torch.zeros(3, dtype=torch.float64)
        done_prob = torch.ones(2, 3, 3, dtype=torch.float64)  # every imagined state is terminal
        gamma = 0.9
        T = VF.candidate_targets(
            reward, rewards, values, VF.continuation_weights(terminated, done_prob), gamma
        )
        first_step = reward.view(1, 1, 1, 3) + gamma * rewards[:, :, None, :, 0]
        for H in range(1, 4):
            torch.testing.assert_close(T[..., H], first_step.expand_as(T[..., H]))


class TestTargets:
    @pytest.mark.parametrize("Ni,Nj,K,B,Hmax", CASES)
    @pytest.mark.parametrize("alpha", [0.0, 1.5, "per-sample"])
    def test_steve_rave_equal_naive(self, Ni, Nj, K, B, Hmax, alpha):
        reward, rewards, values, terminated, done_prob = random_case(
            Ni, Nj, K, B, Hmax, seed=Nj + 7 * K
        )
        gamma, eps = 0.95, 1e-8
        if alpha == "per-sample":
            alpha = torch.rand(B, dtype=torch.float64) * 2
        T = VF.candidate_targets(
            reward, rewards, values, VF.continuation_weights(terminated, done_prob), gamma
        )
        mean, var = VF.horizon_moments(T)
        ref = naive_candidates(reward, rewards, values, terminated, done_prob, gamma)
        ref_mean, ref_var = naive_moments(ref, Ni, Nj, K, B, Hmax)
        torch.testing.assert_close(mean, ref_mean)
        torch.testing.assert_close(var, ref_var)
        for got, want in zip(VF.horizon_moments(T.clone(), two_pass=True), (ref_mean, ref_var),
                             strict=True):  # fmt: skip
            torch.testing.assert_close(got, want)
        target, weights = VF.expansion_target(
            mean, var, mix="inverse_variance", alpha=alpha, eps=eps
        )
        torch.testing.assert_close(target, naive_mix(ref_mean, ref_var, alpha, eps))
        torch.testing.assert_close(weights.sum(-1), torch.ones(B, dtype=torch.float64))

    def test_mve_is_fixed_horizon_mean(self):
        reward, rewards, values, terminated, done_prob = random_case(3, 3, 3, 4, 3, seed=9)
        T = VF.candidate_targets(
            reward, rewards, values, VF.continuation_weights(terminated, done_prob), 0.9
        )
        mean, var = VF.horizon_moments(T)
        for H in range(4):
            target, weights = VF.expansion_target(mean, var, mix="fixed", horizon=H)
            torch.testing.assert_close(target, mean[:, H])
            assert weights[:, H].eq(1).all() and weights.sum(-1).eq(1).all()

    def test_inverse_variance_prefers_low_variance_horizon(self):
        mean = torch.tensor([[0.0, 10.0]])
        var = torch.tensor([[100.0, 1.0]])
        target, w = VF.expansion_target(mean, var, mix="inverse_variance")
        assert w[0, 1] == pytest.approx(100 / 101)
        assert target.item() == pytest.approx(1000 / 101)

    def test_unknown_mix(self):
        with pytest.raises(ValueError, match="mix"):
            VF.expansion_target(torch.zeros(1, 2), torch.ones(1, 2), mix="median")


class TestAdaptiveAlphaFunction:
    @pytest.mark.parametrize("alpha,Z", [(1.5, 1.0), (2.0, 0.5), (0.0, 1.0)])
    def test_matches_formula(self, alpha, Z):
        err = torch.tensor([0.0, 0.1, 0.5, 1.0, 4.0])
        expected = torch.tensor([max(0.0, alpha * (1 - e / Z)) for e in err.tolist()])
        torch.testing.assert_close(VF.adaptive_alpha(err, alpha, Z), expected)


class TestRollout:
    def test_rollout_calls_members_from_shared_start(self):
        calls = []

        def step(s, a, per_member):
            calls.append((tuple(s.shape), per_member))
            base = s if per_member else s.expand(2, *s.shape)
            return base + a + torch.tensor([1.0, 2.0]).view(2, 1, 1)

        states, actions = VF.imagined_rollout(
            torch.zeros(3, 1), lambda s: torch.ones_like(s), step, 2, 2
        )
        assert calls == [((3, 1), False), ((2, 3, 1), True)]
        # member 0 moves by 1 + 1 per step, member 1 by 1 + 2
        torch.testing.assert_close(states[0, 0, :, 0], torch.tensor([0.0, 2.0, 4.0]))
        torch.testing.assert_close(states[1, 0, :, 0], torch.tensor([0.0, 3.0, 6.0]))
        assert actions.shape == (2, 3, 3, 1)


class TestValueExpansionTarget:
    @pytest.mark.parametrize("mix", ["inverse_variance", "fixed"])
    def test_seed_dimensions_equal_each_seed_alone(self, mix):
        """``value_expansion_target`` with a leading seed dimension (callables that take
        it) gives each seed what the seed's own callables give without it."""
        torch.manual_seed(0)
        S, N, K, M, D, A, H = 3, 2, 2, 4, 2, 1, 2
        Wp, Wt = torch.randn(S, D, A), torch.randn(S, N, D + A, D) * 0.3
        Wr, Wd, Wq = torch.randn(S, N, 2 * D + A), torch.randn(S, N, D), torch.randn(S, K, D + A)

        def nets(s):  # seed s's networks, for inputs without the seed; s=None: all seeds
            def pick(w):
                return w if s is None else w[s]

            lead = 1 if s is None else 0

            def policy(x):
                w = pick(Wp)
                return torch.tanh(
                    x @ (w if s is not None else w.view(S, *[1] * (x.dim() - 3), D, A))
                )

            def step(x, a, per_member):  # [*L, M, D] shared or [*L, N, M, D]
                xa = torch.cat([x, a], -1)
                if not per_member:  # one copy for the members: [*L, 1, M, .]
                    x, xa = x.unsqueeze(-3), xa.unsqueeze(-3)
                return x + xa @ pick(Wt)

            def imagined_reward(x, a, x2):  # [*L, Ni, M, H, .] -> [*L, Nj, Ni, M, H]
                z = torch.cat([x, a, x2], -1).unsqueeze(-5)  # a reward member axis
                w = pick(Wr).view(*[S] * lead, N, 1, 1, 1, 2 * D + A)
                return (z * w).sum(-1)

            def termination_prob(x2):  # [*L, Ni, M, H, D] -> [*L, Ni, M, H]
                return torch.sigmoid((x2 * pick(Wd).view(*[S] * lead, N, 1, 1, D)).sum(-1))

            def critic(x, a):  # [*L, R, .] -> [*L, K, R]
                return (torch.cat([x, a], -1) @ pick(Wq).mT).mT

            return dict(policy=policy, step=step, imagined_reward=imagined_reward,
                        termination_prob=termination_prob, critic=critic)  # fmt: skip

        nxt, reward = torch.randn(S, M, D), torch.randn(S, M)
        terminated = torch.tensor([[False, True, False, False]] * S)
        common = dict(num_members=N, horizon=H, gamma=0.9, mix=mix, alpha=0.5)
        group = VF.value_expansion_target(nxt, reward, terminated, **nets(None), **common)
        for s in range(S):
            alone = VF.value_expansion_target(nxt[s], reward[s], terminated[s], **nets(s), **common)
            for got, want in zip(group, alone, strict=True):
                torch.testing.assert_close(got[s], want)


class TestSoftTarget:
    """A stochastic policy's soft value-expansion target against a float64 loop by hand."""

    N, K, M, D, A = 3, 2, 4, 2, 1

    def networks(self):
        g = torch.Generator().manual_seed(0)

        def rand(*shape):
            return torch.randn(*shape, generator=g, dtype=torch.float64)

        N, K, D, A = self.N, self.K, self.D, self.A
        Wp, Wt, Wr = rand(D, A), rand(N, D + A, D) * 0.3, rand(N, 2 * D + A)
        Wd, Wq = rand(N, D), rand(K, D + A)

        def policy(s):  # a sampled action and its log-probability, any leading dims
            return torch.tanh(s @ Wp), -0.1 * s.pow(2).sum(-1)

        def step(s, a, per_member):
            xa = torch.cat([s, a], -1)
            if not per_member:
                s, xa = s.unsqueeze(0), xa.unsqueeze(0)
            return s + torch.tanh(xa @ Wt)

        def imagined_reward(s, a, s2):  # [Ni, M, H, .] -> [Nj, Ni, M, H]
            return torch.einsum("imhf,jf->jimh", torch.cat([s, a, s2], -1), Wr)

        def termination_prob(s2):  # [Ni, M, H, D] -> [Ni, M, H]
            return torch.sigmoid(torch.einsum("imhd,id->imh", s2, Wd))

        def critic(s, a):  # [R, .] -> [K, R]
            return (torch.cat([s, a], -1) @ Wq.mT).mT

        calls = dict(policy=policy, step=step, imagined_reward=imagined_reward,
                     termination_prob=termination_prob, critic=critic)  # fmt: skip
        return calls, (Wt, Wr, Wd, Wq)

    def by_hand(self, nets, weights, nxt, reward, terminated, H, gamma, temp, alpha):
        """Every candidate T_H(i, j, k) by loops, then the moments and the RAVE mix."""
        policy = nets["policy"]
        Wt, Wr, Wd, Wq = weights
        N, K, M = self.N, self.K, self.M
        targets = []
        for b in range(M):
            cands = [[] for _ in range(H + 1)]
            for i in range(N):
                s, traj = nxt[b], []
                for _ in range(H + 1):
                    a, lp = policy(s)
                    traj.append((s, a, lp))
                    s = s + torch.tanh(torch.cat([s, a]) @ Wt[i])
                for j in range(N):
                    for k in range(K):
                        for h_max in range(H + 1):
                            total, c = reward[b].clone(), 1.0 - float(terminated[b])
                            for h in range(1, h_max + 2):  # steps t+1 .. t+H+1
                                if h > 1:  # c_{t,t+h} = c_{t,t+h-1} (1 - p_i(s~_{t+h}))
                                    c = c * (1 - torch.sigmoid(traj[h - 1][0] @ Wd[i]))
                                s_h, a_h, lp_h = traj[h - 1]
                                if h <= h_max:  # an imagined reward and its entropy bonus
                                    r = torch.cat([s_h, a_h, traj[h][0]]) @ Wr[j]
                                    total = total + gamma**h * c * (r - temp * lp_h)
                                else:  # the bootstrap, soft
                                    q = torch.cat([s_h, a_h]) @ Wq[k]
                                    total = total + gamma**h * c * (q - temp * lp_h)
                            cands[h_max].append(total)
            T = torch.stack([torch.stack(c) for c in cands])  # [H+1, N*N*K]
            mean, var = T.mean(1), T.var(1, correction=0)
            w = 1 / (var + 1e-8)
            targets.append(((mean - alpha * var.sqrt()) * w).sum() / w.sum())
        return torch.stack(targets)

    @pytest.mark.parametrize("H", [0, 1, 3])
    def test_equals_a_loop_by_hand(self, H):
        nets, weights = self.networks()
        g = torch.Generator().manual_seed(1)
        nxt = torch.randn(self.M, self.D, generator=g, dtype=torch.float64)
        reward = torch.randn(self.M, generator=g, dtype=torch.float64)
        terminated = torch.tensor([False, True, False, False])
        target, _, _ = VF.value_expansion_target(
            nxt, reward, terminated, **nets, num_members=self.N, horizon=H, gamma=0.9,
            mix="inverse_variance", alpha=0.5, temperature=0.2,
        )  # fmt: skip
        want = self.by_hand(nets, weights, nxt, reward, terminated, H, 0.9, 0.2, 0.5)
        torch.testing.assert_close(target, want)

    def test_horizon_zero_is_sacs_soft_td0_target(self):
        """``H = 0`` with one critic (the minimum SAC takes) is ``r + gamma (1 - d)
        (Q'(s', a') - temperature log pi(a' | s'))``, a' drawn at s'."""
        nets, (_, _, _, Wq) = self.networks()
        nets["critic"] = lambda s, a: (torch.cat([s, a], -1) @ Wq.mT).mT.min(0, keepdim=True)[0]
        nxt = torch.randn(self.M, self.D, dtype=torch.float64)
        reward = torch.randn(self.M, dtype=torch.float64)
        terminated = torch.tensor([False, True, False, True])
        target, var, _ = VF.value_expansion_target(
            nxt, reward, terminated, **nets, num_members=self.N, horizon=0, gamma=0.9,
            mix="fixed", temperature=0.2,
        )  # fmt: skip
        a, log_pi = nets["policy"](nxt)
        q = (torch.cat([nxt, a], -1) @ Wq.mT).min(-1)[0]
        torch.testing.assert_close(target, reward + 0.9 * (~terminated) * (q - 0.2 * log_pi))
        assert torch.all(var == 0)

    def test_temperature_zero_or_none_is_the_deterministic_target(self):
        nets, _ = self.networks()
        nxt, reward = torch.randn(self.M, self.D, dtype=torch.float64), torch.zeros(self.M)
        terminated = torch.zeros(self.M, dtype=torch.bool)
        common = dict(num_members=self.N, horizon=2, gamma=0.9, mix="inverse_variance")
        soft = VF.value_expansion_target(
            nxt, reward.double(), terminated, **nets, **common, temperature=0.0
        )[0]
        policy = nets.pop("policy")
        plain = VF.value_expansion_target(
            nxt, reward.double(), terminated, policy=lambda s: policy(s)[0], **nets, **common
        )[0]
        torch.testing.assert_close(soft, plain)


class TestLayouts:
    """Inputs off the documented layouts are named, not broadcast. TorchRL's ``[B, 1]``
    reward and done entries broadcast without an error where sizes happen to match: with
    ``B = K = 5``, ``[5, 1]`` rewards gave candidates of the right shape in which critic
    ``k``'s row held sample ``k``'s reward, and with ``B = Ni = 2`` ``[2, 1]`` termination
    flags cut member ``i``'s rollouts by sample ``i``'s flag."""

    def layout(self, Ni=2, Nj=3, K=5, B=5, H=3):
        return (torch.zeros(B), torch.zeros(Ni, Nj, B, H), torch.ones(Ni, K, B, H + 1),
                torch.ones(Ni, B, H + 1))  # fmt: skip

    def test_a_torchrl_shaped_reward_is_named(self):
        reward, rewards, values, cont = self.layout()
        assert VF.candidate_targets(reward, rewards, values, cont, 0.9).shape == (2, 3, 5, 5, 4)
        with pytest.raises(ValueError, match=r"reward has shape \[5, 1\], expected \[5\]"):
            VF.candidate_targets(reward[:, None], rewards, values, cont, 0.9)

    @pytest.mark.parametrize(
        "which, bad, message",
        [
            ("values", torch.ones(2, 5, 5, 3), r"values has shape \[2, 5, 5, 3\], expected \[Ni"),
            ("values", torch.ones(3, 5, 5, 4), r"values has shape \[3, 5, 5, 4\]"),
            ("cont", torch.ones(2, 5, 3), r"continuation has shape \[2, 5, 3\], expected \[2, 5, 4\]"),
            ("rewards", torch.zeros(2, 3), r"imagined_rewards has shape \[2, 3\]"),
        ],
    )  # fmt: skip
    def test_other_layouts_are_named(self, which, bad, message):
        inputs = dict(zip(("reward", "rewards", "values", "cont"), self.layout(), strict=True))
        inputs[which] = bad
        with pytest.raises(ValueError, match=message):
            VF.candidate_targets(*inputs.values(), 0.9)

    def test_termination_flags_and_probabilities(self):
        probs = torch.full((2, 5, 3), 0.5)
        assert VF.continuation_weights(torch.zeros(5), probs).shape == (2, 5, 4)
        with pytest.raises(ValueError, match=r"terminated has shape \[5, 1\], expected \[5\]"):
            VF.continuation_weights(torch.zeros(5, 1), probs)

    def test_moments_alpha_and_horizon(self):
        mean, var = torch.zeros(5, 4), torch.ones(5, 4)
        with pytest.raises(ValueError, match=r"ensemble_dims=4 must lie in \[1, 3\]"):
            VF.horizon_moments(torch.zeros(2, 2, 5, 4), ensemble_dims=4)
        with pytest.raises(ValueError, match=r"alpha has shape \[5, 1\], expected \[5\]"):
            VF.confidence_lower_bound(mean, var, torch.ones(5, 1))
        with pytest.raises(ValueError, match=r"var has shape \[5, 3\]"):
            VF.expansion_target(mean, var[:, :3], mix="inverse_variance")
        # H_max = 3: horizon 5 was torch's IndexError, -1 the last horizon silently
        for horizon in (5, -1, 1.5):
            with pytest.raises(
                ValueError, match=rf"horizon={horizon} must be an integer in \[0, 3\]"
            ):
                VF.expansion_target(mean, var, mix="fixed", horizon=horizon)
        assert VF.expansion_target(mean, var, mix="fixed", horizon=3)[1][0].tolist() == [0, 0, 0, 1]

    def test_rollout_arguments(self):
        with pytest.raises(ValueError, match="horizon=-1 must be an integer >= 0"):
            VF.imagined_rollout(torch.zeros(3, 1), lambda s: s, lambda s, a, m: s, 2, -1)
        with pytest.raises(ValueError, match="num_members=0 must be an integer >= 1"):
            VF.imagined_rollout(torch.zeros(3, 1), lambda s: s, lambda s, a, m: s, 0, 2)


def test_clipped_double_q_target_is_the_naive_loop_per_seed_and_row():
    """The one-step target of K critics, plain and soft (a temperature per seed), against
    a loop over seeds and rows in float64."""
    g = torch.Generator().manual_seed(3)
    S, K, B, gamma = 3, 2, 5, 0.9
    next_q = torch.randn(S, K, B, generator=g, dtype=torch.float64)
    reward = torch.randn(S, B, generator=g, dtype=torch.float64)
    terminated = torch.rand(S, B, generator=g) < 0.3
    log_prob = torch.randn(S, B, generator=g, dtype=torch.float64)
    temperature = torch.tensor([0.1, 0.5, 2.0], dtype=torch.float64)
    plain = VF.clipped_double_q_target(next_q, reward, terminated, gamma)
    soft = VF.clipped_double_q_target(next_q, reward, terminated, gamma,
                                      next_log_prob=log_prob, temperature=temperature.view(S, 1))  # fmt: skip
    for s in range(S):
        for b in range(B):
            keep = 0.0 if terminated[s, b] else 1.0
            qs = [float(next_q[s, k, b]) for k in range(K)]
            bonus = float(temperature[s]) * float(log_prob[s, b])
            assert float(plain[s, b]) == pytest.approx(float(reward[s, b]) + gamma * keep * min(qs))
            expected = float(reward[s, b]) + gamma * keep * min(q - bonus for q in qs)
            assert float(soft[s, b]) == pytest.approx(expected)
    with pytest.raises(ValueError, match="come together"):
        VF.clipped_double_q_target(next_q, reward, terminated, gamma, next_log_prob=log_prob)


def test_td3_target_is_td3losss_target():
    """Target smoothing and the clipped double-Q target give TD3Loss's own target, with
    its smoothing noise replayed."""
    from tensordict import TensorDict
    from tensordict.nn import TensorDictModule, TensorDictSequential
    from torchrl.data import Bounded
    from torchrl.modules import MLP, TanhModule, ValueOperator
    from torchrl.objectives import TD3Loss

    torch.manual_seed(0)
    spec = Bounded(-1.0, 1.0, shape=(2,))
    actor = TensorDictSequential(
        TensorDictModule(MLP(in_features=3, out_features=2, num_cells=[8]),
                         in_keys=["observation"], out_keys=["param"]),
        TanhModule(in_keys=["param"], out_keys=["action"], spec=spec))  # fmt: skip
    critic = ValueOperator(MLP(in_features=5, out_features=1, num_cells=[8]),
                           in_keys=["observation", "action"])  # fmt: skip
    loss = TD3Loss(actor, critic, action_spec=spec, num_qvalue_nets=2, policy_noise=0.3,
                   noise_clip=0.4, loss_function="l2")  # fmt: skip
    loss.make_value_estimator(gamma=0.95)
    B = 7
    g = torch.Generator().manual_seed(1)
    terminated = torch.rand(B, 1, generator=g) < 0.3
    td = TensorDict({"observation": torch.randn(B, 3, generator=g),
                     "action": torch.rand(B, 2, generator=g) * 2 - 1,
                     ("next", "observation"): torch.randn(B, 3, generator=g) * 3,
                     ("next", "reward"): torch.randn(B, 1, generator=g),
                     ("next", "done"): terminated.clone(),
                     ("next", "terminated"): terminated}, [B])  # fmt: skip
    noise = torch.randn(B, 2, generator=g) * 3  # large: the clip and the box both act
    real = torch.randn_like
    torch.randn_like = lambda x: noise.clone()
    try:
        _, meta = loss.value_loss(td)
    finally:
        torch.randn_like = real
    with torch.no_grad():
        nxt = td["next", "observation"]
        with loss.target_actor_network_params.to_module(actor):
            next_action = actor(TensorDict({"observation": nxt}, [B]))["action"]
        next_action = VF.smoothed_target_action(next_action, noise, scale=0.3, clip=0.4,
                                                low=-1.0, high=1.0)  # fmt: skip
        qs = []
        for k in range(2):
            with loss.target_qvalue_network_params[k].to_module(critic):
                inputs = TensorDict({"observation": nxt, "action": next_action}, [B])
                qs.append(critic(inputs)["state_action_value"].squeeze(-1))
        ours = VF.clipped_double_q_target(torch.stack(qs), td["next", "reward"].squeeze(-1),
                                          terminated.squeeze(-1), 0.95)  # fmt: skip
    torch.testing.assert_close(ours, meta["target_value"].squeeze(-1))
