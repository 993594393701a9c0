"""TensorCall: the planned tensor-level call gives the TensorDict module's numbers exactly."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictParams, TensorDictSequential
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import MLP, Actor, TanhModule, ValueOperator

from torchrl_rave.modules import TensorCall

S, A, M = 5, 2, 9


def critic(**kw):
    return ValueOperator(
        MLP(in_features=S + A, out_features=1, num_cells=[16, 16], **kw),
        in_keys=["observation", "action"],
    )


def tanh_actor(low=-2.0, high=3.0):
    return TensorDictSequential(
        TensorDictModule(
            MLP(in_features=S, out_features=A, num_cells=[16]),
            in_keys=["observation"],
            out_keys=["param"],
        ),
        TanhModule(in_keys=["param"], out_keys=["action"], spec=Bounded(low, high, shape=(A,))),
    )


def random_params(module, K=None):
    """Parameters unlike the module's own, so using the wrong ones would show."""
    params = TensorDict.from_module(module).data
    if K is not None:
        params = params.expand(K).clone()
    return params.apply(lambda t: torch.randn_like(t) if t.is_floating_point() else t)


def inputs():
    g = torch.Generator().manual_seed(0)
    return {"observation": torch.randn(M, S, generator=g), "action": torch.randn(M, A, generator=g)}


def reference(module, params, x):
    td = TensorDict(dict(x), [M])
    with params.to_module(module):
        return module(td)


class TestEquivalence:
    def test_critic_own_parameters(self):
        net = critic()
        call = TensorCall.plan(net)
        out = call(None, inputs())["state_action_value"]
        torch.testing.assert_close(out, net(TensorDict(inputs(), [M]))["state_action_value"])

    def test_critic_given_parameters(self):
        net = critic()
        params = random_params(net)
        out = TensorCall.plan(net)(params, inputs())["state_action_value"]
        torch.testing.assert_close(out, reference(net, params, inputs())["state_action_value"])

    @pytest.mark.parametrize("K", [1, 3])
    def test_stacked_critics_match_a_loop_over_members(self, K):
        net = critic()
        params = random_params(net, K)
        out = TensorCall.plan(net, stacked=True)(params, inputs())["state_action_value"]
        assert out.shape == (K, M, 1)
        for k in range(K):
            expected = reference(net, params[k], inputs())["state_action_value"]
            torch.testing.assert_close(out[k], expected)

    def test_stacked_per_member_inputs(self):
        net = critic()
        params = random_params(net, 3)
        x = {
            k: v.expand(3, *v.shape) + torch.arange(3.0).view(3, 1, 1) for k, v in inputs().items()
        }
        out = TensorCall.plan(net, stacked=True)(params, x)["state_action_value"]
        for k in range(3):
            member = {key: v[k] for key, v in x.items()}
            expected = reference(net, params[k], member)["state_action_value"]
            torch.testing.assert_close(out[k], expected)

    def test_tanh_actor_lands_in_the_box(self):
        actor = tanh_actor()
        params = random_params(actor)
        out = TensorCall.plan(actor)(params, inputs())["action"]
        torch.testing.assert_close(out, reference(actor, params, inputs())["action"])
        # the box is the one in params, drawn at random like the weights (so the module's
        # own [-2, 3] does not hold, as it did by chance for some test orders), whichever
        # of its bounds came out larger
        low, high = params["module", "1", "action_low"], params["module", "1", "action_high"]
        assert bool((out >= low.minimum(high)).all() and (out <= low.maximum(high)).all())

    def test_nested_sequential_actor(self):
        actor = Actor(nn.Sequential(MLP(in_features=S, out_features=A, num_cells=[8]), nn.Tanh()))
        params = random_params(actor)
        call = TensorCall.plan(actor)
        assert call.steps[0][0] == "mlp"
        torch.testing.assert_close(
            call(params, inputs())["action"], reference(actor, params, inputs())["action"]
        )

    def test_gradients_reach_the_given_parameters(self):
        net = critic()
        params = TensorDict.from_module(net)
        out = TensorCall.plan(net)(params, inputs())["state_action_value"].sum()
        out.backward()
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())


class TestStackedSeeds:
    """``seeds=True``: a seed group's stacked parameters, one dict leaf ``[S, ...]`` per
    dotted key, against each seed's own parameters through the module."""

    @staticmethod
    def stack(params_per_seed):
        return {".".join(k): torch.stack([p.get(k) for p in params_per_seed])
                for k in params_per_seed[0].keys(True, True)}  # fmt: skip

    def test_stacked_critics_of_every_seed(self):
        net = critic()
        seeds = [random_params(net, 3) for _ in range(2)]  # S = 2 seeds of K = 3 critics
        x = {k: torch.stack([v, v.flip(0)]) for k, v in inputs().items()}  # [S, M, F]
        out = TensorCall.plan(net, stacked=True)(self.stack(seeds), x, seeds=True)
        for s, params in enumerate(seeds):
            one = {k: v[s] for k, v in x.items()}
            for k in range(3):
                want = reference(net, params[k], one)["state_action_value"]
                torch.testing.assert_close(out["state_action_value"][s, k], want)

    def test_tanh_actor_of_every_seed_with_the_modules_box(self):
        actor = tanh_actor()
        seeds = [random_params(actor) for _ in range(3)]
        for p in seeds:  # the box is the module's (a group's seeds share it)
            p["module", "1"].update(TensorDict.from_module(actor)["module", "1"])
        x = {"observation": torch.randn(3, M, S)}
        out = TensorCall.plan(actor)(self.stack(seeds), x, seeds=True)["action"]
        for s, params in enumerate(seeds):
            want = reference(actor, params, {"observation": x["observation"][s]})["action"]
            torch.testing.assert_close(out[s], want)

    def test_a_module_step_is_refused(self):
        actor = Actor(nn.Sequential(nn.Linear(S, A), nn.LayerNorm(A)))
        call = TensorCall.plan(actor)
        with pytest.raises(ValueError, match="stacked seeds' parameters run MLP and tanh steps"):
            call({}, {"observation": torch.randn(2, M, S)}, seeds=True)


class TestRefusals:
    def test_layer_norm_runs_through_the_module(self):
        net = critic(norm_class=nn.LayerNorm, norm_kwargs={"normalized_shape": 16})
        params = random_params(net)
        call = TensorCall.plan(net)
        assert [step[0] for step in call.steps] == ["module"]
        torch.testing.assert_close(
            call(params, inputs())["state_action_value"],
            reference(net, params, inputs())["state_action_value"],
        )
        # its parameters are not a Linear stack: no stacked plan
        assert TensorCall.plan(net, stacked=True) is None

    def test_custom_module_runs_through_its_forward(self):
        class Shift(nn.Module):
            def __init__(self):
                super().__init__()
                self.shift = nn.Parameter(torch.ones(A))

            def forward(self, x):
                return x + self.shift

        actor = TensorDictSequential(
            TensorDictModule(
                MLP(in_features=S, out_features=A, num_cells=[8]),
                in_keys=["observation"],
                out_keys=["h"],
            ),
            TensorDictModule(Shift(), in_keys=["h"], out_keys=["action"]),
        )
        params = random_params(actor)
        call = TensorCall.plan(actor)
        assert [step[0] for step in call.steps] == ["mlp", "module"]
        torch.testing.assert_close(
            call(params, inputs())["action"], reference(actor, params, inputs())["action"]
        )
        # a member-specific custom module cannot be stacked exactly
        assert TensorCall.plan(actor, stacked=True) is None


class TestParameterSources:
    """Leaves are read from a TensorDictParams' module dicts (see ``_leaf``); they must
    follow every change of the TensorDict and give the same numbers as a plain one."""

    def test_tensordict_params_equal_plain_tensordict(self):
        net = critic()
        plain = random_params(net, 3)
        wrapped = TensorDictParams(plain.clone())
        call = TensorCall.plan(net, stacked=True)
        assert torch.equal(
            call(wrapped, inputs())["state_action_value"],
            call(plain, inputs())["state_action_value"],
        )

    def test_a_replaced_entry_is_seen(self):
        net = critic()
        params = TensorDictParams(random_params(net))
        call = TensorCall.plan(net)
        before = call(params, inputs())["state_action_value"]
        key = ("module", "0", "weight")
        params.set(key, torch.nn.Parameter(torch.zeros_like(params.get(key))))
        after = call(params, inputs())["state_action_value"]
        assert not torch.equal(before, after)
        torch.testing.assert_close(
            after, reference(net, params.data, inputs())["state_action_value"]
        )

    def test_a_cast_module_is_seen(self):
        net = critic()
        holder = nn.Module()
        holder.params = TensorDictParams(random_params(net, 2))
        holder.to(torch.float64)
        x = {k: v.double() for k, v in inputs().items()}
        out = TensorCall.plan(net, stacked=True)(holder.params, x)["state_action_value"]
        assert out.dtype == torch.float64

    def test_detach_keeps_the_numbers_and_stops_parameter_gradients(self):
        net = critic()
        params = TensorDictParams(random_params(net, 2))
        action = inputs()["action"].requires_grad_()
        call = TensorCall.plan(net, stacked=True)
        x = {"observation": inputs()["observation"], "action": action}
        out = call(params, x, detach=True)["state_action_value"]
        assert torch.equal(out, call(params.data, x)["state_action_value"])
        out.sum().backward()
        assert action.grad is not None and action.grad.abs().sum() > 0
        assert all(p.grad is None for p in params.values(True, True))

    @pytest.mark.parametrize("per_member", [False, True])
    def test_one_stacked_member_matches_the_module(self, per_member):
        # K = 1 runs as plain 2-D linear calls on the squeezed member
        net = critic()
        params = TensorDictParams(random_params(net, 1))
        x = inputs()
        if per_member:
            x = {k: v.unsqueeze(0) for k, v in x.items()}
        out = TensorCall.plan(net, stacked=True)(params, x)["state_action_value"]
        assert out.shape == (1, M, 1)
        expected = reference(net, params.data[0], inputs())["state_action_value"]
        assert torch.equal(out[0], expected)
        out.sum().backward()
        grads = [p.grad for p in params.values(True, True)]
        assert all(g is not None and g.shape[0] == 1 and g.abs().sum() > 0 for g in grads)

    def test_one_member_kept_views_follow_their_leaves(self):
        # without gradients (a target network, detach=True) K = 1 keeps one view per
        # leaf: in-place updates must show through it, a replaced leaf must not be served
        # its predecessor's view, and repeated backward passes stay exact
        net = critic()
        params = TensorDictParams(random_params(net, 1))
        call = TensorCall.plan(net, stacked=True)
        x = {"observation": inputs()["observation"], "action": inputs()["action"].requires_grad_()}

        def expected():
            return reference(net, params.data[0], inputs())["state_action_value"]

        for _ in range(3):
            with torch.no_grad():
                assert torch.equal(call(params, x)["state_action_value"][0], expected())
            out = call(params, x, detach=True)["state_action_value"]
            assert torch.equal(out[0], expected())
            x["action"].grad = None
            out.sum().backward()
            assert x["action"].grad.abs().sum() > 0
            assert all(p.grad is None for p in params.values(True, True))
            # with gradients the view is made afresh: the gradient is the module's
            grad_out = call(params, x)["state_action_value"]
            grad_out.sum().backward()
            assert all(p.grad is not None for p in params.values(True, True))
            for p in params.values(True, True):
                p.grad = None
            with torch.no_grad():  # an optimiser-like in-place step
                for p in params.values(True, True):
                    p.mul_(0.9).add_(0.05)
        key = ("module", "0", "weight")
        params.set(key, torch.nn.Parameter(torch.zeros_like(params.get(key))))
        with torch.no_grad():
            assert torch.equal(call(params, x)["state_action_value"][0], expected())
