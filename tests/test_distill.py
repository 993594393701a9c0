"""Noisy-target distillation: a known policy recovered from synthetic data while the
noised target input is ignored, and the command on a real run, whose output trains on."""

from __future__ import annotations

import json

import distill
import pytest
import rave_mujoco
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from test_recipe import TINY, make_cfg
from torchrl.modules import MLP

from torchrl_rave.recipe import load_policy
from torchrl_rave.recipe.distill import distill_actor


def actor(in_features: int = 6) -> TensorDictModule:
    net = torch.nn.Sequential(
        MLP(in_features=in_features, out_features=2, num_cells=[64, 64]), torch.nn.Tanh()
    )
    return TensorDictModule(net, in_keys=["observation"], out_keys=["action"])


def act(module, obs: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return module(TensorDict(observation=obs, batch_size=[len(obs)]))["action"]


def test_a_known_policy_is_recovered_and_the_noised_target_ignored():
    """The teacher reads the four body entries. In the data the two target entries copy
    two body entries, so they carry what the teacher uses: fitted on the data as they are,
    a student may lean on them; with them noised over [-3, 3] it must not."""
    g = torch.Generator().manual_seed(0)
    w = torch.randn(4, 2, generator=g)
    body = torch.randn(4000, 4, generator=g)
    obs = torch.cat([body, body[:, :2]], 1)  # target entries 4, 5 = body entries 0, 1
    teacher = torch.tanh(body @ w * 0.5)
    torch.manual_seed(0)
    student = actor()
    losses = distill_actor(student, obs, teacher, slice(4, 6), -3.0, 3.0, steps=1500,
                           generator=torch.Generator().manual_seed(1))  # fmt: skip
    assert losses[-1] < 0.02 * losses[0]
    test_body = torch.randn(500, 4, generator=g)
    truth = torch.tanh(test_body @ w * 0.5)
    for target in (test_body[:, :2], torch.full((500, 2), -2.5), torch.full((500, 2), 2.5)):
        predicted = act(student, torch.cat([test_body, target], 1))
        assert (predicted - truth).pow(2).mean() < 0.01 * truth.var()  # whatever the target
    # bad input is named
    with pytest.raises(ValueError, match="as many actions as observations"):
        distill_actor(student, obs, teacher[:10], slice(4, 6), -1.0, 1.0, steps=1)
    with pytest.raises(ValueError, match="selects nothing"):
        distill_actor(student, obs, teacher, slice(6, 9), -1.0, 1.0, steps=1)


def test_the_command_writes_a_run_that_trains_on(tmp_path):
    run, out = tmp_path / "run", tmp_path / "distilled"
    args = [*TINY, "algorithm=ddpg", "eval.episodes=1"]
    rave_mujoco.train(make_cfg(*args, "collector.total_frames=200"), str(run))
    before = sorted(p.name for p in (run / "checkpoints").iterdir())
    result = distill.main([str(run), "--out", str(out), "--target", "0:1", "--frames", "300",
                           "--steps", "300"])  # fmt: skip
    assert result["pairs"] == 300 and result["last_loss"] < result["first_loss"]
    assert json.loads((out / "distill.json").read_text())["target"] == [0, 1]
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == before  # source untouched
    # the distilled policy acts like the source on the states it was fitted on
    source, fitted = load_policy(run), load_policy(out)
    obs = torch.randn(256, 4) * 0.05
    obs[:, 0] = 0.0
    a, b = act(source, obs), act(fitted, obs)
    assert (a - b).abs().mean() < 0.2 * a.abs().mean() + 0.02
    # InvertedPendulum names no target part of its observation: --target is needed
    with pytest.raises(ValueError, match="names no target part"):
        distill.main([str(run), "--out", str(tmp_path / "auto"), "--frames", "10"])
    assert not (tmp_path / "auto").exists()
    # bad counts and ranges are named before the run is read or a pair collected
    with pytest.raises(ValueError, match=r"frames=0: expected an integer >= 1; steps=-1: "
                                         r".*low=1.0, high=0.0: .*low <= high"):  # fmt: skip
        distill.main([str(tmp_path / "none"), "--out", str(tmp_path / "bad"), "--frames", "0",
                      "--steps", "-1", "--low", "1", "--high", "0"])  # fmt: skip
    assert not (tmp_path / "bad").exists()
    with pytest.raises(FileExistsError, match="not empty"):
        distill.main([str(run), "--out", str(out), "--target", "0:1"])
    # training goes on from it
    results = rave_mujoco.train(make_cfg(*args, f"resume={out}", "collector.total_frames=300"), "x")
    assert results["frames"] == 300 and results["updates"] > 0


def test_bad_ranges_and_slices_are_named(tmp_path, capsys):
    """The probes: an infinite range wrote a NaN policy and exited 0; ``--target a:b``
    ended in an ``int()`` traceback."""
    with pytest.raises(ValueError, match="low=-inf: expected a finite number.*high=inf"):
        distill.main([str(tmp_path / "none"), "--out", str(tmp_path / "bad"), "--target", "0:1",
                      "--low=-inf", "--high=inf"])  # fmt: skip
    with pytest.raises(SystemExit):
        distill.main([str(tmp_path / "none"), "--out", str(tmp_path / "bad"), "--target", "a:b"])
    assert "'a:b': expected START:STOP" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()
