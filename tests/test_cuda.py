"""The CUDA path, checked against the CPU: the estimator against the naive reference, each
algorithm's full update against the same update on the CPU, the compiled updates (CUDA
graphs, ``compile.mode=reduce-overhead``) against eager ones, a device-resident replay
buffer, and the recipe end to end with a checkpoint that loads on either device.

Marked ``gpu`` and skipped where ``torch.cuda.is_available()`` is false, so CI (CPU only)
skips the file; on a GPU machine ``pytest -m gpu -n 0`` runs it.
"""

from __future__ import annotations

import pytest
import rave_mujoco
import torch
import update_throughput as bench
from tensordict import TensorDict
from test_compile import SMALL
from test_recipe import TINY, make_cfg, read_scalar
from test_value_expansion import actor_net, batch, critic_net, naive_target, world_model

import torchrl_rave.modules.world_model as world_model_module
from torchrl_rave import ValueExpansionEstimator
from torchrl_rave.objectives.world_model_loss import WorldModelEnsembleLoss
from torchrl_rave.recipe.agent import load_agent, make_replay_buffer
from torchrl_rave.trainers import SeedStreams

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]
CUDA, CPU = torch.device("cuda"), torch.device("cpu")


@pytest.fixture(autouse=True)
def exact_float32_matmuls():
    """TF32 would round matmul inputs to 10 bits: the comparisons below are float32 ones."""
    before = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = before


@pytest.mark.parametrize("N,K,H", [(1, 1, 1), (4, 4, 3)])
@pytest.mark.parametrize("alpha_mode", ["constant", "adaptive"])
def test_estimator_on_cuda_matches_the_naive_reference(N, K, H, alpha_mode):
    wm, actor = world_model(N), actor_net()
    critics = [critic_net() for _ in range(K)]
    params = TensorDict.from_modules(*critics, as_module=True)
    data = batch(B=6, terminal=(1,))
    with torch.no_grad():
        if alpha_mode == "constant":
            alpha = torch.full((6,), 0.7)
        else:
            error = wm.mean_prediction_error(
                data["observation"], data["action"], data["next", "observation"]
            )
            alpha = (0.7 * (1 - error)).clamp_min(0)
        ref = naive_target(wm, actor, critics[0], params, data, 0.9, H, alpha, "inverse_variance")
    est = ValueExpansionEstimator(
        world_model=wm.to(CUDA),
        actor_network=actor.to(CUDA),
        value_network=critics[0].to(CUDA),
        value_params=params.to(CUDA),
        gamma=0.9,
        horizon=H,
        rollout="mean",
        alpha=0.7,
        alpha_mode=alpha_mode,
    )
    ours = est.value_estimate(data.to(CUDA)).squeeze(-1)
    assert ours.device.type == "cuda"
    torch.testing.assert_close(ours.cpu(), ref, rtol=1e-5, atol=1e-5)


@pytest.fixture
def draws_from_the_cpu(monkeypatch):
    """Bootstrap indices and rollout noise drawn from torch's CPU generator on either
    device, so a CPU and a CUDA update see the same random numbers."""

    def indices(self, batch_size, device=None):
        n = self.world_model.num_models
        if not self.bootstrap:
            return torch.arange(batch_size, device=device).expand(n, batch_size)
        return torch.randint(batch_size, (n, batch_size)).to(device)

    def draw(mean, logvar, sample):
        if not sample:
            return mean
        noise = torch.randn(mean.shape, dtype=mean.dtype).to(mean.device)
        return mean + noise * (0.5 * logvar).exp()

    monkeypatch.setattr(WorldModelEnsembleLoss, "bootstrap_indices", indices)
    monkeypatch.setattr(world_model_module, "_draw", draw)


def _three_updates(algorithm, overrides, device, seed=1):
    data = bench.batches(32, device, count=3)
    step, _, loss = bench.recipe_update(algorithm, [*SMALL, *overrides], device)
    torch.manual_seed(seed)
    for b in data:
        step(b)
    return {k: v.detach().cpu().clone() for k, v in loss.named_parameters()}


@pytest.mark.parametrize("algorithm", ["ddpg", "steve", "rave"])
def test_full_update_on_cuda_matches_the_cpu(algorithm, draws_from_the_cpu):
    """World-model step, K critics, actor and soft update, three times, on each device."""
    cpu = _three_updates(algorithm, [], CPU)
    cuda = _three_updates(algorithm, [], CUDA)
    assert cpu.keys() == cuda.keys()
    for name, value in cpu.items():
        torch.testing.assert_close(cuda[name], value, rtol=1e-4, atol=1e-5, msg=name)
    # three updates moved the parameters: the comparison is not between two initialisations
    _, _, fresh = bench.recipe_update(algorithm, SMALL, CPU)
    assert any(not torch.equal(p, cpu[n]) for n, p in fresh.named_parameters())


@pytest.mark.parametrize("algorithm", ["ddpg", "rave"])
@pytest.mark.parametrize("mode", ["default", "reduce-overhead"])
def test_compiled_updates_on_cuda_match_eager(algorithm, mode):
    """``reduce-overhead`` replays CUDA graphs: several replays must still match eager."""
    eager = _three_updates(algorithm, [], CUDA)
    compiled = _three_updates(algorithm, ["compile.enabled=true", f"compile.mode={mode}"], CUDA)
    for name, value in eager.items():
        torch.testing.assert_close(compiled[name], value, rtol=1e-4, atol=1e-5, msg=name)


def test_replay_buffer_on_cuda_samples_on_cuda():
    cfg = make_cfg(*TINY)
    rb = make_replay_buffer(cfg, CUDA)
    data = bench.batches(64, CPU, count=1)[0]
    rb.extend(data)
    sample = rb.sample(32)
    assert sample["observation"].device.type == "cuda"
    assert sample["next", "reward"].device.type == "cuda"
    # every sampled row is one of the stored rows
    stored = data["observation"].to(CUDA)
    assert (sample["observation"][:, None] == stored[None]).all(-1).any(-1).all()


@pytest.mark.parametrize(
    "overrides",
    [
        ["algorithm=rave"],
        ["algorithm=rave", "compile.enabled=true", "compile.mode=reduce-overhead"],
        ["algorithm=steve", "preset=paper"],
    ],
    ids=["rave", "rave-reduce-overhead", "steve-paper"],
)
def test_recipe_trains_on_cuda(overrides, tmp_path):
    tiny = TINY if "preset=paper" not in overrides else [o for o in TINY if "cells" not in o]
    cfg = make_cfg(*overrides, *tiny, "collector.device=cuda")
    results = rave_mujoco.train(cfg, str(tmp_path))
    assert results["frames"] == 400
    assert results["updates"] == int(0.1 * (400 - 200))
    algo = cfg.algorithm
    assert [step for step, _ in read_scalar(tmp_path, "eval/return", algo)] == [200, 400]
    assert all(torch.isfinite(torch.tensor(v)) for _, v in read_scalar(
        tmp_path, "train/loss_critic", algo))  # fmt: skip
    # the checkpoint written on the GPU loads on either device, with equal parameters
    _, on_cuda = load_agent(tmp_path, CUDA)
    _, on_cpu = load_agent(tmp_path, CPU)
    cuda_params = dict(on_cuda.loss.named_parameters())
    assert next(iter(cuda_params.values())).device.type == "cuda"
    for name, p in on_cpu.loss.named_parameters():
        assert p.device.type == "cpu"
        assert torch.equal(p, cuda_params[name].cpu()), name


def test_seed_streams_swap_the_cuda_generator():
    """On a GPU each seed's stream holds the CUDA generator's state too."""
    streams = SeedStreams(2, CUDA)
    for i in range(2):
        torch.manual_seed(20 + i)  # seeds the CPU and every CUDA generator
        streams.capture(i)
    with streams.use(1):
        one = torch.rand(5, device=CUDA)
    with streams.use(0):
        zero = torch.rand(5, device=CUDA)
    with streams.use(1):
        one_more = torch.rand(5, device=CUDA)
    torch.manual_seed(21)
    assert torch.equal(torch.cat([one, one_more]), torch.rand(10, device=CUDA))
    torch.manual_seed(20)
    assert torch.equal(zero, torch.rand(5, device=CUDA))


@pytest.mark.parametrize("algorithm", ["rave", "sac"])
def test_a_seed_group_trains_on_cuda(algorithm, tmp_path):
    """``seeds=[0,1]`` on the GPU: both seeds train and evaluate, and each seed's first
    logged critic loss is its single CUDA run's (its own stream; batched kernels round
    differently, so to 1e-2)."""
    overrides = [*TINY, f"algorithm={algorithm}", "collector.device=cuda"]
    rave_mujoco.train(make_cfg(*overrides, "seeds=[0,1]"), str(tmp_path / "group"))
    rave_mujoco.train(make_cfg(*overrides, "env.seed=1"), str(tmp_path / "one"))
    for seed in (0, 1):
        run = tmp_path / "group" / f"seed{seed}"
        assert [step for step, _ in read_scalar(run, "eval/return", algorithm)] == [200, 400]
        losses = [v for _, v in read_scalar(run, "train/loss_critic", algorithm)]
        assert losses and all(torch.isfinite(torch.tensor(losses)))
    grouped = read_scalar(tmp_path / "group" / "seed1", "train/loss_critic", algorithm)[0][1]
    single = read_scalar(tmp_path / "one", "train/loss_critic", algorithm)[0][1]
    assert grouped == pytest.approx(single, rel=1e-2)


def test_the_readmes_swap_runs_with_models_on_the_gpu_and_the_buffer_on_the_cpu(capsys):
    """The README's block is shaped as TorchRL's sota scripts are: models on
    ``get_available_device()`` (here the GPU), the replay buffer on the CPU; the world
    model's trainer moves what it samples."""
    import test_readme

    test_readme.test_use_rave_in_your_own_loss(capsys)
