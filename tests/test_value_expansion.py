"""MVE / STEVE / RAVE estimators: exact cases, naive loops, TorchRL losses, call counts."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from test_world_model import small_model
from torch import nn
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, Actor, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import (
    CQLLoss,
    CrossQLoss,
    DDPGLoss,
    DiscreteSACLoss,
    IQLLoss,
    REDQLoss,
    SACLoss,
    SoftUpdate,
    TD3Loss,
    ValueEstimators,
)

from torchrl_rave import (
    EnsembleDDPGLoss,
    MVEEstimator,
    RAVEValueEstimator,
    STEVEEstimator,
    ValueExpansionEstimator,
    WorldModelEnsemble,
    make_value_expansion_estimator,
    patch_value_estimator_setter,
)
from torchrl_rave.modules import TensorCall
from torchrl_rave.objectives.target_networks import TargetNetworks

S, A = 3, 2


def world_model(N=4, seed=0):
    torch.manual_seed(seed)
    wm = small_model(S, A, N)
    g = torch.Generator().manual_seed(seed)
    wm.update_normalizers(
        torch.randn(64, S, generator=g),
        torch.rand(64, A, generator=g),
        torch.randn(64, S, generator=g),
        torch.randn(64, generator=g),
    )
    return wm


def actor_net():
    return Actor(nn.Sequential(MLP(in_features=S, out_features=A, num_cells=[16]), nn.Tanh()))


def critic_net():
    return ValueOperator(
        MLP(in_features=S + A, out_features=1, num_cells=[16]), in_keys=["observation", "action"]
    )


def batch(B=8, terminal=(), seed=1):
    g = torch.Generator().manual_seed(seed)
    terminated = torch.zeros(B, 1, dtype=torch.bool)
    for b in terminal:
        terminated[b] = True
    return TensorDict(
        observation=torch.randn(B, S, generator=g),
        action=torch.rand(B, A, generator=g) * 2 - 1,
        next=TensorDict(
            observation=torch.randn(B, S, generator=g),
            reward=torch.randn(B, 1, generator=g),
            done=terminated.clone(),
            terminated=terminated,
            batch_size=[B],
        ),
        batch_size=[B],
    )


def stochastic_actor():
    """A SAC-style actor: a TanhNormal policy over the action box."""
    body = TensorDictModule(
        nn.Sequential(MLP(in_features=S, out_features=2 * A, num_cells=[16]), NormalParamExtractor()),
        in_keys=["observation"], out_keys=["loc", "scale"],
    )  # fmt: skip
    return ProbabilisticActor(
        body, in_keys=["loc", "scale"], distribution_class=TanhNormal, spec=Bounded(-1, 1, (A,))
    )


def ddpg_loss():
    torch.manual_seed(3)
    loss = DDPGLoss(actor_net(), critic_net(), delay_actor=True, delay_value=True)
    SoftUpdate(loss, tau=0.05)
    return loss


def ensemble_loss(K=2):
    torch.manual_seed(3)
    loss = EnsembleDDPGLoss(actor_net(), critic_net(), num_value_nets=K)
    SoftUpdate(loss, tau=0.05)
    return loss


def td3_loss(K=4):
    torch.manual_seed(3)
    loss = TD3Loss(actor_net(), critic_net(), action_spec=Bounded(-1, 1, (A,)), num_qvalue_nets=K)
    SoftUpdate(loss, tau=0.05)
    return loss


def record_critic_shapes(est) -> list:
    """The shape of every critic call ``est`` makes from now on, in order."""
    shapes, original = [], est.networks.critic

    def spy(o, a, p, keys):
        out = original(o, a, p, keys)
        shapes.append(tuple(out.shape))
        return out

    est.networks.critic = spy
    return shapes


def perturb(params, scale=0.1):
    """Target networks equal to the online ones hide bugs that mix them up."""
    with torch.no_grad():
        for p in params.values(True, True):
            p.add_(scale * torch.randn_like(p))


class TestTD0Equivalence:
    """H_max = 0 and alpha = 0 is the TD(0) target of the same critic."""

    @pytest.mark.parametrize("N", [1, 4])
    @pytest.mark.parametrize("cls", [RAVEValueEstimator, STEVEEstimator, MVEEstimator])
    def test_ddpg_td0(self, N, cls):
        loss = ddpg_loss()
        perturb(loss.target_value_network_params)
        perturb(loss.target_actor_network_params)
        data = batch(B=16, terminal=(2, 5))
        td0 = loss.value_estimator.value_estimate(
            data.clone(), target_params=loss._cached_target_params
        )
        kw = {"alpha": 0.0, "alpha_mode": "constant"} if cls is RAVEValueEstimator else {}
        loss.make_value_estimator(
            cls.for_loss(loss, world_model=world_model(N), gamma=0.99, horizon=0, **kw)
        )
        ours = loss.value_estimator.value_estimate(
            data.clone(), target_params=loss._cached_target_params
        )
        if N == 1:  # a single candidate: bit-for-bit the same arithmetic
            assert torch.equal(ours, td0)
        else:
            torch.testing.assert_close(ours, td0, rtol=1e-6, atol=1e-6)
        # ... and without explicit params it reads the loss's own target parameters
        torch.testing.assert_close(loss.value_estimator.value_estimate(data.clone()), ours)


def naive_target(wm, actor, critic, critic_params, data, gamma, H, alpha, mix, temperature=None):
    """Member by member, candidate by candidate, with the world model in mean mode. With a
    ``temperature``, the actor is a probabilistic one: every action is drawn (``rsample``)
    and scored (``log_prob``) apart, and ``-temperature * log pi`` joins each imagined
    reward and each bootstrap."""
    N = wm.num_models
    K = critic_params.batch_size[0]
    obs1 = data["next", "observation"]
    r = data["next", "reward"].squeeze(-1)
    d = data["next", "terminated"].squeeze(-1).to(r.dtype)

    def pi(s):  # (action, -temperature * log pi(action | s))
        td = TensorDict(observation=s, batch_size=s.shape[:-1])
        if temperature is None:
            return actor(td)["action"], 0.0
        with set_exploration_type(ExplorationType.RANDOM):
            dist = actor.get_dist(td)
        a = dist.rsample()
        return a, -temperature * dist.log_prob(a)

    def q(k, s, a):
        with critic_params[k].to_module(critic):
            return critic(TensorDict(observation=s, action=a, batch_size=s.shape[:-1]))[
                "state_action_value"
            ].squeeze(-1)

    traj = []  # per member i: states, actions, entropy bonuses, continuation
    for i in range(N):
        s, (a, e) = obs1, pi(obs1)
        states, actions, bonus, cont = [s], [a], [e], [1 - d]
        for _ in range(H):
            s = wm.step(s, a, sample=False)[i]
            a, e = pi(s)
            states.append(s)
            actions.append(a)
            bonus.append(e)
            cont.append(cont[-1] * (1 - wm.termination_prob(s)[i].squeeze(-1)))
        traj.append((states, actions, bonus, cont))
    means, variances = [], []
    for Hh in range(H + 1):
        cands = []
        for i in range(N):
            states, actions, bonus, cont = traj[i]
            for j in range(N):
                for k in range(K):
                    T = r.clone()
                    for h in range(1, Hh + 1):
                        rj = wm.reward(states[h - 1], actions[h - 1], states[h], sample=False)[
                            j
                        ].squeeze(-1)
                        T = T + gamma**h * cont[h - 1] * (rj + bonus[h - 1])
                    value = q(k, states[Hh], actions[Hh]) + bonus[Hh]
                    T = T + gamma ** (Hh + 1) * cont[Hh] * value
                    cands.append(T)
        cands = torch.stack(cands)
        means.append(cands.mean(0))
        variances.append(cands.var(0, unbiased=False))
    mean, var = torch.stack(means, -1), torch.stack(variances, -1)
    clb = mean - alpha.unsqueeze(-1) * var.sqrt()
    if mix == "fixed":
        return clb[:, H]
    w = 1 / (var + 1e-8)
    return (w * clb).sum(-1) / w.sum(-1)


class TestAgainstNaiveRollout:
    @pytest.mark.parametrize("N,K,H", [(1, 1, 1), (3, 2, 2), (4, 4, 3)])
    @pytest.mark.parametrize("alpha_mode", ["constant", "adaptive"])
    def test_mean_rollout_k_critic_ensemble(self, N, K, H, alpha_mode):
        wm = world_model(N)
        actor = actor_net()
        critics = [critic_net() for _ in range(K)]
        params = TensorDict.from_modules(*critics, as_module=True)
        est = ValueExpansionEstimator(
            world_model=wm,
            actor_network=actor,
            value_network=critics[0],
            value_params=params,
            gamma=0.9,
            horizon=H,
            rollout="mean",
            alpha=0.7,
            alpha_mode=alpha_mode,
        )
        data = batch(B=6, terminal=(1,))
        ours = est.value_estimate(data).squeeze(-1)
        if alpha_mode == "constant":
            alpha = torch.full((6,), 0.7)
        else:
            alpha = (
                0.7
                * (
                    1
                    - wm.mean_prediction_error(
                        data["observation"], data["action"], data["next", "observation"]
                    )
                )
            ).clamp_min(0)
        torch.testing.assert_close(data["value_expansion_alpha"].squeeze(-1), alpha)
        with torch.no_grad():
            ref = naive_target(
                wm, actor, critics[0], params, data, 0.9, H, alpha, "inverse_variance"
            )
        torch.testing.assert_close(ours, ref, rtol=1e-5, atol=1e-5)

    def test_mve_fixed_horizon(self):
        wm, actor, critic = world_model(3), actor_net(), critic_net()
        params = TensorDict.from_module(critic, as_module=True).expand(1).clone()
        est = MVEEstimator(
            world_model=wm,
            actor_network=actor,
            value_network=critic,
            value_params=params,
            gamma=0.8,
            horizon=2,
        )
        data = batch(B=5)
        with torch.no_grad():
            ref = naive_target(wm, actor, critic, params, data, 0.8, 2, torch.zeros(5), "fixed")
        torch.testing.assert_close(est.value_estimate(data).squeeze(-1), ref, rtol=1e-5, atol=1e-5)


class LineModel:
    """A hand-checkable 1-D "world model": s' = s + a, r = s', p(done) = p."""

    observation_dim = action_dim = 1

    def __init__(self, num_models=1, done_prob=0.0):
        self.num_models = num_models
        self.done_prob = done_prob

    def _members(self, x, per_member):
        return x if per_member else x.expand(self.num_models, *x.shape)

    def step(self, s, a, *, sample, per_member=False):
        return self._members(s + a, per_member)

    def reward(self, s, a, s2, *, sample, per_member=False):
        return self._members(s2, per_member)

    def termination_prob(self, s2, *, per_member=False):
        return self._members(torch.full_like(s2, self.done_prob), per_member)


def line_estimator(cls=MVEEstimator, done_prob=0.0, **kw):
    actor = TensorDictModule(
        lambda o: torch.ones_like(o), in_keys=["observation"], out_keys=["action"]
    )
    critic = TensorDictModule(
        lambda o, a: 10 * o + a, in_keys=["observation", "action"], out_keys=["state_action_value"]
    )
    return cls(
        world_model=LineModel(done_prob=done_prob),
        actor_network=actor,
        value_network=critic,
        gamma=0.5,
        **kw,
    )


def line_batch(terminated=False):
    t = torch.tensor([[terminated]])
    return TensorDict(
        observation=torch.tensor([[1.0]]),
        action=torch.tensor([[1.0]]),
        next=TensorDict(
            observation=torch.tensor([[2.0]]),
            reward=torch.tensor([[1.0]]),
            done=t.clone(),
            terminated=t,
            batch_size=[1],
        ),
        batch_size=[1],
    )


class TestHandComputed:
    """s_{t+1} = 2, r_t = 1, gamma = 1/2, pi = 1, s' = s + a, r = s', Q(s, a) = 10 s + a."""

    @pytest.mark.parametrize(
        "H,expected",
        [
            (0, 1 + 0.5 * 21),  # r + g Q(2, 1)
            (1, 1 + 0.5 * 3 + 0.25 * 31),  # r + g r~(3) + g^2 Q(3, 1)
            (2, 1 + 0.5 * 3 + 0.25 * 4 + 0.125 * 41),  # = 8.625
        ],
    )
    def test_one_member_mve_is_h_step_return(self, H, expected):
        est = line_estimator(horizon=H)
        assert est.value_estimate(line_batch()).item() == pytest.approx(expected)

    def test_terminal_real_transition_gives_reward(self):
        for cls in (MVEEstimator, STEVEEstimator, RAVEValueEstimator):
            kw = {"alpha_mode": "constant"} if cls is RAVEValueEstimator else {}
            assert (
                line_estimator(cls, horizon=3, **kw)
                .value_estimate(line_batch(terminated=True))
                .item()
                == 1.0
            )

    def test_certain_model_termination_cuts_later_terms(self):
        # p(done) = 1 at every imagined state: only r_t and the first imagined reward remain
        assert line_estimator(done_prob=1.0, horizon=3).value_estimate(
            line_batch()
        ).item() == pytest.approx(1 + 0.5 * 3)
        # STEVE with one member has zero variance everywhere: equal weights over H = 0..3
        steve = line_estimator(STEVEEstimator, done_prob=1.0, horizon=3)
        data = line_batch()
        assert steve.value_estimate(data).item() == pytest.approx((11.5 + 3 * 2.5) / 4)
        torch.testing.assert_close(data["steve_horizon_weights"], torch.full((1, 4), 0.25))

    def test_terminal_batch_with_neural_ensemble(self):
        loss = ensemble_loss()
        loss.make_value_estimator(
            RAVEValueEstimator.for_loss(loss, world_model=world_model(4), gamma=0.99, horizon=3)
        )
        data = batch(B=6, terminal=range(6))
        torch.testing.assert_close(
            loss.value_estimator.value_estimate(data), data["next", "reward"]
        )


class TestZeroVariance:
    def test_rave_alpha0_equals_steve(self):
        wm = world_model(4)
        with torch.no_grad():  # a model with no aleatoric noise: samples are the means
            for head in (wm.transition, wm.reward_model):
                head.max_logvar.fill_(-1e4)
                head.min_logvar.fill_(-1e4)
        loss = td3_loss(K=4)
        data = batch(B=10, terminal=(3,))
        steve = STEVEEstimator.for_loss(loss, world_model=wm, gamma=0.95, horizon=3).value_estimate(
            data.clone()
        )
        rave = RAVEValueEstimator.for_loss(
            loss, world_model=wm, gamma=0.95, horizon=3, alpha=0.0, alpha_mode="constant"
        ).value_estimate(data.clone())
        torch.testing.assert_close(rave, steve)

    def test_sampling_changes_rave_with_noise(self):
        loss = td3_loss(K=2)
        est = RAVEValueEstimator.for_loss(loss, world_model=world_model(4), gamma=0.95, horizon=3)
        data = batch()
        assert not torch.allclose(
            est.value_estimate(data.clone()), est.value_estimate(data.clone())
        )


class TestLossIntegration:
    def test_both_doors_install_the_estimator(self):
        wm = world_model()
        loss = ensemble_loss()
        est = RAVEValueEstimator.for_loss(loss, world_model=wm, gamma=0.99)
        loss.make_value_estimator(est)
        assert loss.value_estimator is est
        loss2 = ensemble_loss()
        est2 = RAVEValueEstimator.for_loss(loss2, world_model=wm, gamma=0.99)
        patch_value_estimator_setter()  # the opt-in fix for torchrl 0.14's setter
        loss2.value_estimator = est2
        assert loss2.value_estimator is est2
        # the world model is not registered inside the loss
        ids = {id(p) for p in loss2.parameters()}
        assert not any(id(p) in ids for p in wm.parameters())

    def test_subclass_door(self):
        loss = ddpg_loss()
        loss.make_value_estimator(
            STEVEEstimator,
            world_model=world_model(1),
            actor_network=loss.actor_network,
            value_network=loss.value_network,
            gamma=0.9,
        )
        assert isinstance(loss.value_estimator, STEVEEstimator)
        out = loss(batch())
        assert torch.isfinite(out["loss_value"])

    def test_td3_uses_its_critic_ensemble(self):
        loss = td3_loss(K=3)
        est = RAVEValueEstimator.for_loss(loss, world_model=world_model(2), gamma=0.99, horizon=1)
        shapes = record_critic_shapes(est)
        loss.make_value_estimator(est)
        data = batch(B=5)
        out = loss(data)
        assert shapes == [(3, 5 * (1 + 2 * 1))]
        (out["loss_actor"] + out["loss_qvalue"]).backward()

    def test_reads_soft_updated_target_params(self):
        loss = ensemble_loss()
        updater = SoftUpdate(loss, tau=0.5)
        est = STEVEEstimator.for_loss(loss, world_model=world_model(), gamma=0.9)
        data = batch()
        before = est.value_estimate(data.clone())
        perturb(loss.value_network_params, 1.0)
        updater.step()
        after = est.value_estimate(data.clone())
        assert not torch.allclose(before, after)

    def test_make_by_name(self):
        loss = ensemble_loss()
        wm = world_model()
        assert (
            type(make_value_expansion_estimator("RAVE", loss, world_model=wm, gamma=0.9))
            is RAVEValueEstimator
        )
        est = make_value_expansion_estimator("mve", loss, world_model=wm, gamma=0.9, horizon=2)
        assert (est.rollout, est.mix, float(est.alpha)) == ("mean", "fixed", 0.0)
        est = make_value_expansion_estimator("steve", loss, world_model=wm, gamma=0.9)
        assert (est.rollout, est.mix) == ("mean", "inverse_variance")


def sac_loss(K=2, dtype=torch.float32):
    torch.manual_seed(3)
    actor, critic = stochastic_actor().to(dtype), critic_net().to(dtype)
    loss = SACLoss(actor, critic, num_qvalue_nets=K, target_entropy=-float(A))
    SoftUpdate(loss, tau=0.05)
    perturb(loss.target_qvalue_network_params)
    return loss


@pytest.fixture
def constant_noise(monkeypatch):
    """Every Gaussian draw (SAC's tanh-Gaussian ``rsample``) takes the same standard-normal
    values per action dimension, so that separate draws, batched or row by row, agree."""
    eps = torch.tensor([0.4, -0.9])

    def draw(shape, dtype, device):
        return eps.to(dtype).expand(shape).clone()

    monkeypatch.setattr(torch.distributions.normal, "_standard_normal", draw)


def as_double(data):
    return data.apply(lambda x: x.double() if x.is_floating_point() else x)


class TestSoftTargetInSACLoss:
    """The soft value-expansion target inside TorchRL's own SACLoss (and REDQLoss)."""

    def test_rave_at_horizon_zero_with_alpha_one_is_sacs_own_target(self, constant_noise):
        """With K = 2 critics the mean less one (population) std of their two values is
        their minimum: RAVE at H = 0 with a constant alpha = 1 is SACLoss's clipped
        double-Q soft TD(0) target, at the temperature the loss has at call time."""
        loss = sac_loss()
        data = batch(B=8, terminal=(2, 5))
        for log_alpha in (0.0, -1.3, 0.8):
            loss.log_alpha.data.fill_(log_alpha)
            loss.make_value_estimator(ValueEstimators.TD0, gamma=0.9)
            want, want_meta = loss.qvalue_v2_loss(data.clone())
            est = RAVEValueEstimator.for_loss(
                loss, world_model=world_model(3), gamma=0.9, horizon=0, alpha=1.0,
                alpha_mode="constant",
            )  # fmt: skip
            loss.make_value_estimator(est)
            got, got_meta = loss.qvalue_v2_loss(data.clone())
            torch.testing.assert_close(got_meta["td_error"], want_meta["td_error"])
            torch.testing.assert_close(got, want)
        # and the estimator alone, against r + gamma (1 - d) (min_k Q'_k - alpha log pi)
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            nxt = data["next"].clone()
            dist = loss.actor_network.get_dist(nxt)
            a = dist.rsample()
            nxt["action"] = a
            q = torch.stack([_q(loss, nxt, k) for k in range(2)]).min(0)[0]
            soft = q - loss._alpha * dist.log_prob(a)
        r, d = data["next", "reward"].squeeze(-1), data["next", "terminated"].squeeze(-1)
        torch.testing.assert_close(
            est.value_estimate(data.clone()).squeeze(-1), r + 0.9 * (~d) * soft
        )

    @pytest.mark.parametrize("H", [1, 3])
    def test_against_a_naive_rollout_in_float64(self, H, constant_noise):
        loss = sac_loss(dtype=torch.float64)
        loss.log_alpha.data.fill_(-0.5)
        wm = world_model(3).double()
        est = ValueExpansionEstimator.for_loss(
            loss, world_model=wm, gamma=0.9, horizon=H, rollout="mean", alpha=0.7
        )
        data = as_double(batch(B=6, terminal=(1,)))
        ours = est.value_estimate(data).squeeze(-1)
        alpha = torch.full((6,), 0.7, dtype=torch.float64)
        with torch.no_grad(), loss.actor_network_params.to_module(loss.actor_network):
            ref = naive_target(
                wm, loss.actor_network, loss.qvalue_network, loss.target_qvalue_network_params,
                data, 0.9, H, alpha, "inverse_variance", temperature=float(loss._alpha),
            )  # fmt: skip
        torch.testing.assert_close(ours, ref, rtol=1e-10, atol=1e-10)
        # the entropy terms count: without them the target is another number
        with torch.no_grad(), loss.actor_network_params.to_module(loss.actor_network):
            plain = naive_target(
                wm, loss.actor_network, loss.qvalue_network, loss.target_qvalue_network_params,
                data, 0.9, H, alpha, "inverse_variance", temperature=0.0,
            )  # fmt: skip
        assert (ours - plain).abs().max() > 1e-2

    def test_no_gradient_reaches_the_actor_or_model_through_the_target(self):
        loss = sac_loss()
        wm = world_model(3)
        loss.make_value_estimator(
            RAVEValueEstimator.for_loss(loss, world_model=wm, gamma=0.9, horizon=2)
        )
        loss_qvalue, _ = loss.qvalue_v2_loss(batch(B=12))
        loss_qvalue.backward()  # the sampled imagined actions are reparameterised draws
        assert all(p.grad is None for p in wm.parameters())
        assert all(p.grad is None for p in loss.actor_network_params.values(True, True))
        assert loss.log_alpha.grad is None
        assert all(p.grad is not None for p in loss.qvalue_network_params.values(True, True))

    def test_sacloss_trains_with_rave_and_logs_its_diagnostics(self):
        loss = sac_loss()
        est = RAVEValueEstimator.for_loss(loss, world_model=world_model(3), gamma=0.9, horizon=2)
        loss.make_value_estimator(est)
        out = loss(batch(B=10))
        (out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]).backward()
        assert est.diagnostics["rave_horizon_weights"].shape == (10, 3)
        torch.testing.assert_close(est.diagnostics["rave_horizon_weights"].sum(-1), torch.ones(10))

    def test_redq_expands_over_every_critic_with_its_temperature(self, constant_noise):
        torch.manual_seed(3)
        loss = REDQLoss(stochastic_actor(), critic_net(), num_qvalue_nets=5)
        loss.log_alpha.data.fill_(0.5)
        est = STEVEEstimator.for_loss(loss, world_model=world_model(2), gamma=0.9, horizon=1)
        shapes = record_critic_shapes(est)
        loss.make_value_estimator(est)
        out = loss(batch(B=4))
        assert shapes == [(5, 4 * (1 + 2 * 1))]
        assert est.networks.temperature() == loss.alpha
        (out["loss_actor"] + out["loss_qvalue"]).backward()


def _q(loss, td, k):
    with loss.target_qvalue_network_params[k].to_module(loss.qvalue_network):
        return loss.qvalue_network(td.clone())["state_action_value"].squeeze(-1)


class TestNoGradientThroughTarget:
    def test_critic_actor_and_model_get_no_target_gradient(self):
        wm = world_model(1)  # one member: a single critic is then no degenerate mix
        loss = ddpg_loss()
        loss.make_value_estimator(RAVEValueEstimator.for_loss(loss, world_model=wm, gamma=0.99))
        data = batch(B=12)
        torch.manual_seed(11)
        loss_value, meta = loss.loss_value(data.clone())
        loss_value.backward()
        assert all(p.grad is None for p in wm.parameters())
        assert all(p.grad is None for p in loss.actor_network_params.values(True, True))
        assert all(p.grad is None for p in loss.target_value_network_params.values(True, True))
        assert all(p.grad is None for p in loss.target_actor_network_params.values(True, True))
        # the critic's gradient is that of (Q(s, a) - const)^2: the target is a constant
        target = meta["target_value"]
        assert not target.requires_grad
        critic = loss.value_network
        params = loss.value_network_params.detach().clone().requires_grad_()
        with params.to_module(critic):
            q = critic(data.select("observation", "action"))["state_action_value"].squeeze(-1)
        (q - target).pow(2).mean().backward()
        for name, p in loss.value_network_params.items(True, True):
            torch.testing.assert_close(p.grad, params.get(name).grad)


class TestFastCalls:
    """The planned tensor calls give the TensorDict path's target exactly."""

    @pytest.mark.parametrize("make_loss", [ensemble_loss, td3_loss, sac_loss])
    def test_same_target_and_diagnostics(self, make_loss):
        loss = make_loss()
        if make_loss is sac_loss:  # SAC's actor: its MLP planned, its draws the same
            assert TargetNetworks.of_loss(loss).calls.gaussian_actor(loss.actor_network)
            perturb(loss.actor_network_params)
        else:
            perturb(loss.target_actor_network_params)
        critic_name = (
            "value" if getattr(loss, "target_value_network_params", None) is not None else "qvalue"
        )
        perturb(getattr(loss, f"target_{critic_name}_network_params"))
        out = {}
        for fast in (False, True):
            est = RAVEValueEstimator.for_loss(
                loss, world_model=world_model(3), gamma=0.9, horizon=3, fast_calls=fast
            )
            torch.manual_seed(7)  # the same sampled rollouts
            data = batch(B=16, terminal=(1,))
            out[fast] = (est.value_estimate(data), data)
        torch.testing.assert_close(out[True][0], out[False][0])
        for key in ("rave_horizon_variance", "rave_horizon_weights", "rave_alpha"):
            torch.testing.assert_close(out[True][1][key], out[False][1][key])


class TestCallCounts:
    """O(N H) transition, O(N^2 H) reward, O(N K H) critic rows: never N^3 network work."""

    @pytest.mark.parametrize("fast_calls", [False, True])
    @pytest.mark.parametrize("N,K,H", [(1, 1, 0), (3, 2, 2), (4, 4, 3), (5, 2, 1)])
    def test_rows_per_network(self, N, K, H, fast_calls, monkeypatch):
        wm = world_model(N)
        loss = td3_loss(K)
        est = RAVEValueEstimator.for_loss(
            loss, world_model=wm, gamma=0.9, horizon=H, alpha_mode="constant", fast_calls=fast_calls
        )
        M = 7
        counts = {}
        if fast_calls:
            # The actor and critics are evaluated as planned tensor calls, not as modules:
            # count the planned calls (rows in, and members for stacked critic parameters).
            call_impl = TensorCall.__call__
            names = {}

            def counted(plan, params, inputs, **kwargs):
                out = call_impl(plan, params, inputs, **kwargs)
                name = "critic" if "state_action_value" in plan.out_keys else "actor"
                names[name] = params.batch_size.numel() if params is not None else 1
                rows = next(iter(inputs.values())).shape[:-1].numel()
                calls, total = counts.get(name, (0, 0))
                counts[name] = (calls + 1, total + rows)
                return out

            monkeypatch.setattr(TensorCall, "__call__", counted)

        def counter(name):
            def hook(module, args, out):
                t = out[0] if isinstance(out, tuple) else out
                rows = t.batch_size.numel() if isinstance(t, TensorDict) else t.shape[:-1].numel()
                calls, total = counts.get(name, (0, 0))
                counts[name] = (calls + 1, total + rows)

            return hook

        handles = [
            wm.transition.register_forward_hook(counter("transition")),
            wm.reward_model.register_forward_hook(counter("reward")),
            wm.termination.register_forward_hook(counter("termination")),
            loss.actor_network.register_forward_hook(counter("actor")),
            loss.qvalue_network.register_forward_hook(counter("critic")),
        ]
        est.value_estimate(batch(B=M))
        for h in handles:
            h.remove()
        assert counts.get("transition", (0, 0)) == (H, N * M * H)
        assert counts["reward"] == (1, N * N * M * H)
        assert counts["termination"] == (1, N * M * H)
        assert counts["actor"] == (H + 1, M * (1 + N * H))
        # one vmapped call over the K stacked critics (the hook sees one member's rows), or
        # one planned call with all K members' parameters stacked
        assert counts["critic"] == (1, M * (1 + N * H))
        if fast_calls:
            assert names["critic"] == K


class TestBadInput:
    def est(self, **kw):
        loss = ensemble_loss()
        return RAVEValueEstimator.for_loss(loss, world_model=world_model(), gamma=0.9, **kw)

    def test_observation_size_mismatch(self):
        data = batch()
        data["next", "observation"] = torch.randn(8, S + 1)
        with pytest.raises(ValueError, match=r"'next', 'observation'.*last dimension 3"):
            self.est().value_estimate(data)

    def test_action_size_mismatch(self):
        data = batch()
        data["action"] = torch.randn(8, A + 2)
        with pytest.raises(ValueError, match=r"'action'.*last dimension 2"):
            self.est().value_estimate(data)

    @pytest.mark.parametrize("key", ["observation", ("next", "reward"), ("next", "observation")])
    def test_nan(self, key):
        data = batch()
        data[key][0, 0] = math.nan
        with pytest.raises(ValueError, match="NaN"):
            self.est().value_estimate(data)

    @pytest.mark.parametrize(
        "kw,match",
        [
            ({"horizon": -1}, "horizon"),
            ({"alpha": -0.5}, "alpha"),
            ({"gamma": 1.5}, "gamma"),
            ({"alpha_error_scale": 0.0}, "alpha_error_scale"),
            ({"variance_eps": -1e-8}, "variance_eps must be a finite number > 0"),
            ({"variance_eps": 0.0}, "variance_eps must be a finite number > 0"),
            ({"variance_eps": math.nan}, "variance_eps must be a finite number > 0"),
        ],
    )
    def test_bad_hyperparameters(self, kw, match):
        args = {"gamma": 0.9, **kw}
        with pytest.raises(ValueError, match=match):
            RAVEValueEstimator.for_loss(ddpg_loss(), world_model=world_model(), **args)

    def test_bad_modes_and_ensemble_size(self):
        with pytest.raises(ValueError, match="rollout"):
            ValueExpansionEstimator(
                world_model=world_model(),
                actor_network=actor_net(),
                value_network=critic_net(),
                gamma=0.9,
                rollout="median",
            )
        with pytest.raises(ValueError, match="num_models"):
            WorldModelEnsemble(S, A, num_models=0)
        with pytest.raises(ValueError, match="world_model"):
            RAVEValueEstimator.for_loss(ddpg_loss(), gamma=0.9)

    @pytest.mark.parametrize("cls", [RAVEValueEstimator, STEVEEstimator])
    def test_single_critic_is_refused_with_a_pointer(self, cls):
        with pytest.raises(ValueError, match="needs K >= 2 critics.*EnsembleDDPGLoss"):
            cls.for_loss(ddpg_loss(), world_model=world_model(4), gamma=0.9)
        with pytest.raises(ValueError, match="needs K >= 2 critics"):
            cls.for_loss(td3_loss(K=1), world_model=world_model(4), gamma=0.9)
        # an estimator built by hand on one critic is refused at its first call, before
        # any rollout
        est = cls(
            world_model=world_model(4), actor_network=actor_net(), value_network=critic_net(),
            gamma=0.9,
        )  # fmt: skip
        with pytest.raises(ValueError, match="needs K >= 2 critics"):
            est.value_estimate(batch())
        # MVE's fixed horizon and one-member models have no degenerate mix
        MVEEstimator.for_loss(ddpg_loss(), world_model=world_model(4), gamma=0.9)
        cls.for_loss(ddpg_loss(), world_model=world_model(1), gamma=0.9).value_estimate(batch())

    @pytest.mark.parametrize("cls", [RAVEValueEstimator, STEVEEstimator, MVEEstimator])
    def test_entropy_losses_whose_target_it_cannot_expand_are_refused(self, cls):
        wm = world_model(4)
        crossq = CrossQLoss(stochastic_actor(), critic_net(), num_qvalue_nets=2)
        with pytest.raises(ValueError, match="cannot expand CrossQLoss: it has no target critics"):
            cls.for_loss(crossq, world_model=wm, gamma=0.9)
        cql = CQLLoss(stochastic_actor(), critic_net())
        with pytest.raises(ValueError, match="cannot expand CQLLoss: it is an offline loss"):
            cls.for_loss(cql, world_model=wm, gamma=0.9)
        discrete = ProbabilisticActor(
            TensorDictModule(MLP(in_features=S, out_features=3), ["observation"], ["logits"]),
            in_keys=["logits"], distribution_class=torch.distributions.Categorical,
        )  # fmt: skip
        dsac = DiscreteSACLoss(discrete, critic_net(), num_actions=3, num_qvalue_nets=2)
        with pytest.raises(ValueError, match="DiscreteSACLoss: it acts on a discrete action set"):
            cls.for_loss(dsac, world_model=wm, gamma=0.9)
        value = ValueOperator(MLP(in_features=S, out_features=1, num_cells=[16]), ["observation"])
        sac_v1 = SACLoss(stochastic_actor(), critic_net(), value_network=value)
        with pytest.raises(ValueError, match="SACLoss bootstraps from a separate state-value"):
            cls.for_loss(sac_v1, world_model=wm, gamma=0.9)

    def test_a_loss_bootstrapping_from_a_state_value_network_is_refused(self):
        value = ValueOperator(MLP(in_features=S, out_features=1, num_cells=[16]), ["observation"])
        loss = IQLLoss(stochastic_actor(), critic_net(), value, num_qvalue_nets=4)
        with pytest.raises(ValueError, match="IQLLoss bootstraps from a separate state-value"):
            RAVEValueEstimator.for_loss(loss, world_model=world_model(4), gamma=0.9)

    def test_tensordict_alpha_needs_the_key(self):
        est = self.est(alpha_mode="tensordict")
        with pytest.raises(ValueError, match="rave_alpha"):
            est.value_estimate(batch())


@pytest.mark.parametrize("shape", [(3, 4), (4, 3)])
def test_estimator_on_td3_loss_takes_any_batch_shape(shape):
    """Issue 15, deliverable 3: RAVE in a stock TD3Loss (K = 4) gives the flattened
    batch's losses for [B1, B2] batches, including a leading dimension equal to K."""
    flat = batch(B=12, terminal=(2, 7))
    outs = []
    for data in (flat.clone(), flat.clone().reshape(shape)):
        loss = td3_loss()
        loss.make_value_estimator(
            RAVEValueEstimator.for_loss(loss, world_model=world_model(3), gamma=0.9, horizon=2)
        )
        torch.manual_seed(9)  # the same rollouts and target smoothing noise
        outs.append(loss(data))
    for key in ("loss_actor", "loss_qvalue"):
        torch.testing.assert_close(outs[1][key], outs[0][key])


@pytest.mark.parametrize("cls, prefix", [(RAVEValueEstimator, "rave"), (STEVEEstimator, "steve")])
def test_diagnostics_are_keyed_by_their_estimator_and_renameable(cls, prefix):
    loss = td3_loss()
    estimator = cls.for_loss(loss, world_model=world_model(3), gamma=0.9, horizon=2)
    data = batch(B=5)
    estimator.value_estimate(data)
    for name in ("alpha", "horizon_variance", "horizon_weights"):
        assert data.get(f"{prefix}_{name}", None) is not None
    estimator.set_keys(alpha="my_alpha", horizon_weights=("diag", "w"))
    renamed = batch(B=5)
    estimator.value_estimate(renamed)
    assert renamed.get("my_alpha", None) is not None
    assert renamed.get(("diag", "w"), None) is not None
    assert renamed.get(f"{prefix}_alpha", None) is None
    with pytest.raises(KeyError, match="not an accepted tensordict key"):
        estimator.set_keys(no_such_key="x")
