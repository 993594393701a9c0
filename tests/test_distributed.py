"""Parallel collection through TorchRL's collectors, on both worker backends: ``process``
(``MultiSyncCollector``) and ``ray`` (``RayCollector`` on a local Ray instance that this
module starts). Each delivers frames from every worker, pushes the learner's weights to
each, trains RAVE end to end, and a worker that raises or dies stops the run with a
checkpoint."""

from __future__ import annotations

import os
import re
import signal
from pathlib import Path

import pytest
import rave_mujoco
import torch
from tensordict import TensorDict
from test_recipe import TINY, make_cfg

from torchrl_rave.recipe import loop
from torchrl_rave.recipe.agent import make_actor, make_env
from torchrl_rave.recipe.checkpoint import RunCheckpoint
from torchrl_rave.recipe.collect import CollectorFailure, make_collector, push_policy_weights
from torchrl_rave.recipe.config import check_config
from torchrl_rave.recipe.episode import EpisodeCheckpoint

TESTS = Path(__file__).resolve().parent


@pytest.fixture(scope="module")
def local_ray():
    """A small local Ray instance shared by this module's Ray tests. Its workers find the
    test envs (``failing_env``) on PYTHONPATH."""
    import ray

    path = os.pathsep.join(p for p in (str(TESTS), os.environ.get("PYTHONPATH")) if p)
    ray.init(
        num_cpus=2,
        include_dashboard=False,
        runtime_env={"env_vars": {"PYTHONPATH": path, "OMP_NUM_THREADS": "1"}},
    )
    yield ray
    ray.shutdown()


@pytest.fixture(params=["process", "ray"])
def backend(request):
    """The config overrides for two workers on each backend."""
    if request.param == "ray":
        request.getfixturevalue("local_ray")
    return [f"collector.backend={request.param}", "collector.num_workers=2"]


def test_frames_from_every_worker_and_weight_push(backend):
    cfg = make_cfg(*TINY, *backend, "algorithm=rave")
    algo = check_config(cfg)
    env = make_env(cfg, torch.device("cpu"))
    _, policy = make_actor(cfg, env, algo)
    collector = make_collector(cfg, env, policy, torch.device("cpu"))

    def assert_workers_hold(weights: TensorDict) -> None:
        remotes = collector.get_distant_attr("policy")
        assert len(remotes) == 2
        for remote in remotes:
            theirs = TensorDict.from_module(remote)
            assert set(theirs.keys(True, True)) == set(weights.keys(True, True))
            for key in weights.keys(True, True):
                assert torch.equal(theirs[key], weights[key]), key

    try:
        # the workers start with the learner's weights (Ray workers build their own policy)
        assert_workers_hold(TensorDict.from_module(policy).clone())
        data = next(iter(collector))
        # stacked per worker: [workers, frames per worker]
        assert data.batch_size == (2, 50)
        first, second = data[0]["observation"], data[1]["observation"]
        assert torch.isfinite(data["observation"]).all()
        assert not torch.equal(first, second)  # two workers, two seeds, two streams
        before = TensorDict.from_module(policy).clone()
        with torch.no_grad():
            for p in policy.parameters():
                p.add_(torch.randn_like(p))
        after = TensorDict.from_module(policy).clone()
        assert not torch.equal(before["module", "0", "module", "0", "module", "0", "weight"],
                               after["module", "0", "module", "0", "module", "0", "weight"])  # fmt: skip
        if backend[0].endswith("ray"):
            # Ray workers keep their own copy until the push: the check below sees the push
            assert_workers_hold(before)
        else:
            # MultiSyncCollector moves the learner's CPU parameters into shared memory, so
            # its workers read every change at once; the push then only synchronises
            assert all(p.is_shared() for p in policy.parameters())
            assert_workers_hold(after)
        push_policy_weights(collector, policy)
        assert_workers_hold(after)
    finally:
        collector.shutdown()


def test_ray_collectors_of_one_seed_collect_alike(local_ray):
    """Two Ray collectors of one config collect the same first batch, exploration noise
    included: each actor seeds its torch generator and resets from its seeded env (Ray's
    own ``set_seed`` does neither, and an actor's first step acted from an unseeded
    reset)."""
    cfg = make_cfg(*TINY, "collector.backend=ray", "collector.num_workers=2",
                   "algorithm=ddpg", "collector.init_random_frames=0")  # fmt: skip
    cpu = torch.device("cpu")
    env = make_env(cfg, cpu)
    _, policy = make_actor(cfg, env, check_config(cfg))
    batches = []
    for _ in range(2):
        collector = make_collector(cfg, env, policy, cpu)
        try:
            batches.append(next(iter(collector)))
        finally:
            collector.shutdown()
    for key in ["observation", "action", ("next", "observation")]:
        assert torch.equal(batches[0][key], batches[1][key]), key
    assert not torch.equal(batches[0]["observation"][0], batches[0]["observation"][1])


def test_a_checkpointed_episode_continues_in_new_workers(backend):
    """Each worker's episode, next step and random state, saved between batches, go into
    the workers of a new collector, which then collect the batch the first would have
    collected next, to the last bit (exploration noise included: no random frames)."""
    cfg = make_cfg(*TINY, *backend, "algorithm=ddpg", "env.name=HalfCheetah-v5",
                   "env.action_noise=0.3", "collector.init_random_frames=0")  # fmt: skip
    cpu = torch.device("cpu")
    env = make_env(cfg, cpu)
    _, policy = make_actor(cfg, env, check_config(cfg))
    episode = EpisodeCheckpoint()
    first = make_collector(cfg, env, policy, cpu)
    try:
        episode.attach(env, first)
        batches = iter(first)
        next(batches)
        saved = episode.state_dict()
        expected = next(batches)
    finally:
        first.shutdown()
    assert saved["kept"] and [len(w["actions"]) for w in saved["workers"]] == [50, 50]
    second = make_collector(cfg, env, policy, cpu, frames_done=100)
    try:
        episode.load_state_dict(saved)
        assert episode.restore(env, second) is None
        got = next(iter(second))
    finally:
        second.shutdown()
    for key in ["observation", "action", ("next", "reward"), ("next", "observation"),
                ("next", "step_count"), ("next", "episode_reward")]:  # fmt: skip
        assert torch.equal(got[key], expected[key]), key
    assert (got["next", "step_count"][:, 0] == 51).all()  # each worker's 51st step


def test_rave_trains_with_two_workers(backend, tmp_path):
    cfg = make_cfg(*TINY, *backend, "algorithm=rave", "logger.backend=csv")
    result = rave_mujoco.train(cfg, str(tmp_path))
    assert result["frames"] == 400
    # utd 0.1 per frame collected after the 200-frame start: 20 updates
    assert result["updates"] == 20
    assert result["eval/episode_length"] >= 1


@pytest.mark.parametrize("env_id", ["FailingPendulum-v0", "DyingPendulum-v0"])
def test_failing_worker_stops_with_a_checkpoint(backend, env_id, tmp_path, capfd):
    cfg = make_cfg(*TINY, *backend, "algorithm=ddpg", f"env.name=failing_env:{env_id}")
    with pytest.raises(CollectorFailure, match=rf"{env_id} failed after frame 200: ") as failure:
        rave_mujoco.train(cfg, str(tmp_path))
    cause = str(failure.value.__cause__)
    if backend[0].endswith("process"):
        # Both workers fail on the same step. TorchRL names the one it notices first
        # ("worker 1 (exit code 1)"), or, when the other is still exiting while it shuts
        # down, says only "Cannot close a process ..."; so the error points at stderr,
        # where a worker that raised left its traceback
        assert "stderr" in str(failure.value)
        code = 1 if env_id == "FailingPendulum-v0" else 3  # DyingPendulum: os._exit(3)
        assert re.search(rf"worker [01] \(exit code {code}\)|Cannot close a process", cause)
        if env_id == "FailingPendulum-v0":
            assert "simulated simulator crash at step 150" in capfd.readouterr().err
    elif env_id == "FailingPendulum-v0":  # Ray carries the worker's traceback to the learner
        assert "simulated simulator crash at step 150" in cause
    else:
        assert "actor died" in cause
    counters = RunCheckpoint(tmp_path).read("counters")
    # each worker collects 50 frames per batch and fails on its 150th step: two whole
    # batches made it into the buffer and the checkpoint
    assert counters["frames"] == 200
    # DDPG updates start after init_random_frames (100): utd 0.1 x 100 frames
    assert counters["updates"] == 10


def test_a_worker_dead_between_batches_stops_the_run_with_a_checkpoint(tmp_path, monkeypatch):
    """A worker process killed while the learner trains on its batch (SIGKILL, as the
    kernel's OOM killer sends it) left the weight push after that batch waiting for its
    answer forever. The run now stops with ``CollectorFailure`` naming the worker, and a
    checkpoint of everything up to that batch."""
    made, make, update = [], loop.make_collector, loop.update_on_batch

    def make_collector(*args, **kwargs):
        made.append(make(*args, **kwargs))
        return made[-1]

    def update_on_batch(cfg, learner, counters, n_frames, **kwargs):
        out = update(cfg, learner, counters, n_frames, **kwargs)
        if counters["frames"] == 200:
            worker = made[0].procs[1]
            os.kill(worker.pid, signal.SIGKILL)
            worker.join(30)
        return out

    monkeypatch.setattr(loop, "make_collector", make_collector)
    monkeypatch.setattr(loop, "update_on_batch", update_on_batch)
    cfg = make_cfg(*TINY, "collector.backend=process", "collector.num_workers=2", "algorithm=ddpg")
    with pytest.raises(CollectorFailure, match=r"after frame 200: worker 1 \(exit code -9\) died"):
        rave_mujoco.train(cfg, str(tmp_path))
    counters = RunCheckpoint(tmp_path).read("counters")
    assert counters["frames"] == 200 and counters["updates"] == 10


def test_bad_worker_settings_are_refused():
    with pytest.raises(ValueError, match="collector.num_workers.*backend=process or ray"):
        check_config(make_cfg(*TINY, "collector.num_workers=2"))
    with pytest.raises(ValueError, match="frames_per_batch.*multiple of collector.num_workers"):
        check_config(make_cfg(*TINY, "collector.backend=ray", "collector.num_workers=3"))
    with pytest.raises(ValueError, match="collector.backend"):
        check_config(make_cfg(*TINY, "collector.backend=threads"))
    with pytest.raises(ValueError, match="collector.weight_sync_every"):
        check_config(make_cfg(*TINY, "collector.weight_sync_every=0"))
    ray = ["collector.backend=ray", "collector.num_workers=2"]
    for override, key in [
        ("ray.worker_cpus=0", "ray.worker_cpus"),
        ("ray.num_cpus=0", "ray.num_cpus"),
        ("ray.worker_memory=-1", "ray.worker_memory"),
        ("ray.worker_resources={actors:0}", "ray.worker_resources"),
    ]:
        with pytest.raises(ValueError, match=rf"config key {key}="):
            check_config(make_cfg(*TINY, *ray, override))
    # more workers than a local instance has CPUs would wait forever
    too_many = ["collector.backend=ray", "collector.num_workers=4", "ray.num_cpus=2"]
    with pytest.raises(ValueError, match=r"ray.worker_cpus=1(\.0)? .* = 4 CPU <= the 2 CPU of"):
        check_config(make_cfg(*TINY, *too_many))
    check_config(make_cfg(*TINY, *too_many, "ray.worker_cpus=0.5"))  # fits
    # a resource no node has
    with pytest.raises(ValueError, match=r"ray.worker_resources.* = 2 actors <= the 0 actors"):
        check_config(make_cfg(*TINY, *ray, "ray.worker_resources={actors:1}"))


def test_ray_backend_without_ray_names_the_fix(monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real(name, *a)
    )
    with pytest.raises(
        ValueError, match=r"needs the 'ray' package: pip install 'torchrl-rave\[ray\]'"
    ):
        check_config(make_cfg(*TINY, "collector.backend=ray", "collector.num_workers=2"))


@pytest.mark.parametrize(("every", "pushed_at"), [(1, [200, 300, 400]), (15, [300])])
def test_weights_are_pushed_once_enough_updates_are_new(every, pushed_at, monkeypatch, tmp_path):
    """DDPG (TINY) makes 10 updates per 100-frame batch from frame 200 on; with
    weight_sync_every=15 only the batch that brings the new updates to 20 pushes."""
    events = []
    real = loop.push_or_stop

    def counting(collector, policy, *args):
        events.append("push")
        real(collector, policy, *args)

    real_update = loop.update_on_batch

    def update(cfg, learner, counters, n_frames, **kwargs):  # each batch, before its push
        events.append(counters["frames"])
        return real_update(cfg, learner, counters, n_frames, **kwargs)

    monkeypatch.setattr(loop, "push_or_stop", counting)
    monkeypatch.setattr(loop, "update_on_batch", update)
    cfg = make_cfg(*TINY, "algorithm=ddpg", f"collector.weight_sync_every={every}")
    assert rave_mujoco.train(cfg, str(tmp_path))["updates"] == 30
    batches = [e for e in events if e != "push"]
    assert batches == [100, 200, 300, 400]
    # the batch a push belongs to is the update call just before it
    pushes = [events[k - 1] for k, e in enumerate(events) if e == "push"]
    assert pushes == pushed_at
