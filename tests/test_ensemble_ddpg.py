"""EnsembleDDPGLoss: DDPG's losses by hand, and the fast path equal to TD3Loss's own path."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from test_value_expansion import A, actor_net, batch, critic_net, perturb, world_model
from torchrl.data import Bounded
from torchrl.objectives import SoftUpdate, ValueEstimators

from torchrl_rave import (
    EnsembleDDPGLoss,
    ForeachSoftUpdate,
    RAVEValueEstimator,
    STEVEEstimator,
)

GAMMA = 0.9


def make_loss(K, fast_calls=True, estimator=None):
    torch.manual_seed(3)
    loss = EnsembleDDPGLoss(
        actor_net(),
        critic_net(),
        action_spec=Bounded(-1, 1, (A,)),
        num_qvalue_nets=K,
        fast_calls=fast_calls,
    )
    SoftUpdate(loss, tau=0.05)
    perturb(loss.target_actor_network_params)
    perturb(loss.target_qvalue_network_params)
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
    for k in range(loss.num_qvalue_nets):
        td = TensorDict({"observation": obs, "action": action}, obs.shape[:-1])
        with params[k].to_module(loss.qvalue_network):
            out.append(loss.qvalue_network(td)["state_action_value"].squeeze(-1))
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
            loss.target_qvalue_network_params,
            next_obs,
            act_by_hand(loss, loss.target_actor_network_params, next_obs),
        )
        not_done = 1.0 - data["next", "terminated"].squeeze(-1).float()
        target = data["next", "reward"].squeeze(-1) + GAMMA * not_done * next_q.min(0)[0]
        q = q_by_hand(loss, loss.qvalue_network_params, data["observation"], data["action"])
        expected_critic = ((q - target) ** 2).sum(0).mean()
        pi = act_by_hand(loss, loss.actor_network_params, data["observation"])
        expected_actor = -q_by_hand(loss, loss.qvalue_network_params, data["observation"], pi)
        expected_actor = expected_actor.mean(0).mean()
    torch.testing.assert_close(out["loss_qvalue"], expected_critic)
    torch.testing.assert_close(out["loss_actor"], expected_actor)


# STEVE's mean rollouts: TD3Loss's path draws (zero-scaled) smoothing noise first, which
# would shift RAVE's sampled rollouts between the two paths.
@pytest.mark.parametrize("estimator", ["td0", "steve"])
def test_fast_path_matches_td3_path_with_gradients(estimator):
    grads, losses = {}, {}
    for fast in (True, False):
        loss = make_loss(4, fast, estimator)
        out = loss(batch(B=12, terminal=(0,)))
        (out["loss_qvalue"] + out["loss_actor"]).backward()
        losses[fast] = (out["loss_qvalue"].detach(), out["loss_actor"].detach())
        grads[fast] = [
            p.grad.clone()
            for p in (
                *loss.actor_network_params.values(True, True),
                *loss.qvalue_network_params.values(True, True),
            )
        ]
    torch.testing.assert_close(losses[True], losses[False])
    for fast_grad, td_grad in zip(grads[True], grads[False], strict=True):
        torch.testing.assert_close(fast_grad, td_grad)


def test_actor_loss_leaves_critics_alone():
    loss = make_loss(2)
    out = loss(batch(B=6))
    out["loss_actor"].backward()
    assert all(p.grad is None for p in loss.qvalue_network_params.values(True, True))
    assert all(p.grad is not None for p in loss.actor_network_params.values(True, True))


def test_fast_path_is_used_and_skips_the_unused_td3_target():
    loss = make_loss(2, estimator="rave")
    out = loss(batch(B=4))
    assert loss._fast()
    # value expansion computes its own target: no TD(0) next-state value is formed
    assert "next_state_value" not in out.keys()  # noqa: SIM118 (a TensorDict)
    assert "next_state_value" in make_loss(2)(batch(B=4)).keys()  # noqa: SIM118


@pytest.mark.parametrize("K", [1, 3])
def test_foreach_soft_update_matches_torchrl(K):
    ours, theirs = make_loss(K), make_loss(K)
    before = ours.target_qvalue_network_params.clone()
    updaters = [ForeachSoftUpdate(ours, tau=0.1), SoftUpdate(theirs, tau=0.1)]
    for step in range(3):
        for loss in (ours, theirs):
            torch.manual_seed(step)  # the same change of the online networks in both
            perturb(loss.actor_network_params)
            perturb(loss.qvalue_network_params)
        for updater in updaters:
            updater.step()
    assert not (ours.target_qvalue_network_params == before).all()
    for name in ("target_actor_network_params", "target_qvalue_network_params"):
        torch.testing.assert_close(getattr(ours, name), getattr(theirs, name), rtol=0, atol=1e-7)
