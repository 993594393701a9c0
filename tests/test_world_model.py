"""World-model ensemble: batched layers against loops, normalisers, modes, learning, bootstrap."""

from __future__ import annotations

import math
import re

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import set_interaction_type

from torchrl_rave.modules import EnsembleLinear, EnsembleMLP, RunningNormalizer, WorldModelEnsemble
from torchrl_rave.modules.ensemble import GaussianEnsembleMLP
from torchrl_rave.modules.world_model import network_sizes
from torchrl_rave.objectives import WorldModelEnsembleLoss, gaussian_nll


def fit_identity(wm: WorldModelEnsemble) -> WorldModelEnsemble:
    """Marks the normalisers as fitted while keeping them the identity: +-1 rows have mean
    0 and variance 1 for the observation, action, state change and reward."""
    S, A = wm.observation_dim, wm.action_dim
    sign = torch.tensor([[-1.0], [1.0]])
    obs = sign.expand(2, S)
    wm.update_normalizers(obs, sign.expand(2, A), 2 * obs, sign)
    torch.testing.assert_close(wm.delta_norm.var, torch.ones(S))
    return wm


def small_model(S=3, A=2, N=4, width=16, **kw):
    return fit_identity(
        WorldModelEnsemble(
            S, A, num_models=N, **network_sizes((width, 3), (width, 3), (width, 3)), **kw
        )
    )


def transitions(B, S=3, A=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(B, S, generator=g)
    return TensorDict(
        observation=obs,
        action=torch.rand(B, A, generator=g) * 2 - 1,
        next=TensorDict(
            observation=obs + 0.1 * torch.randn(B, S, generator=g),
            reward=torch.randn(B, 1, generator=g),
            terminated=torch.rand(B, 1, generator=g) < 0.2,
            done=torch.zeros(B, 1, dtype=torch.bool),
            batch_size=[B],
        ),
        batch_size=[B],
    )


class TestEnsembleLayers:
    # (3, 2) and (5, 1) take the output-major weight copy (out < in), (2, 3) does not
    @pytest.mark.parametrize("fan_in,fan_out", [(3, 2), (5, 1), (2, 3)])
    @pytest.mark.parametrize("N,M", [(1, 5), (4, 7)])
    def test_linear_equals_member_loop(self, N, M, fan_in, fan_out):
        layer = EnsembleLinear(N, fan_in, fan_out)
        shared = torch.randn(M, fan_in)
        per = torch.randn(N, M, fan_in)
        out_shared, out_per = layer(shared), layer(per, per_member=True)
        for i in range(N):
            torch.testing.assert_close(out_shared[i], shared @ layer.weight[i] + layer.bias[i])
            torch.testing.assert_close(out_per[i], per[i] @ layer.weight[i] + layer.bias[i])
        # gradients reach the [N, in, out] parameter as a member loop's would
        g = torch.randn(N, M, fan_out)
        (out_per * g).sum().backward()
        for i in range(N):
            torch.testing.assert_close(layer.weight.grad[i], per[i].T @ g[i])
            torch.testing.assert_close(layer.bias.grad[i], g[i].sum(0, keepdim=True))
        assert layer.weight.shape == (N, fan_in, fan_out) and layer.weight.is_contiguous()
        assert layer.weight.grad.stride() == layer.weight.stride()
        # the matmul's operand: output-major ([N, out, in] in memory) exactly when out < in
        w = layer._matmul_weight()
        assert w.stride()[1:] == ((1, fan_in) if fan_out < fan_in else (fan_out, 1))

    def test_mlp_shared_equals_expanded_per_member(self):
        mlp = EnsembleMLP(3, 4, 2, num_cells=[8, 8])
        x = torch.randn(6, 4)
        torch.testing.assert_close(mlp(x), mlp(x.expand(3, 6, 4), per_member=True))

    def test_members_differ_after_init(self):
        wm = small_model(N=4)
        for name, p in wm.named_parameters():
            if "logvar" in name:  # the log-variance bounds start equal on purpose
                continue
            flat = p.detach().reshape(4, -1)
            for i in range(4):
                for j in range(i + 1, 4):
                    assert not torch.equal(flat[i], flat[j]), (
                        f"{name}: members {i} and {j} are equal"
                    )

    def test_bad_layout(self):
        mlp = EnsembleMLP(3, 4, 2, num_cells=[8])
        with pytest.raises(ValueError, match="per-member input"):
            mlp(torch.randn(2, 6, 4), per_member=True)
        with pytest.raises(ValueError, match="4 input features"):
            mlp(torch.randn(6, 5))
        # a layer on its own names them too (it failed inside baddbmm)
        layer = EnsembleLinear(3, 4, 2)
        with pytest.raises(ValueError, match="per-member input must have shape \\[3, M, 4\\]"):
            layer(torch.randn(2, 6, 4), per_member=True)
        with pytest.raises(ValueError, match="4 input features"):
            layer(torch.randn(6, 5))

    @pytest.mark.parametrize(
        "build,match",
        [
            (lambda: EnsembleLinear(0, 4, 2), "num_members must be an integer >= 1"),
            (lambda: EnsembleLinear(3, 0, 2), "in_features must be an integer >= 1"),  # was 1/0
            (lambda: EnsembleMLP(3, 4, 2, num_cells=[8, 0]), "num_cells must be a sequence"),
            (lambda: EnsembleMLP(3, 4, 2, num_cells=8), "num_cells must be a sequence"),
            (lambda: GaussianEnsembleMLP(3, 4, 2, [8], init_max_logvar=-20.0), "init_min_logvar"),
        ],
    )
    def test_bad_sizes_are_named(self, build, match):
        with pytest.raises(ValueError, match=match):
            build()


class TestRunningNormalizer:
    def test_streamed_equals_full_batch(self):
        x = torch.randn(1000, 3) * torch.tensor([1.0, 5.0, 0.1]) + torch.tensor([2.0, -1.0, 7.0])
        norm = RunningNormalizer(3)
        for chunk in x.split([1, 10, 300, 689]):
            norm.update(chunk)
        torch.testing.assert_close(norm.mean, x.mean(0))
        torch.testing.assert_close(norm.var, x.var(0, unbiased=False), rtol=1e-5, atol=1e-6)
        assert int(norm.count) == 1000

    def test_constant_feature_is_floored(self):
        norm = RunningNormalizer(1, min_std=1e-3)
        norm.update(torch.full((10, 1), 4.0))
        assert norm.std.item() == pytest.approx(1e-3)
        assert norm.normalize(torch.tensor([[4.0]])).item() == 0.0

    def test_inputs_beyond_float32_statistics_are_refused_and_change_nothing(self):
        """Issue 39, defect 9: inputs of 1e20 gave an infinite float32 variance, and the
        world model's parameters were NaN after one step, with no error."""
        norm = RunningNormalizer(2)
        norm.update(torch.tensor([[1.0, 2.0], [3.0, 4.0]]))
        before = {k: v.clone() for k, v in norm.state_dict().items()}
        huge = torch.tensor([[1e20, 0.0], [-1e20, 1.0]])
        with pytest.raises(ValueError, match="inputs up to 1e\\+20 .* beyond torch.float32"):
            norm.update(huge)
        for key, value in norm.state_dict().items():
            torch.testing.assert_close(value, before[key])
        norm.update(torch.tensor([[1e18, 0.0], [-1e18, 1.0]]))  # still representable
        assert torch.isfinite(norm.std).all()


class TestWorldModelEnsemble:
    @pytest.mark.parametrize("batch", [(5,), (2, 3)])
    def test_shapes(self, batch):
        wm = small_model(N=4)
        obs, act = torch.randn(*batch, 3), torch.randn(*batch, 2)
        assert wm.step(obs, act, sample=True).shape == (4, *batch, 3)
        nxt = wm.step(obs, act, sample=False)
        assert wm.step(nxt, act.expand(4, *batch, 2), sample=False, per_member=True).shape == (
            4,
            *batch,
            3,
        )
        assert wm.reward(obs, act, obs, sample=True).shape == (4, *batch, 1)
        assert wm.termination_prob(obs).shape == (4, *batch, 1)
        assert wm.mean_prediction_error(obs, act, obs).shape == batch

    def test_mean_mode_is_deterministic_and_sample_mode_matches_gaussian(self):
        torch.manual_seed(0)
        wm = small_model(S=2, A=1, N=2)
        wm.update_normalizers(
            torch.randn(100, 2) * 3,
            torch.rand(100, 1),
            torch.randn(100, 2) * 3,
            torch.randn(100) * 2,
        )
        obs, act = torch.randn(1, 2), torch.rand(1, 1)
        a, b = wm.step(obs, act, sample=False), wm.step(obs, act, sample=False)
        torch.testing.assert_close(a, b)
        mean, logvar = wm.predict_transition(obs, act)
        std_raw = (0.5 * logvar).exp() * wm.delta_norm.std
        draws = wm.step(obs.expand(20000, 2), act.expand(20000, 1), sample=True)  # [N, 20000, 2]
        torch.testing.assert_close(
            draws.mean(1), a[:, 0], atol=0.05 * std_raw.max().item() + 1e-4, rtol=0
        )
        torch.testing.assert_close(draws.std(1), std_raw[:, 0], rtol=0.03, atol=0)
        # reward: same story in reward units
        r_mean = wm.reward(obs, act, obs, sample=False)
        r_draws = wm.reward(
            obs.expand(20000, 2), act.expand(20000, 1), obs.expand(20000, 2), sample=True
        )
        _, r_logvar = wm.predict_reward(obs, act, obs)
        r_std = (0.5 * r_logvar).exp() * wm.reward_norm.std
        torch.testing.assert_close(r_draws.std(1), r_std[:, 0], rtol=0.03, atol=0)
        torch.testing.assert_close(
            r_draws.mean(1), r_mean[:, 0], atol=0.05 * r_std.max().item(), rtol=0
        )

    def test_tensordict_forward_follows_interaction_type(self):
        torch.manual_seed(0)
        wm = small_model()
        td = TensorDict(observation=torch.randn(5, 3), action=torch.randn(5, 2), batch_size=[5])
        with set_interaction_type("deterministic"):
            a, b = wm(td.clone()), wm(td.clone())
        torch.testing.assert_close(a["next", "observation"], b["next", "observation"])
        torch.testing.assert_close(
            a["next", "observation"], wm.step(td["observation"], td["action"], sample=False)
        )
        with set_interaction_type("random"):
            c = wm(td.clone())
        assert not torch.allclose(a["next", "observation"], c["next", "observation"])
        assert a.batch_size == (4, 5)

    def test_normalizers_in_state_dict_and_round_trip(self, tmp_path):
        wm = small_model()
        batch = transitions(64)
        wm.update_normalizers_from(batch)
        sd = wm.state_dict()
        for name in (
            "obs_norm.mean",
            "obs_norm.var",
            "delta_norm.mean",
            "reward_norm.var",
            "action_norm.count",
        ):
            assert name in sd
        torch.save(sd, tmp_path / "wm.pt")
        other = small_model()
        other.load_state_dict(torch.load(tmp_path / "wm.pt"))
        torch.testing.assert_close(
            other.step(batch["observation"], batch["action"], sample=False),
            wm.step(batch["observation"], batch["action"], sample=False),
        )

    def test_from_specs(self):
        from torchrl.data import Bounded, Composite, Unbounded

        wm = WorldModelEnsemble.from_specs(
            Composite(observation=Unbounded(shape=(11,))),
            Bounded(-1, 1, shape=(3,)),
            num_models=2,
            transition_cells=8,
            reward_cells=8,
            termination_cells=8,
        )
        assert (wm.observation_dim, wm.action_dim, wm.num_models) == (11, 3, 2)
        with pytest.raises(ValueError, match="pixels"):
            WorldModelEnsemble.from_specs(
                Composite(observation=Unbounded(shape=(11,))),
                Bounded(-1, 1, shape=(3,)),
                observation_key="pixels",
            )

    def test_paper_size_follows_paper_depths_and_steve_widths(self):
        wm = WorldModelEnsemble(4, 2, size="paper")
        assert wm.num_models == 4
        # 8 FC layers for the transition model: 7 trunk layers + the mean/logvar heads
        assert len(wm.transition.trunk.layers) == 7 and wm.transition.mean_head.in_features == 512
        assert (
            len(wm.reward_model.trunk.layers) == 3 and wm.reward_model.mean_head.in_features == 128
        )
        assert len(wm.termination.layers) == 4 and wm.termination.layers[0].out_features == 128

    def test_cpu_size_is_the_default_and_arguments_override_it(self):
        wm = WorldModelEnsemble(4, 2)
        # 4 FC layers for the transition model: 3 trunk layers + the heads, width 64
        assert len(wm.transition.trunk.layers) == 3 and wm.transition.mean_head.in_features == 64
        assert (
            len(wm.reward_model.trunk.layers) == 2 and wm.reward_model.mean_head.in_features == 64
        )
        assert len(wm.termination.layers) == 3 and wm.termination.layers[0].out_features == 64
        wide = WorldModelEnsemble(4, 2, size="paper", transition_cells=32)
        assert wide.transition.mean_head.in_features == 32
        assert len(wide.transition.trunk.layers) == 7  # the paper's depth stays
        with pytest.raises(ValueError, match="size must be one of"):
            WorldModelEnsemble(4, 2, size="huge")

    def test_training_before_any_normaliser_update_is_refused(self):
        wm = WorldModelEnsemble(3, 2)
        assert not wm.normalizers_fitted
        with pytest.raises(RuntimeError, match="normalisers were never updated"):
            WorldModelEnsembleLoss(wm)(transitions(8))
        wm.update_normalizers_from(transitions(8))
        assert wm.normalizers_fitted
        WorldModelEnsembleLoss(wm)(transitions(8))
        # statistics loaded from a trained model count as fitted
        fresh = WorldModelEnsemble(3, 2)
        fresh.load_state_dict(wm.state_dict())
        assert fresh.normalizers_fitted

    @pytest.mark.parametrize("bad", [0, -1, 2.5])
    def test_bad_ensemble_size(self, bad):
        with pytest.raises(ValueError, match="num_models"):
            WorldModelEnsemble(3, 1, num_models=bad)

    def test_size_mismatch_is_named(self):
        wm = small_model()
        with pytest.raises(ValueError, match="observation of size 3"):
            wm.step(torch.randn(4, 5), torch.randn(4, 2), sample=False)
        with pytest.raises(ValueError, match="action of size 2"):
            wm.step(torch.randn(4, 3), torch.randn(4, 1), sample=False)


class TestWorldModelLoss:
    def test_nll_formula(self):
        mean, logvar, x = torch.tensor([1.0]), torch.tensor([0.5]), torch.tensor([2.0])
        expected = torch.distributions.Normal(mean, (0.5 * logvar).exp()).log_prob(x).neg()
        torch.testing.assert_close(gaussian_nll(mean, logvar, x), expected)

    def test_loss_terms_with_seed_dims_equal_each_seed_alone_and_a_hand_loop(self):
        """The functional core takes ``[*S, N, B, F]``: each seed's slice gives what the
        seed's tensors give alone, and the members' sum is a loop over members by hand."""
        from torchrl_rave.objectives.world_model_loss import world_model_loss_terms

        torch.manual_seed(0)
        S, N, B, D = 3, 4, 5, 2

        def parts(*lead):
            return (
                (torch.randn(*lead, N, B, D), torch.randn(*lead, N, B, D)), torch.randn(*lead, N, B, D),
                (torch.randn(*lead, N, B, 1), torch.randn(*lead, N, B, 1)), torch.randn(*lead, N, B, 1),
                torch.randn(*lead, N, B, 1), torch.randint(0, 2, (*lead, N, B, 1)).float(),
                (torch.randn(*lead), torch.randn(*lead)),
            )  # fmt: skip

        args = parts(S)
        coeffs = dict(reward_coeff=0.5, termination_coeff=2.0, logvar_bound_coeff=0.1)
        group = world_model_loss_terms(*args, **coeffs)
        for s in range(S):
            one = world_model_loss_terms(
                *[tuple(t[s] for t in a) if isinstance(a, tuple) else a[s] for a in args], **coeffs
            )
            for key, value in one.items():
                torch.testing.assert_close(group[key][s], value, msg=key)
        (mean, logvar), target = args[0], args[1]
        (r_mean, r_logvar), r_target, logits, done, (tb, rb) = (
            args[2],
            args[3],
            args[4],
            args[5],
            args[6],
        )
        for s in range(S):
            nll = sum(gaussian_nll(mean[s, n], logvar[s, n], target[s, n]).mean() for n in range(N))
            r_nll = sum(gaussian_nll(r_mean[s, n], r_logvar[s, n], r_target[s, n]).mean()
                        for n in range(N))  # fmt: skip
            bce = sum(torch.nn.functional.binary_cross_entropy_with_logits(logits[s, n], done[s, n])
                      for n in range(N))  # fmt: skip
            torch.testing.assert_close(group["loss_transition"][s], nll + 0.1 * tb[s])
            torch.testing.assert_close(group["loss_reward"][s], 0.5 * (r_nll + 0.1 * rb[s]))
            torch.testing.assert_close(group["loss_termination"][s], 2.0 * bce)
            hits = ((logits[s] > 0).float() == done[s]).float().mean()
            torch.testing.assert_close(group["termination_accuracy"][s], hits)

    def test_bootstrap_indices_independent_per_member(self):
        torch.manual_seed(0)
        loss = WorldModelEnsembleLoss(small_model(N=4))
        idx = loss.bootstrap_indices(256)
        assert idx.shape == (4, 256)
        for i in range(4):
            # a bootstrap resample repeats rows (about 63% unique) ...
            assert 0.5 < idx[i].unique().numel() / 256 < 0.75
            for j in range(i + 1, 4):
                # ... and no two members share their resample
                assert (idx[i] != idx[j]).float().mean() > 0.9

    @pytest.mark.parametrize("bootstrap", [True, False])
    def test_members_train_on_different_samples(self, bootstrap):
        torch.manual_seed(0)
        wm = small_model(N=3)
        with torch.no_grad():  # make every member identical, then see whether the updates split
            for p in wm.parameters():
                p.copy_(p[:1].expand_as(p))
        loss = WorldModelEnsembleLoss(wm, bootstrap=bootstrap)
        out = loss(transitions(128))
        (out["loss_transition"] + out["loss_reward"] + out["loss_termination"]).backward()
        grad = wm.transition.trunk.layers[0].weight.grad
        same = torch.allclose(grad[0], grad[1]) and torch.allclose(grad[1], grad[2])
        assert same != bootstrap

    def test_logs_and_errors(self):
        loss = WorldModelEnsembleLoss(small_model())
        out = loss(transitions(32))
        for key in (
            "transition_nll",
            "transition_mse",
            "reward_nll",
            "reward_mse",
            "termination_bce",
        ):
            assert torch.isfinite(out[key]) and out[key] > 0
        bad = transitions(32)
        bad["next", "observation"][3, 1] = float("nan")
        with pytest.raises(ValueError, match=r"next.*observation.*NaN"):
            loss(bad)
        with pytest.raises(ValueError, match="observation"):
            loss(transitions(32, S=4))
        # without the finiteness check (data checked upstream) NaN flows through
        unchecked = WorldModelEnsembleLoss(loss.world_model, check_finite=False)
        assert torch.isnan(unchecked(bad)["transition_mse"])
        with pytest.raises(ValueError, match="observation"):  # shapes are still checked
            unchecked(transitions(32, S=4))


class TestLearnsLinearGaussianSystem:
    """s' = A s + B a + sigma * eps: the mean, the aleatoric std and the epistemic spread."""

    S, Adim = 2, 1
    A = torch.tensor([[0.9, 0.2], [-0.1, 0.8]])
    Bm = torch.tensor([[0.5], [-0.3]])
    sigma = torch.tensor([0.1, 0.3])

    def data(self, n, seed):
        g = torch.Generator().manual_seed(seed)
        obs = torch.randn(n, self.S, generator=g)
        act = torch.rand(n, self.Adim, generator=g) * 2 - 1
        nxt = obs @ self.A.T + act @ self.Bm.T + self.sigma * torch.randn(n, self.S, generator=g)
        rew = (obs**2).sum(-1, keepdim=True)
        return TensorDict(
            observation=obs,
            action=act,
            next=TensorDict(
                observation=nxt,
                reward=rew,
                terminated=torch.zeros(n, 1, dtype=torch.bool),
                batch_size=[n],
            ),
            batch_size=[n],
        )

    def train(self, data, steps, seed):
        torch.manual_seed(seed)
        sizes = network_sizes(transition=(64, 3), reward=(16, 2), termination=(8, 2))
        wm = WorldModelEnsemble(self.S, self.Adim, num_models=4, **sizes)
        wm.update_normalizers_from(data)
        loss = WorldModelEnsembleLoss(wm)
        opt = torch.optim.Adam(wm.parameters(), lr=3e-3)
        n = data.shape[0]
        for _ in range(steps):
            batch = data[torch.randint(n, (min(n, 256),))]
            out = loss(batch)
            opt.zero_grad()
            (out["loss_transition"] + out["loss_reward"] + out["loss_termination"]).backward()
            opt.step()
        return wm

    def test_mean_and_aleatoric_std(self):
        wm = self.train(self.data(4000, seed=0), steps=1500, seed=0)
        test = self.data(2000, seed=1)
        obs, act = test["observation"], test["action"]
        with torch.no_grad():
            mean, logvar = wm.predict_transition(obs, act)
            pred_next = obs + wm.delta_norm.denormalize(mean)  # [N, B, S]
            pred_std = (0.5 * logvar).exp() * wm.delta_norm.std
        true_mean = obs @ self.A.T + act @ self.Bm.T
        # mean: within a fifth of the noise level on average
        err = (pred_next.mean(0) - true_mean).abs().mean(0)
        assert (err < 0.2 * self.sigma).all(), err
        # aleatoric std: within 10% of the true noise, per dimension
        std = pred_std.mean((0, 1))
        assert ((std - self.sigma).abs() / self.sigma < 0.10).all(), std

    def test_epistemic_spread_shrinks_with_data(self):
        test = self.data(1000, seed=2)

        def spread(n):
            wm = self.train(self.data(n, seed=3), steps=600, seed=4)
            with torch.no_grad():
                mean, _ = wm.predict_transition(test["observation"], test["action"])
                return (mean * wm.delta_norm.std).var(0, unbiased=False).mean().item()

        small, large = spread(40), spread(4000)
        assert large < 0.5 * small, (small, large)


class TestBadInput:
    """Issue 15, defect 10: bad batches are refused by name, not deep inside torch."""

    def setup_method(self):
        from test_value_expansion import batch, world_model

        self.model = world_model(3)
        self.data = batch(B=6)
        self.model.update_normalizers_from(self.data)
        self.loss = WorldModelEnsembleLoss(self.model)

    def test_missing_action(self):
        with pytest.raises(ValueError, match="no entry 'action'"):
            self.loss(self.data.exclude("action"))

    def test_float64_in_the_loss_and_the_normalisers_alike(self):
        # the loss failed in baddbmm, the normalisers took float64 silently
        wrong = self.data.to(torch.float64)
        with pytest.raises(ValueError, match="'observation' is torch.float64 but the model"):
            self.loss(wrong)
        before = self.model.obs_norm.count.clone()
        with pytest.raises(ValueError, match="'observation' is torch.float64 but the model"):
            self.model.update_normalizers_from(wrong)
        assert torch.equal(self.model.obs_norm.count, before)  # nothing merged

    @pytest.mark.parametrize("key", ["observation", ("next", "reward")])
    def test_nan_in_the_normalisers_input_is_named(self, key):
        # was "inputs up to nan in magnitude ... beyond torch.float32's range"
        bad = self.data.clone()
        bad[key][1] = math.nan
        before = self.model.obs_norm.count.clone()
        with pytest.raises(ValueError, match=re.escape(f"entry {key!r} holds NaN")):
            self.model.update_normalizers_from(bad)
        assert torch.equal(self.model.obs_norm.count, before)  # nothing merged
        with pytest.raises(ValueError, match="inputs hold NaN or infinite"):
            self.model.obs_norm.update(torch.full((2, self.model.observation_dim), math.inf))

    def test_integer_rewards_and_a_model_step_without_action_or_in_float64(self):
        """The probes: int64 rewards were taken silently; a model step without an action,
        or in float64, ended in unrelated errors."""
        bad = self.data.clone()
        bad["next", "reward"] = bad["next", "reward"].round().long()
        with pytest.raises(ValueError, match="'reward'\\) is torch.int64, expected a floating"):
            self.loss(bad)
        with pytest.raises(ValueError, match="no entry 'action'"):
            self.model(self.data.exclude("action"))
        with pytest.raises(ValueError, match="'observation' is torch.float64 but the model"):
            self.model(self.data.to(torch.float64))

    def test_inputs_too_large_for_float32_are_named(self):
        big = self.data.clone()
        big["observation"] = big["observation"] * 1e20
        with pytest.raises(ValueError, match="WorldModelEnsembleLoss: the losses .* not finite"):
            self.loss(big)

    def test_empty_batch(self):
        # failed inside random_ when drawing the bootstrap indices
        with pytest.raises(ValueError, match="WorldModelEnsembleLoss got an empty batch"):
            self.loss(self.data[:0])

    def test_a_double_model_takes_double_input(self):
        model = self.model.to(torch.float64)
        out = WorldModelEnsembleLoss(model)(self.data.to(torch.float64))
        assert out["loss_transition"].dtype == torch.float64
        assert torch.isfinite(out["loss_transition"])


@pytest.mark.parametrize("shape", [(3, 4), (4, 3)])
def test_world_model_loss_takes_any_batch_shape(shape):
    """Issue 15, deliverable 3: [B1, B2] batches give the flattened batch's losses (the
    bootstrap draws from the flattened rows)."""
    from test_value_expansion import batch, world_model

    model = world_model(3)
    flat = batch(B=12)
    model.update_normalizers_from(flat)
    outs = []
    for data in (flat, flat.reshape(shape)):
        torch.manual_seed(5)
        outs.append(WorldModelEnsembleLoss(model)(data))
    for key in ("loss_transition", "loss_reward", "loss_termination"):
        torch.testing.assert_close(outs[1][key], outs[0][key])


class TestStackedSeeds:
    """A seed group's world models as one module with the seed leading every parameter:
    each seed's outputs against its own model's, seed by seed."""

    S, N, D, A = 3, 4, 5, 2

    def models(self):
        from torchrl_rave.trainers.seed_group import _stacked

        models = []
        for s in range(self.S):
            torch.manual_seed(s)
            wm = WorldModelEnsemble(self.D, self.A, num_models=self.N, transition_cells=16,
                                    reward_cells=16, termination_cells=16)  # fmt: skip
            g = torch.Generator().manual_seed(10 + s)
            wm.update_normalizers(torch.randn(32, self.D, generator=g) * (1 + s),
                                  torch.rand(32, self.A, generator=g),
                                  torch.randn(32, self.D, generator=g) + s,
                                  torch.randn(32, generator=g) * (2 + s))  # fmt: skip
            models.append(wm)
        return models, _stacked(models, [])

    def seeds(self, fn):
        return torch.stack([fn(s) for s in range(self.S)])

    @pytest.mark.parametrize("grad", [True, False])
    def test_every_call_is_each_seeds_own(self, grad):
        models, stacked = self.models()
        assert stacked.seeds == self.S and models[0].seeds is None
        g = torch.Generator().manual_seed(0)
        S, N, D, A = self.S, self.N, self.D, self.A
        obs, act = torch.randn(S, 2, 6, D, generator=g), torch.rand(S, 2, 6, A, generator=g)
        obs_m, act_m = torch.randn(S, N, 6, D, generator=g), torch.rand(S, N, 6, A, generator=g)
        close = torch.testing.assert_close
        with torch.set_grad_enabled(grad):
            close(
                stacked.step(obs, act, sample=False),
                self.seeds(lambda s: models[s].step(obs[s], act[s], sample=False)),
            )
            close(
                stacked.step(obs_m, act_m, sample=False, per_member=True),
                self.seeds(
                    lambda s: models[s].step(obs_m[s], act_m[s], sample=False, per_member=True)
                ),
            )
            close(
                stacked.reward(obs, act, obs + 1, sample=False),
                self.seeds(lambda s: models[s].reward(obs[s], act[s], obs[s] + 1, sample=False)),
            )
            close(
                stacked.termination_prob(obs_m, per_member=True),
                self.seeds(lambda s: models[s].termination_prob(obs_m[s], per_member=True)),
            )
            close(stacked.mean_prediction_error(obs[:, 0], act[:, 0], obs[:, 1]),
                  self.seeds(lambda s: models[s].mean_prediction_error(
                      obs[s, 0], act[s, 0], obs[s, 1])))  # fmt: skip
            loss = WorldModelEnsembleLoss(models[0], reward_coeff=0.5)
            r, d = torch.randn(S, N, 6, 1, generator=g), (torch.rand(S, N, 6, 1) < 0.3).float()
            out = loss.loss_terms(stacked, obs_m, act_m, obs_m + 1, r, d)
            for s in range(S):
                one = loss.loss_terms(models[s], obs_m[s], act_m[s], obs_m[s] + 1, r[s], d[s])
                for key, value in one.items():
                    close(out[key][s], value, msg=key)

    def test_its_draw_and_its_refusals(self):
        models, stacked = self.models()
        obs, act = torch.randn(self.S, 4, self.D), torch.rand(self.S, 4, self.A)
        stacked.draw = lambda mean, logvar, sample: torch.zeros_like(mean)  # the delta's mean
        torch.testing.assert_close(
            stacked.step(obs, act, sample=True),
            self.seeds(lambda s: (obs[s] + models[s].delta_norm.mean).expand(self.N, 4, self.D)),
        )
        with pytest.raises(
            ValueError, match=r"observation must lead with the number of seeds \[3\]"
        ):
            stacked.step(obs[:2], act[:2], sample=False)
        with pytest.raises(
            ValueError,
            match=r"per-member input must have shape \[3, 4, M, 7\]",
        ):
            stacked.transition(torch.randn(3, 2, 4, 7), per_member=True)
        with pytest.raises(
            ValueError, match=r"per-member observation must lead with the ensemble size \[4\]"
        ):  # one model's layout, for comparison
            models[0].step(obs[0, :3], act[0, :3], sample=False, per_member=True)
        with pytest.raises(RuntimeError, match="each learner's own normaliser"):
            stacked.obs_norm.update(obs)
        with pytest.raises(RuntimeError, match="not through forward"):
            stacked(TensorDict(observation=obs, action=act, batch_size=obs.shape[:-1]))
