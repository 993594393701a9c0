"""envs.EpisodeReplay: an episode in progress rebuilt in a fresh env, step for step; and
the recipe's runs, killed mid-episode and resumed, give the numbers of the run that was
never stopped."""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
import terms_env  # noqa: F401  registers TermsPendulum-v0
import torch
from test_recipe import TINY, kill_after_first_checkpoint, make_cfg
from test_seed_group_recipe import scalars
from torchrl.envs.utils import RandomPolicy

from torchrl_rave.envs import ActuatorNoise, EpisodeReplay, EpisodeReplayError, import_env_family
from torchrl_rave.recipe import loop
from torchrl_rave.recipe.agent import make_env
from torchrl_rave.recipe.checkpoint import RunCheckpoint
from torchrl_rave.recipe.collect import make_collector
from torchrl_rave.recipe.episode import EpisodeCheckpoint, EpisodeNotRestored
from torchrl_rave.recipe.loop import train


def play_until(env: gym.Env, rng: np.random.Generator, ends: int, then: int) -> np.ndarray:
    """Random actions until ``ends`` episodes have ended, then ``then`` steps more; the
    last observation."""
    while ends:
        ends -= sum(len(step) == 1 for step in play(env, rng, 1))
    return play(env, rng, then)[-1][0]


def play(env: gym.Env, rng: np.random.Generator, steps: int) -> list:
    """``steps`` random actions, resetting at each episode's end; every step's output."""
    out = []
    space = env.action_space
    for _ in range(steps):
        middle = rng.uniform(0.3, 0.7, space.shape)  # of the action box
        step = env.step((space.low + (space.high - space.low) * middle).astype(space.dtype))
        out.append(step[:4])
        if step[2] or step[3]:
            out.append(env.reset()[:1])
    return out


def same(a: list, b: list) -> bool:
    return len(a) == len(b) and all(
        all(np.array_equal(x, y) for x, y in zip(p, q, strict=True))
        for p, q in zip(a, b, strict=True)
    )


@pytest.mark.parametrize(
    "name, sigma, ends, steps",
    [
        ("Hopper-v5", 0.3, 2, 80),
        ("Hopper-v5", 0.0, 2, 80),
        ("Humanoid-v5", 0.3, 2, 80),
        ("HopperBulletEnv-v0", 0.3, 2, 80),
        ("LearnToRun-v0", 0.0, 0, 15),  # OpenSim: 15-40 ms a step
    ],
    ids=["hopper-noise", "hopper", "humanoid-noise", "bullet-hopper-noise", "learn-to-run"],
)
def test_a_replayed_episode_continues_as_the_original(name, sigma, ends, steps):
    """A fresh env, differently seeded and already stepped, given the recorded episode,
    then goes on exactly as the original: observations, rewards and episode ends, across
    later resets (its reset stream restored) and with the actuator noise's stream
    restored. Humanoid's reward reads quantities MuJoCo derived during the previous step
    (the centre of mass before the step), which restoring the integration state alone
    would not give back; PyBullet and OpenSim keep their own simulator state."""
    import_env_family(name)

    def make():
        env = gym.make(name)
        return EpisodeReplay(ActuatorNoise(env, sigma) if sigma else env)

    rng = np.random.default_rng(0)
    env = make()
    env.reset(seed=1)
    seen = play_until(env, rng, ends=ends, then=7)
    state = env.episode_state()
    assert len(state["actions"]) == 7  # mid-episode, after resets from the moved stream
    twin = make()
    twin.reset(seed=99)
    play(twin, np.random.default_rng(5), 10)
    last = twin.replay(state)
    after = rng.bit_generator.state
    original = play(env, rng, steps)
    rng.bit_generator.state = after
    assert same(play(twin, rng, steps), original)
    np.testing.assert_array_equal(last, seen)  # where the original was
    if not ends:
        return
    # a fresh env seeded as the original was and given the same actions is not enough:
    # the reset stream had moved on, and so had the noise's
    naive = make()
    naive.reset(seed=1)
    for action in state["actions"].astype(np.float32):
        naive.step(action)
    rng.bit_generator.state = after
    assert not same(play(naive, rng, 80), original)


def test_what_cannot_be_replayed_is_named():
    env = EpisodeReplay(ActuatorNoise(gym.make("Hopper-v5"), 0.3))
    env.reset(seed=0)
    play(env, np.random.default_rng(0), 5)
    state = env.episode_state()
    with pytest.raises(EpisodeReplayError, match=r"generators .* not those of the recorded"):
        EpisodeReplay(gym.make("Hopper-v5")).replay(state)
    with pytest.raises(EpisodeReplayError, match=r"shape \(3,\), this env's \(6,\)"):
        EpisodeReplay(ActuatorNoise(gym.make("HalfCheetah-v5"), 0.3)).replay(state)
    # an unseeded first reset drew its generators from fresh entropy: not replayable
    fresh = EpisodeReplay(gym.make("Hopper-v5"))
    fresh.reset()
    with pytest.raises(EpisodeReplayError, match="not those of the recorded"):
        EpisodeReplay(gym.make("Hopper-v5")).replay(fresh.episode_state())
    # what no recording holds
    for key, value, message in [
        ("dtype", "O", "actions of dtype object"),
        ("reset", {**state["reset"], "seed": "0"}, "seed '0'"),
        ("reset", {**state["reset"], "generators": {"0._rng": {"bit_generator": "PCG64"}}},
         "generator 0._rng: unusable recorded state"),
        ("actions", "many", "not a recorded episode"),
    ]:  # fmt: skip
        with pytest.raises(EpisodeReplayError, match=message):
            EpisodeReplay(ActuatorNoise(gym.make("Hopper-v5"), 0.3)).replay({**state, key: value})
    # an env that is not deterministic given its generators: its episode ends early
    first = EpisodeReplay(Moody())
    first.reset(seed=0)
    for _ in range(3):
        first.step(np.zeros(1, dtype=np.float32))
    with pytest.raises(EpisodeReplayError, match="ended at step 1 of 3"):
        EpisodeReplay(Moody()).replay(first.episode_state())


class Moody(gym.Env):
    """Episodes of 4 steps in the first instance made, 1 step in every later one."""

    made = 0
    observation_space = gym.spaces.Box(-1.0, 1.0, (1,))
    action_space = gym.spaces.Box(-1.0, 1.0, (1,))

    def __init__(self):
        self.length = 4 if Moody.made == 0 else 1
        Moody.made += 1

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(1, dtype=np.float32), {}

    def step(self, action):
        self.t += 1
        return np.zeros(1, dtype=np.float32), 0.0, self.t >= self.length, False, {}


def test_an_episode_past_max_steps_is_not_kept():
    env = EpisodeReplay(gym.make("HalfCheetah-v5"), max_steps=10)
    assert env.episode_state() is None  # no reset yet
    env.reset(seed=0)
    play(env, np.random.default_rng(0), 10)
    assert len(env.episode_state()["actions"]) == 10
    play(env, np.random.default_rng(0), 1)
    assert env.episode_state() is None and env.why_not == "longer than max_steps=10"
    env.reset()
    assert len(env.episode_state()["actions"]) == 0
    with pytest.raises(ValueError, match="max_steps=-1"):
        EpisodeReplay(gym.make("HalfCheetah-v5"), max_steps=-1)


# ---------------------------------------------------------------- through the recipe

# HalfCheetah's episodes end at their time limit only, here 400 steps: a checkpoint at 300
# or 700 frames is mid-episode, and the episode's end, after the resume, draws the next
# reset from the restored stream
CHEETAH = [*TINY, "algorithm=ddpg", "env.name=HalfCheetah-v5", "env.action_noise=0.3",
           "env.kwargs={max_episode_steps:400}", "collector.total_frames=900",
           "checkpoint.interval=300", "eval.interval=900", "eval.episodes=1",
           "threads=1"]  # fmt: skip


@pytest.mark.parametrize(
    "group, workers", [(None, 0), ([0, 1], 0), (None, 2)], ids=["run", "group", "process"]
)
def test_a_run_killed_mid_episode_resumes_as_if_never_stopped(group, workers, tmp_path):
    """SIGKILL a run (or a seed group, or a run of two worker processes) after its first
    checkpoint and resume it: every metric it logs (the training episodes' returns, the
    losses, the evaluations) equals that of the same run never stopped, to the last bit;
    the checkpoint it resumed from kept the episode (each worker's, with its random
    state, which draws its exploration noise)."""
    overrides = CHEETAH if group is None else [*CHEETAH, f"seeds={group}"]
    if workers:
        overrides = [*overrides, "collector.backend=process", f"collector.num_workers={workers}"]
    runs = [""] if group is None else [f"seed{s}" for s in group]
    whole = tmp_path / "whole"
    train(make_cfg(*overrides), str(whole))
    killed = tmp_path / "killed"
    frames = kill_after_first_checkpoint(overrides, killed, runs)
    assert frames in (300, 600)
    for c in (RunCheckpoint(killed / run) for run in runs):
        episode = c.read("episode", c.root / f"checkpoint-{frames:012d}")
        assert episode["kept"]
        if workers:  # each worker took half of every batch's steps
            assert [len(w["actions"]) for w in episode["workers"]] == [frames // 2 % 400] * 2
            assert not torch.equal(*(w["rng"] for w in episode["workers"]))
        else:
            assert len(episode["actions"]) == frames % 400
    with warnings.catch_warnings():
        warnings.simplefilter("error", EpisodeNotRestored)
        train(make_cfg(*overrides, f"resume={killed}"), "unused")
    for run in runs:
        expected = scalars(whole / run / "ddpg")
        # a batch logged by the killed start and again by the resumed one has two rows,
        # alike; NaN equals NaN here (no evaluation state is far enough from a 400-step
        # limit for the value-error metrics)
        resumed = {}
        for name, rows in scalars(killed / run / "ddpg").items():
            by_step = {}
            for step, value in rows:
                by_step.setdefault(step, []).append(value)
            for step, values in by_step.items():
                np.testing.assert_equal(values, values[:1] * len(values), f"{name} {step}")
            resumed[name] = [(step, values[-1]) for step, values in by_step.items()]
        np.testing.assert_equal(resumed, expected)
        # a worker's episode ends at its own 400th step
        ends = [800] if workers else [400, 800]
        assert [s for s, _ in expected["train/episode_reward"]] == ends


def test_workers_behind_the_learners_weights_resume_at_a_new_episode(tmp_path, monkeypatch):
    """A CPU learner's process workers act with its own weights (in shared memory), so
    their episodes are kept whatever ``collector.weight_sync_every``. Workers that hold
    copies (a GPU learner's, here made so) and act with older weights than the learner's
    keep no episode: a resumed run pushes the current weights, so it could not act as the
    run never stopped. It resumes at a new episode and says why."""
    overrides = [*TINY, "algorithm=ddpg", "collector.backend=process", "collector.num_workers=1",
                 "collector.weight_sync_every=1000", "replay_buffer.size=1000"]  # fmt: skip
    shared = tmp_path / "shared"
    train(make_cfg(*overrides), str(shared))
    c = RunCheckpoint(shared)
    assert c.read("episode", c.root / "checkpoint-000000000200")["kept"]
    # a workers' episode goes back to workers only, as many as kept it
    for collector, why in [
        (["collector.backend=direct", "collector.total_frames=500"],
         "the episodes of worker processes"),
        (["collector.num_workers=2", "collector.total_frames=600"],
         "no workers' episodes, the collector has 2 workers"),
    ]:  # fmt: skip
        with pytest.warns(EpisodeNotRestored, match=why):
            train(make_cfg(*overrides, *collector, f"resume={shared}"), "unused")
    monkeypatch.setattr(loop, "workers_share_weights", lambda collector, policy: False)
    copies = tmp_path / "copies"
    train(make_cfg(*overrides), str(copies))
    c = RunCheckpoint(copies)
    episode = c.read("episode", c.root / "checkpoint-000000000200")
    assert not episode["kept"] and "weight_sync_every" in episode["why"]
    with pytest.warns(EpisodeNotRestored, match="older weights than the learner's"):
        train(make_cfg(*overrides, "collector.total_frames=500", f"resume={copies}"), "unused")


def test_a_checkpoint_without_an_episode_resumes_at_a_new_one(tmp_path, monkeypatch):
    """A checkpoint written before episodes were kept resumes too, at a new episode, and
    says so."""
    overrides = [*TINY, "algorithm=ddpg", "collector.total_frames=200"]
    train(make_cfg(*overrides), str(tmp_path))
    monkeypatch.setattr(RunCheckpoint, "read_optional", lambda self, name, path: None)
    with pytest.warns(EpisodeNotRestored, match="written before episodes were kept"):
        out = train(make_cfg(*TINY, "algorithm=ddpg", f"resume={tmp_path}"), "unused")
    assert out["frames"] == 400


def test_reset_options_from_a_run_directory_reach_no_env(tmp_path, monkeypatch):
    """A run directory comes from anyone; the recipe resets its envs without options, so a
    saved episode that names some (a string an env might open as a file) is not replayed."""
    cfg = make_cfg(*TINY, "algorithm=ddpg")
    env = make_env(cfg, torch.device("cpu"), record_episode=True)
    collector = make_collector(cfg, env, RandomPolicy(env.action_spec), torch.device("cpu"))
    episode = EpisodeCheckpoint()
    episode.attach(env, collector)
    next(iter(collector))
    state = episode.state_dict()
    assert state["kept"] and state["reset"]["options"] is None
    replayed = []
    replay = EpisodeReplay.replay
    monkeypatch.setattr(
        EpisodeReplay, "replay", lambda self, s: replayed.append(s) or replay(self, s)
    )
    tampered = {**state, "reset": {**state["reset"], "options": {"model": str(tmp_path)}}}
    episode.load_state_dict(tampered)
    assert "reset options" in episode.restore(env, collector)
    # and a record no checkpoint holds is named, not replayed
    at = [k[-1] for k in state["carrier_keys"]].index("observation")
    values = list(state["carrier_values"])
    values[at] = values[at][:2]
    for bad, message in [
        ({"carrier_values": state["carrier_values"][1:]}, "unusable"),
        ({"carrier_values": values}, "holds another 'observation'"),
        ({"reset": {"seed": 0}}, "unusable"),
    ]:
        episode.load_state_dict({**state, **bad})
        assert message in episode.restore(env, collector)
    assert replayed == []
    episode.load_state_dict(state)
    assert episode.restore(env, collector) is None and len(replayed) == 1
    collector.shutdown()


class _StopAfter:
    """A :class:`~torchrl_rave.recipe.collect.StopRequest` stand-in for the loop whose
    request is made by the test, at a chosen model step or agent update, as a Ctrl-C in
    the middle of a batch's updates would make it."""

    active = None

    def __init__(self) -> None:
        self.requested = False
        _StopAfter.active = self

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        _StopAfter.active = None


def _stop_at(monkeypatch, owner, name: str, calls: int) -> None:
    """Requests the stop as ``owner.name`` returns for the ``calls``-th time."""
    real, made = getattr(owner, name), []

    def counted(*args, **kwargs):
        out = real(*args, **kwargs)
        made.append(1)
        if len(made) == calls:
            _StopAfter.active.requested = True
        return out

    monkeypatch.setattr(owner, name, counted)


def flat(state) -> dict:
    """A checkpoint component's leaves by their path."""
    return dict(torch.utils._pytree.tree_flatten_with_path(state)[0])


# reward terms relabelled in the replay buffer, one of them delayed: the owed updates must
# relabel with the weights of their batch, not the ones a new run starts with
TERMS = ["env.name=terms_env:TermsPendulum-v0", "reward.weights={effort:0.5}",
         "reward.delayed=effort", "reward.delay_frames=0"]  # fmt: skip


@pytest.mark.parametrize(
    "group, extra", [(None, []), ([0, 1], []), (None, TERMS)], ids=["run", "group", "reward-terms"]
)
def test_a_stop_in_the_middle_of_the_updates_resumes_as_if_never_stopped(
    group, extra, tmp_path, monkeypatch
):
    """A stop (Ctrl-C, SIGTERM) checkpoints after the model step or agent update under way,
    not after the whole batch's updates (a pretraining of 10,000 model steps took minutes,
    past a batch scheduler's grace period). Here one stop falls in the world model's
    pretraining and one between two agent updates; each resumed run first takes what the
    stopped one owed, and the run ends with the parameters and evaluations of the run
    never stopped, to the last bit. The stopped batch's training means cover the updates
    after the resume: those two rows alone differ."""
    from torchrl_rave.recipe.group import GroupLearner
    from torchrl_rave.recipe.update import AgentLearner
    from torchrl_rave.trainers import WorldModelTrainer
    from torchrl_rave.trainers.seed_group import SeedGroup

    overrides = [*CHEETAH, "algorithm=steve", "world_model.pretrain_updates=12", *extra]
    if group is not None:
        overrides.append(f"seeds={group}")
    runs = [""] if group is None else [f"seed{s}" for s in group]
    whole, stopped = tmp_path / "whole", tmp_path / "stopped"
    train(make_cfg(*overrides), str(whole))
    model_step = (SeedGroup, "update_world_model") if group else (WorldModelTrainer, "_update")
    update = (GroupLearner, "update") if group else (AgentLearner, "update")
    monkeypatch.setattr(loop, "StopRequest", _StopAfter)

    with monkeypatch.context() as m:  # in the pretraining, at frame 200
        _stop_at(m, *model_step, calls=5)
        train(make_cfg(*overrides), str(stopped))
    checkpoints = [RunCheckpoint(stopped / run) for run in runs]
    for c in checkpoints:
        assert c.read("counters")["frames"] == 200 and c.read("counters")["updates"] == 0
        assert c.read("world_model_trainer")["pretrain_steps"] == 5
    with monkeypatch.context() as m:  # after the 3rd of the 10 updates of frame 300
        _stop_at(m, *update, calls=3)
        train(make_cfg(*overrides, f"resume={stopped}"), "unused")
    for c in checkpoints:
        counters = c.read("counters")
        assert (counters["frames"], counters["updates"]) == (300, 3)
        assert counters["update_budget"] == pytest.approx(7.0)
        assert c.read("world_model_trainer")["pretrain_steps"] == 12
    train(make_cfg(*overrides, f"resume={stopped}"), "unused")

    for run in runs:
        final_whole = RunCheckpoint(whole / run)
        final = checkpoints[runs.index(run)]
        assert final.read("counters") == final_whole.read("counters")
        for part in ("loss", "world_model", "optim_actor", "optim_critic", "world_model_trainer"):
            a, b = (flat(c.read(part)) for c in (final, final_whole))
            assert a.keys() == b.keys(), part
            for key, value in a.items():
                same = torch.equal(value, b[key]) if torch.is_tensor(value) else value == b[key]
                assert same, f"{part} {key}"
        expected, resumed = scalars(whole / run / "steve"), scalars(stopped / run / "steve")
        assert resumed.keys() == expected.keys()
        for name, rows in expected.items():
            got = resumed[name]
            if name == "train/episode_reward":  # an episode ended in a stopped batch: unlogged
                rows = [r for r in rows if r[0] not in (200, 300)]
                got = [r for r in got if r[0] not in (200, 300)]
            elif name.startswith("train/"):
                # the stopped batch (300): the means of the 7 updates after the resume
                assert [s for s, _ in got] == [s for s, _ in rows], name
                rows, got = ([r for r in x if r[0] != 300] for x in (rows, got))
            np.testing.assert_equal(got, rows, name)
