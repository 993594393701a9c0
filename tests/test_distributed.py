"""Parallel collection: the process backend (TorchRL's MultiSyncCollector) delivers frames
from every worker, pushes the learner's weights to each, trains end to end, and a failing
worker stops the run with a checkpoint."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recipes"))
import rave_mujoco  # noqa: E402
import utils as recipe_utils  # noqa: E402
from test_recipe import TINY, make_cfg  # noqa: E402

PROCESS = ["collector.backend=process", "collector.num_workers=2"]


def test_frames_from_every_worker_and_weight_push():
    cfg = make_cfg(*TINY, *PROCESS, "algorithm=rave")
    algo = recipe_utils.check_config(cfg)
    env = recipe_utils.make_env(cfg, torch.device("cpu"))
    _, policy = recipe_utils.make_actor(cfg, env, algo)
    collector = recipe_utils.make_collector(cfg, env, policy, torch.device("cpu"))
    try:
        data = next(iter(collector))
        # stacked per worker: [workers, frames per worker]
        assert data.batch_size == (2, 50)
        first, second = data[0]["observation"], data[1]["observation"]
        assert torch.isfinite(data["observation"]).all()
        assert not torch.equal(first, second)  # two workers, two seeds, two streams
        with torch.no_grad():
            for p in policy.parameters():
                p.add_(torch.randn_like(p))
        collector.update_policy_weights_()
        learner = TensorDict.from_module(policy)
        for remote in collector.get_distant_attr("policy"):
            theirs = TensorDict.from_module(remote)
            for key in learner.keys(True, True):
                assert torch.equal(theirs[key], learner[key]), key
    finally:
        collector.shutdown()


def test_rave_trains_with_two_process_workers(tmp_path):
    cfg = make_cfg(*TINY, *PROCESS, "algorithm=rave")
    result = rave_mujoco.train(cfg, str(tmp_path))
    assert result["frames"] == 400
    # utd 0.1 per frame collected after the 200-frame start: 20 updates
    assert result["updates"] == 20
    assert result["eval/episode_length"] >= 1


def test_bad_worker_settings_are_refused():
    with pytest.raises(ValueError, match="collector.num_workers.*backend=process"):
        recipe_utils.check_config(make_cfg(*TINY, "collector.num_workers=2"))
    with pytest.raises(ValueError, match="frames_per_batch.*multiple of collector.num_workers"):
        recipe_utils.check_config(make_cfg(*TINY, *PROCESS[:1], "collector.num_workers=3"))
    with pytest.raises(ValueError, match="collector.backend"):
        recipe_utils.check_config(make_cfg(*TINY, "collector.backend=threads"))


def test_failing_worker_stops_with_a_checkpoint(tmp_path):
    cfg = make_cfg(*TINY, *PROCESS, "algorithm=ddpg", "env.name=failing_env:FailingPendulum-v0")
    with pytest.raises(
        recipe_utils.CollectorFailure,
        match=r"FailingPendulum-v0 failed after frame 200: .*worker 0",
    ):
        rave_mujoco.train(cfg, str(tmp_path))
    state = torch.load(
        recipe_utils.Checkpointer(tmp_path).latest() / "state.pt", weights_only=False
    )
    # each worker collects 50 frames per batch and crashes on its 150th step: two whole
    # batches made it into the buffer and the checkpoint
    assert state["counters"]["frames"] == 200
