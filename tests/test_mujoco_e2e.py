"""End to end on real MuJoCo -v5 data collected through TorchRL."""

from __future__ import annotations

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import DoubleToFloat, GymEnv, TransformedEnv
from torchrl.modules import MLP, Actor, ValueOperator
from torchrl.objectives import SoftUpdate, TD3Loss

from torchrl_rave import (
    EnsembleDDPGLoss,
    RAVEValueEstimator,
    WorldModelEnsemble,
    WorldModelEnsembleLoss,
)
from torchrl_rave.modules.world_model import network_sizes


@pytest.fixture(scope="module", params=["Hopper-v5", "HalfCheetah-v5"])
def mujoco_batch(request):
    torch.manual_seed(0)
    env = TransformedEnv(GymEnv(request.param), DoubleToFloat())
    collector = Collector(env, policy=None, frames_per_batch=200, total_frames=400)
    rb = TensorDictReplayBuffer(storage=LazyTensorStorage(1000), batch_size=64)
    for data in collector:
        rb.extend(data.reshape(-1))
    collector.shutdown()
    return env, rb


def build(env, N=4, width=32):
    S = env.observation_spec["observation"].shape[-1]
    A = env.action_spec.shape[-1]
    wm = WorldModelEnsemble.from_specs(
        env.observation_spec,
        env.action_spec,
        num_models=N,
        **network_sizes(transition=(width, 3), reward=(width, 2), termination=(width, 2)),
    )
    actor = Actor(
        torch.nn.Sequential(MLP(in_features=S, out_features=A, num_cells=[width]), torch.nn.Tanh()),
        spec=env.action_spec,
    )
    qvalue = ValueOperator(
        MLP(in_features=S + A, out_features=1, num_cells=[width]), in_keys=["observation", "action"]
    )
    return wm, actor, qvalue


def test_world_model_and_rave_losses_on_mujoco(mujoco_batch):
    env, rb = mujoco_batch
    assert len(rb) == 400
    wm, actor, qvalue = build(env)
    wm.update_normalizers_from(rb[:])
    wm_loss = WorldModelEnsembleLoss(wm)
    opt = torch.optim.Adam(wm.parameters(), lr=1e-3)
    first = None
    for _ in range(30):
        out = wm_loss(rb.sample())
        total = out["loss_transition"] + out["loss_reward"] + out["loss_termination"]
        opt.zero_grad()
        total.backward()
        opt.step()
        first = out["transition_mse"].item() if first is None else first
    assert out["transition_mse"].item() < first  # it learns from real data

    batch = rb.sample()
    for loss in (
        EnsembleDDPGLoss(actor, qvalue, num_value_nets=4),
        TD3Loss(actor, qvalue, action_spec=env.action_spec, num_qvalue_nets=4),
    ):
        SoftUpdate(loss, tau=0.01)
        loss.make_value_estimator(
            RAVEValueEstimator.for_loss(loss, world_model=wm, gamma=0.99, horizon=3)
        )
        td = batch.clone()
        out = loss(td)
        names = [k for k in out.keys() if k.startswith("loss_")]  # noqa: SIM118 (iterating a TensorDict walks its batch)
        total = sum(out[k] for k in names)
        assert torch.isfinite(total)
        total.backward()
        grads = [p.grad for p in loss.parameters() if p.grad is not None]
        assert grads and all(torch.isfinite(g).all() for g in grads)
        assert any(g.abs().sum() > 0 for g in grads)
        # both losses hand the estimator a shallow copy of the batch
        diag = loss.value_estimator.diagnostics
        assert diag["rave_horizon_weights"].shape == (64, 4)
        torch.testing.assert_close(diag["rave_horizon_weights"].sum(-1), torch.ones(64))
        assert ((diag["rave_alpha"] >= 0) & (diag["rave_alpha"] <= 1.5)).all()
        assert (diag["rave_horizon_variance"] >= 0).all()
