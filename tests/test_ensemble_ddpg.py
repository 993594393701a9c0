"""EnsembleDDPGLoss: DDPG's losses by hand, DDPGLoss's interface, and the fast path equal
to the TensorDict + vmap path."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from test_value_expansion import A, actor_net, batch, critic_net, perturb, world_model
from torchrl.data import Bounded
from torchrl.objectives import SoftUpdate, TD3Loss, ValueEstimators

from torchrl_rave import (
    EnsembleDDPGLoss,
    ForeachSoftUpdate,
    RAVEValueEstimator,
    STEVEEstimator,
)

GAMMA = 0.9


def make_loss(K, fast_calls=True, estimator=None):
    torch.manual_seed(3)
    loss = EnsembleDDPGLoss(actor_net(), critic_net(), num_value_nets=K, fast_calls=fast_calls)
    SoftUpdate(loss, tau=0.05)
    perturb(loss.target_actor_network_params)
    perturb(loss.target_value_network_params)
    if estimator in ("rave", "steve"):
        cls = RAVEValueEstimator if estimator == "rave" else STEVEEstimator
        loss.make_value_estimator(
            cls.for_loss(loss, world_model=world_model(3), gamma=GAMMA, horizon=2)
        )
    else:
        loss.make_value_estimator(ValueEstimators.TD0, gamma=GAMMA)
    return loss


def q_by_hand(loss, params, obs, action):
    """``[K, B]`` by a loop over the critic members."""
    out = []
    for k in range(loss.num_value_nets):
        td = TensorDict({"observation": obs, "action": action}, obs.shape[:-1])
        with params[k].to_module(loss.value_network):
            out.append(loss.value_network(td)["state_action_value"].squeeze(-1))
    return torch.stack(out)


def act_by_hand(loss, params, obs):
    with params.to_module(loss.actor_network):
        return loss.actor_network(TensorDict({"observation": obs}, obs.shape[:-1]))["action"]


@pytest.mark.parametrize("K", [1, 3])
@pytest.mark.parametrize("fast_calls", [True, False])
def test_losses_by_hand(K, fast_calls):
    loss = make_loss(K, fast_calls)
    data = batch(B=10, terminal=(4,))
    out = loss(data.clone())
    with torch.no_grad():
        next_obs = data["next", "observation"]
        next_q = q_by_hand(
            loss,
            loss.target_value_network_params,
            next_obs,
            act_by_hand(loss, loss.target_actor_network_params, next_obs),
        )
        not_done = 1.0 - data["next", "terminated"].squeeze(-1).float()
        target = data["next", "reward"].squeeze(-1) + GAMMA * not_done * next_q.min(0)[0]
        q = q_by_hand(loss, loss.value_network_params, data["observation"], data["action"])
        expected_critic = ((q - target) ** 2).sum(0).mean()
        pi = act_by_hand(loss, loss.actor_network_params, data["observation"])
        expected_actor = -q_by_hand(loss, loss.value_network_params, data["observation"], pi)
        expected_actor = expected_actor.mean(0).mean()
    torch.testing.assert_close(out["loss_value"], expected_critic)
    torch.testing.assert_close(out["loss_actor"], expected_actor)


@pytest.mark.parametrize("estimator", ["td0", "steve", "rave"])
def test_fast_path_matches_vmap_path_with_gradients(estimator):
    grads, losses = {}, {}
    for fast in (True, False):
        loss = make_loss(4, fast, estimator)
        torch.manual_seed(5)  # the same sampled rollouts for RAVE
        out = loss(batch(B=12, terminal=(0,)))
        (out["loss_value"] + out["loss_actor"]).backward()
        losses[fast] = (out["loss_value"].detach(), out["loss_actor"].detach())
        grads[fast] = [
            p.grad.clone()
            for p in (
                *loss.actor_network_params.values(True, True),
                *loss.value_network_params.values(True, True),
            )
        ]
    torch.testing.assert_close(losses[True], losses[False])
    for fast_grad, td_grad in zip(grads[True], grads[False], strict=True):
        torch.testing.assert_close(fast_grad, td_grad)


def test_actor_loss_leaves_critics_alone():
    loss = make_loss(2)
    out = loss(batch(B=6))
    out["loss_actor"].backward()
    assert all(p.grad is None for p in loss.value_network_params.values(True, True))
    assert all(p.grad is not None for p in loss.actor_network_params.values(True, True))


def test_fast_path_is_used_and_skips_the_unused_td0_target(monkeypatch):
    calls = []
    for estimator in ("rave", "td0"):
        loss = make_loss(2, estimator=estimator)
        assert loss._calls.get("critic", loss.value_network, stacked=True) is not None
        original = loss._actions
        count = []
        monkeypatch.setattr(loss, "_actions", lambda *a, c=count, f=original: c.append(1) or f(*a))
        loss(batch(B=4))
        calls.append(len(count))
    # value expansion computes its own target: only the actor loss runs the loss's actor;
    # TD(0) also runs the target actor on the next observations
    assert calls == [1, 2]


def test_ddpg_interface():
    """What a DDPGLoss script touches: names, outputs, the two loss methods."""
    loss = make_loss(3)
    data = batch(B=5)
    out = loss(data)
    assert {"loss_actor", "loss_value", "pred_value", "target_value"} <= set(out.keys())
    assert out["pred_value"].shape == (3, 5) and out["target_value"].shape == (5,)
    assert data["td_error"].shape == (5,)  # for a prioritised buffer
    loss_value, meta = loss.loss_value(data)
    loss_actor, _ = loss.loss_actor(data)
    torch.testing.assert_close(loss_value, out["loss_value"])
    torch.testing.assert_close(loss_actor, out["loss_actor"])
    assert loss.value_network_params.batch_size == (3,)
    assert loss.target_value_network_params.batch_size == (3,)
    with pytest.raises(ValueError, match="num_value_nets"):
        EnsembleDDPGLoss(actor_net(), critic_net(), num_value_nets=0)


@pytest.mark.parametrize("K", [1, 4])
def test_members_initialised_as_td3_loss_does(K):
    """The same seed gives TD3Loss's stacked critics (the recipe's numbers before the
    DDPG-named loss came are kept) and independent members."""
    torch.manual_seed(0)
    ours = EnsembleDDPGLoss(actor_net(), critic_net(), num_value_nets=K)
    torch.manual_seed(0)
    theirs = TD3Loss(actor_net(), critic_net(), num_qvalue_nets=K, action_spec=Bounded(-1, 1, (A,)))
    torch.testing.assert_close(ours.value_network_params.data, theirs.qvalue_network_params.data)
    torch.testing.assert_close(ours.actor_network_params.data, theirs.actor_network_params.data)
    if K > 1:
        w = ours.value_network_params.get(("module", "0", "weight"))
        assert not torch.equal(w[0], w[1])


@pytest.mark.parametrize("K", [1, 3])
def test_foreach_soft_update_matches_torchrl(K):
    ours, theirs = make_loss(K), make_loss(K)
    before = ours.target_value_network_params.clone()
    updaters = [ForeachSoftUpdate(ours, tau=0.1), SoftUpdate(theirs, tau=0.1)]
    for step in range(3):
        for loss in (ours, theirs):
            torch.manual_seed(step)  # the same change of the online networks in both
            perturb(loss.actor_network_params)
            perturb(loss.value_network_params)
        for updater in updaters:
            updater.step()
    assert not (ours.target_value_network_params == before).all()
    for name in ("target_actor_network_params", "target_value_network_params"):
        torch.testing.assert_close(getattr(ours, name), getattr(theirs, name), rtol=0, atol=1e-7)


@pytest.mark.parametrize(
    "kw,match", [({"tau": 1.5}, "tau must be in"), ({"tau": math.nan}, "tau must be in"),
                 ({"eps": -0.1}, "eps must be in")],
)  # fmt: skip
def test_foreach_soft_update_names_a_bad_tau(kw, match):
    # TorchRL's own message speaks of "eps = -0.5" for tau = 1.5
    with pytest.raises(ValueError, match=match):
        ForeachSoftUpdate(make_loss(2), **kw)
    ForeachSoftUpdate(make_loss(2), tau=torch.tensor(0.0))  # the bounds hold


def test_summing_every_output_entry_gives_the_loss_gradients():
    """Scripts that sum every entry of the loss output (TorchRL 0.14.1's sota DDPG does)
    get the same gradients as loss_value + loss_actor: the metadata carry no graph."""
    grads = []
    for total in ("losses", "everything"):
        loss = make_loss(2, estimator="steve")
        out = loss(batch(B=8))
        keys = [k for k in out.keys() if total == "everything" or k.startswith("loss_")]  # noqa: SIM118
        sum(out[k].sum() for k in keys).backward()
        grads.append([p.grad.clone() for p in loss.parameters() if p.grad is not None])
    assert len(grads[0]) == len(grads[1]) > 0
    for a, b in zip(*grads, strict=True):
        torch.testing.assert_close(a, b)


@pytest.mark.parametrize("shape", [(12,), (3, 4), (4, 3)])
@pytest.mark.parametrize("fast_calls", [True, False])
@pytest.mark.parametrize("estimator", ["td0", "rave"])
def test_any_batch_shape_equals_the_flattened_batch(shape, fast_calls, estimator):
    """[B], [B1, B2] and a leading dimension equal to K (4 x 3 with K = 4, which a
    shape-blind planned call would read as [K, M, F]) give the flattened batch's losses."""
    flat = batch(B=12, terminal=(2, 7))
    outs = []
    for data in (flat.clone(), flat.clone().reshape(shape)):
        loss = make_loss(4, fast_calls, estimator)
        torch.manual_seed(9)  # the same sampled rollouts for RAVE
        outs.append(loss(data))
        assert data["td_error"].shape == data.batch_size
    for key in ("loss_value", "loss_actor"):
        torch.testing.assert_close(outs[1][key], outs[0][key])
    torch.testing.assert_close(outs[1]["pred_value"].reshape(4, 12), outs[0]["pred_value"])


def _without_action(td):
    return td.exclude("action")


def _float64(td):
    return td.to(torch.float64)


def _empty(td):
    return td[:0]


def _nan_observation(td):
    td = td.clone()
    td["observation"][2, 0] = float("nan")
    return td


def _inf_reward(td):
    td = td.clone()
    td["next", "reward"][1] = float("inf")
    return td


def _wide_observation(td):
    td = td.clone()
    width = td["observation"].shape[-1] + 1
    td["observation"] = torch.randn(*td.batch_size, width)
    td["next", "observation"] = torch.randn(*td.batch_size, width)
    return td


def _int64_reward(td):
    td = td.clone()
    td["next", "reward"] = td["next", "reward"].round().long()
    return td


def _int64_action(td):
    td = td.clone()
    td["action"] = td["action"].round().long()
    return td


def _wide_reward(td):
    td = td.clone()
    td["next", "reward"] = td["next", "reward"].expand(*td.batch_size, 2).clone()
    return td


def _flat_reward(td):
    td = td.clone()
    td["next", "reward"] = td["next", "reward"].squeeze(-1)
    return td


def _float_terminated(td):
    td = td.clone()
    td["next", "terminated"] = td["next", "terminated"].float()
    return td


_BAD_BATCHES = [
    ("td0", _without_action, "no entry 'action'"),
    # the probes: these ended in TorchRL's errors, which name neither entry nor shape
    ("td0", _wide_reward, r"entry \('next', 'reward'\) has shape \(6, 2\), expected \(6, 1\)"),
    ("td0", _flat_reward, r"entry \('next', 'reward'\) has shape \(6,\), expected \(6, 1\)"),
    (
        "td0",
        _float_terminated,
        r"entry \('next', 'terminated'\) is torch.float32, expected torch.bool",
    ),
    # issue 39, defect 9: integer rewards and actions were cast silently
    ("td0", _int64_reward, "entry \\('next', 'reward'\\) is torch.int64, expected a floating"),
    ("rave", _int64_reward, "entry \\('next', 'reward'\\) is torch.int64, expected a floating"),
    ("td0", _int64_action, "entry 'action' is torch.int64, expected a floating"),
    ("rave", _int64_action, "entry 'action' is torch.int64, expected a floating"),
    ("rave", _without_action, "no entry 'action'"),
    ("td0", _float64, "entry 'observation' is torch.float64 but the model's parameters"),
    ("rave", _float64, "entry 'observation' is torch.float64 but the model's parameters"),
    ("td0", _empty, "EnsembleDDPGLoss got an empty batch"),
    ("rave", _empty, "EnsembleDDPGLoss got an empty batch"),
    # the estimator knows the width; its check runs before any network sees the batch
    ("rave", _wide_observation, "entry 'observation' has shape \\(6, 4\\), expected last"),
    # without one, the loss reads the widths off the networks' first layers
    (
        "td0",
        _wide_observation,
        "the (actor|critic) takes [0-9]+ input features, but the batch "
        "gives .*'observation' of width 4",
    ),
    ("td0", _nan_observation, "entry 'observation' holds NaN or infinite values"),
    ("td0", _inf_reward, "entry \\('next', 'reward'\\) holds NaN or infinite values"),
]


@pytest.mark.parametrize(
    "method, estimator, damage, message",
    [
        (method, *case)
        for method in ("forward", "loss_value", "loss_actor")
        for case in _BAD_BATCHES
        # the actor loss reads no action and no reward
        if not (
            method == "loss_actor"
            and case[1]
            in (
                _without_action,
                _inf_reward,
                _int64_reward,
                _int64_action,
                _wide_reward,
                _flat_reward,
                _float_terminated,
            )
        )
    ],
)
def test_bad_batches_are_named_before_any_network_runs(method, estimator, damage, message):
    """Issue 15, defect 10: these failed with NoneType, matmul dtype or shape errors, a
    max() over nothing, or (the actor loss of an empty batch) NaN."""
    loss = make_loss(3, estimator=estimator)
    bad = damage(batch(B=6))
    with pytest.raises(ValueError, match=message):
        getattr(loss, method)(bad)


def test_td0_checks_can_be_turned_off_and_then_nan_flows_through():
    """Issue 39, defect 6: the TD(0) path used to give NaN losses silently. With
    ``check_inputs=False`` (the recipe's, whose batches are checked on collection) it does."""
    loss = make_loss(3)
    loss.check_inputs = False
    out = loss(_nan_observation(batch(B=6)))
    assert torch.isnan(out["loss_value"]) and torch.isnan(out["loss_actor"])


@pytest.mark.parametrize("estimator", ["td0", "rave"])
def test_forward_adds_only_the_priority_to_the_callers_batch(estimator):
    """The estimators write into the batch they get (TD(0) nothing, RAVE its diagnostics);
    the loss hands them a shallow copy, so the caller's batch gains only ``td_error``,
    and its entries are the same tensors as before."""
    data = batch(B=12, terminal=(2, 7))
    before = {k: data.get(k) for k in data.keys(True, True)}
    make_loss(4, estimator=estimator)(data)
    assert set(data.keys(True, True)) == set(before) | {"td_error"}
    assert all(data.get(k) is v for k, v in before.items())


def test_the_estimators_diagnostics_are_in_the_loss_output():
    """Issue 39, defect 10: a stock script that logs the loss outputs saw nothing of RAVE."""
    loss = make_loss(3, estimator="rave")
    out = loss(batch(B=6))
    diag, keys = loss.value_estimator.diagnostics, loss.value_estimator.tensor_keys
    # every entry a scalar, so that a stock script logging each output's mean logs them
    # (a [H + 1] vector of weights logged as its mean was a constant 1 / (H + 1))
    names = out.keys()  # (iterating a TensorDict itself runs along its batch)
    diagnostics = [k for k in names if k.startswith("rave_")]
    assert len(diagnostics) == 7 and all(out[k].shape == () for k in diagnostics)
    torch.testing.assert_close(out[keys.alpha], diag[keys.alpha].mean())
    weights = [out[f"{keys.horizon_weights}_h{H}"] for H in range(3)]  # H = 0, 1, 2
    variances = [out[f"{keys.horizon_variance}_h{H}"] for H in range(3)]
    torch.testing.assert_close(torch.stack(weights), diag[keys.horizon_weights].mean(0))
    torch.testing.assert_close(torch.stack(variances), diag[keys.horizon_variance].mean(0))
    assert sum(weights).item() == pytest.approx(1.0)
    assert f"{keys.horizon_weights}_h3" not in names
    assert keys.alpha == "rave_alpha"  # never SAC's "alpha"
    assert not make_loss(3)(batch(B=6)).keys() & {keys.alpha, "steve_alpha"}  # TD(0): none


def test_an_untrained_world_model_is_named_once():
    """Issue 39, defect 10: forgetting WorldModelTrainer left the estimator expanding with
    an untrained model, silently."""
    import warnings

    from test_value_expansion import S

    from torchrl_rave import WorldModelEnsemble

    loss = make_loss(3)
    fresh = WorldModelEnsemble(S, A, num_models=3, transition_cells=16, reward_cells=16,
                               termination_cells=16)  # fmt: skip
    est = RAVEValueEstimator.for_loss(loss, world_model=fresh, gamma=GAMMA)
    loss.make_value_estimator(est)
    with pytest.warns(UserWarning, match="world model that never saw data"):
        loss(batch(B=6))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loss(batch(B=6))  # once
        make_loss(3, estimator="rave")(batch(B=6))  # a fitted model: no warning


@pytest.mark.parametrize("estimator", ["td0", "rave"])
def test_inputs_too_large_for_float32_are_named_before_a_step(estimator):
    """The probe: rewards of 1e20 passed every check, gave inf losses, and one Adam step
    later every parameter was NaN, silently."""
    loss = make_loss(4, estimator=None if estimator == "td0" else "rave")
    data = batch()
    data["next", "reward"] = torch.full_like(data["next", "reward"], 1e20)
    with pytest.raises(ValueError, match="not finite although the batch holds no NaN or inf.*"
                       "entry \\('next', 'reward'\\) reaches 1e\\+20"):  # fmt: skip
        loss(data)
