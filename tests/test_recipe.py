"""The training recipe: every algorithm end to end, config errors, checkpoints and resume,
determinism, NaN handling, and a learning check on InvertedPendulum-v5."""

from __future__ import annotations

import csv
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import rave_mujoco
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from torchrl_rave.recipe.agent import (
    critic_params,
    make_actor,
    make_critic,
    make_env,
    make_loss,
    make_replay_buffer,
    make_world_model,
)
from torchrl_rave.recipe.checkpoint import RunCheckpoint
from torchrl_rave.recipe.collect import NonFiniteEnvOutput
from torchrl_rave.recipe.config import ALGORITHMS, world_model_sizes
from torchrl_rave.recipe.metrics import describe
from torchrl_rave.recipe.runs import value_logged_at

RECIPES = Path(__file__).resolve().parents[1] / "recipes"

# Budgets of a few hundred frames: every code path runs, nothing is expected to learn.
TINY = [
    "collector.total_frames=400",
    "collector.frames_per_batch=100",
    "collector.init_random_frames=100",
    "world_model.pretrain_frames=200",
    "world_model.pretrain_updates=3",
    "world_model.transition_cells=16",
    "world_model.reward_cells=16",
    "world_model.termination_cells=16",
    "network.actor_cells=16",
    "network.critic_cells=16",
    "replay_buffer.batch_size=32",
    "optim.utd_ratio=0.1",
    "eval.interval=200",
    "eval.episodes=2",
    "checkpoint.interval=200",
    "logger.progress_bar=false",
]


def kill_after_first_checkpoint(overrides: list[str], run_dir: Path, runs=("",)) -> int:
    """Starts the recipe with ``overrides`` into ``run_dir`` in a process of its own,
    SIGKILLs it as soon as each of ``runs`` (a seed group's ``seed<s>``) has a checkpoint,
    and returns the newest frame all of them have a checkpoint of."""
    proc = subprocess.Popen(
        [sys.executable, str(RECIPES / "rave_mujoco.py"), *overrides, f"hydra.run.dir={run_dir}"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    checkpoints = [RunCheckpoint(run_dir / run) for run in runs]
    deadline = time.time() + 240
    while (any(c.latest() is None for c in checkpoints) and proc.poll() is None
           and time.time() < deadline):  # fmt: skip
        time.sleep(0.1)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    firsts = [c.latest() for c in checkpoints]
    assert None not in firsts, "the run died before its first checkpoint"
    return min(c.read("counters", p)["frames"] for c, p in zip(checkpoints, firsts, strict=True))


def make_cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(RECIPES), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def read_scalar(run_dir: Path, name: str, exp: str) -> list[tuple[int, float]]:
    with open(run_dir / exp / "scalars" / f"{name}.csv") as f:
        return [(int(step), float(value)) for step, value in csv.reader(f)]


def undocumented_metrics(exp_dir: Path) -> list[str]:
    """Logged metrics that ``torchrl_rave.recipe.metrics.METRICS`` (the documented list)
    does not describe."""
    scalars = exp_dir / "scalars"
    logged = [str(p.relative_to(scalars).with_suffix("")) for p in scalars.rglob("*.csv")]
    assert "eval/return" in logged
    return sorted(m for m in logged if describe(m) is None)


class TestAlgorithms:
    @pytest.mark.parametrize(
        "algorithm",
        ["ddpg", "mve", "steve", "rave", "rave_constant", "td3", "sac", "steve_sac", "rave_sac"],
    )
    def test_smoke_hopper(self, algorithm, tmp_path):
        cfg = make_cfg(f"algorithm={algorithm}", "env.name=Hopper-v5", *TINY)
        results = rave_mujoco.train(cfg, str(tmp_path))
        assert results["frames"] == 400
        # updates start at F (model-based) or after the random frames, 0.1 per frame
        start = 200 if ALGORITHMS[algorithm].model_based else 100
        assert results["updates"] == int(0.1 * (400 - start))
        assert 0.0 <= results["eval/falling_rate"] <= 1.0
        assert np.isfinite(results["eval/return"])
        evals = read_scalar(tmp_path, "eval/return", algorithm)
        assert [step for step, _ in evals] == [200, 400]
        # the value error of every evaluation: random-ish Hopper policies fall within the
        # 1,000-step limit, so every state of the 2 episodes counts
        lengths = read_scalar(tmp_path, "eval/episode_length", algorithm)
        states = read_scalar(tmp_path, "eval/q_states", algorithm)
        assert [v for _, v in states] == [2 * v for _, v in lengths]
        for metric in ("q_bias", "q_rmse"):
            assert all(
                np.isfinite(v) for _, v in read_scalar(tmp_path, f"eval/{metric}", algorithm)
            )
        critic = read_scalar(tmp_path, "train/loss_critic", algorithm)
        assert all(np.isfinite(v) for _, v in critic)
        assert undocumented_metrics(tmp_path / algorithm) == []
        if algorithm in ("steve", "rave", "rave_constant"):
            w = [read_scalar(tmp_path, f"train/horizon_weight_h{h}", algorithm) for h in range(4)]
            # per-sample weights sum to one, so their batch means do too
            total = [sum(col[i][1] for col in w) for i in range(len(w[0]))]
            assert np.allclose(total, 1.0, atol=1e-5)
        if algorithm == "rave_constant":
            alphas = read_scalar(tmp_path, "train/rave_alpha", algorithm)
            assert all(v == pytest.approx(1.5) for _, v in alphas)
        if algorithm == "rave":
            alphas = read_scalar(tmp_path, "train/rave_alpha", algorithm)
            assert all(0.0 <= v <= 1.5 for _, v in alphas)

    def test_ddpg_has_one_critic_and_rave_four(self, tmp_path):
        env = make_env(make_cfg(*TINY), torch.device("cpu"))
        for name, k in [("ddpg", 1), ("rave", 4), ("td3", 2), ("sac", 2)]:
            cfg = make_cfg(f"algorithm={name}", *TINY)
            algo = ALGORITHMS[name]
            actor, _ = make_actor(cfg, env, algo)
            wm = make_world_model(cfg, env) if algo.model_based else None
            loss, _ = make_loss(cfg, env, algo, actor, make_critic(cfg, env), wm)
            assert critic_params(loss)[0].batch_size[0] == k


class TestExploration:
    def test_actor_spans_the_action_box(self):
        # InvertedPendulum's actions lie in [-3, 3]; a tanh actor must reach past +-1.
        cfg = make_cfg(*TINY)
        env = make_env(cfg, torch.device("cpu"))
        actor, _ = make_actor(cfg, env, ALGORITHMS["rave"])
        td = env.reset()
        with torch.no_grad():
            actor[0].module[-1].bias.fill_(100.0)  # saturate the tanh
            assert actor(td)["action"].item() == pytest.approx(3.0)

    @pytest.mark.parametrize("scale, floor", [(1.0, 1e-4), (0.2, 0.05)])
    def test_sac_policy_scale_starts_at_its_setting_and_keeps_its_floor(self, scale, floor):
        """``network.default_policy_scale``: the pre-tanh scale where the network outputs
        0; ``network.scale_lb``: none falls below it (nor below the mapping's own floor of
        0.01), however negative the output."""
        cfg = make_cfg(*TINY, "algorithm=sac", f"network.default_policy_scale={scale}",
                       f"network.scale_lb={floor}")  # fmt: skip
        env = make_env(cfg, torch.device("cpu"))
        actor, _ = make_actor(cfg, env, ALGORITHMS["sac"])
        td = env.reset()
        last = actor.module[0].module[0][-1]  # the MLP's output layer
        with torch.no_grad():
            last.weight.zero_()
            last.bias.zero_()
            assert actor(td.clone())["scale"].item() == pytest.approx(scale, rel=1e-5)
            last.bias.fill_(-100.0)
            least = actor(td.clone())["scale"].item()
            assert least == pytest.approx(max(floor, 0.01), rel=1e-5)

    def test_epsilon_noise_rate_in_collected_data(self):
        cfg = make_cfg(*TINY, "exploration.epsilon=0.05", "exploration.sigma=0.5")
        env = make_env(cfg, torch.device("cpu"))
        actor, policy = make_actor(cfg, env, ALGORITHMS["rave"])
        torch.manual_seed(0)
        td = env.reset().expand(4000).clone()
        from torchrl.envs.utils import ExplorationType, set_exploration_type

        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            noisy = policy(td.clone())["action"]
            clean = actor(td.clone())["action"]
        rate = (noisy != clean).float().mean().item()
        assert 0.04 < rate < 0.06


class TestConfigErrors:
    def test_an_empty_resume_is_refused(self, tmp_path):
        """The probe: ``resume=`` (empty) started a new default run and exited 0."""
        done = subprocess.run(
            [sys.executable, str(RECIPES / "rave_mujoco.py"), "resume=",
             f"hydra.run.dir={tmp_path / 'run'}"],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 1 and "Traceback" not in done.stderr
        assert "resume= takes the run directory to continue" in done.stderr
        assert not (tmp_path / "run" / "checkpoints").exists()

    @pytest.mark.parametrize(
        "override, message",
        [
            ("algorithm=dqn", "algorithm='dqn'.*one of \\['ddpg', 'mve'.*'ppo'\\]"),
            ("env.name=Hoper-v5", "env.name='Hoper-v5' is not a registered gymnasium id"),
            ("collector.total_frames=-5", "collector.total_frames=-5 is invalid"),
            ("collector.frames_per_batch=0", "collector.frames_per_batch=0"),
            ("replay_buffer.batch_size=100000", "replay_buffer.batch_size=100000.*<= the replay"),
            ("estimator.horizon=-1", "estimator.horizon=-1"),
            ("exploration.epsilon=1.5", "exploration.epsilon=1.5"),
            ("logger.backend=stdout", "logger.backend='stdout'.*one of"),
            ("network.num_critics=0", "network.num_critics=0"),
            ("threads=0", "threads=0 is invalid: expected null or an integer >= 1"),
            ("env.seed=-1", "env.seed=-1 is invalid: expected an integer >= 0"),
            # was gymnasium's traceback from inside the env's constructor
            ("env.kwargs={foo:1}", "env.kwargs=.*got an unexpected keyword argument 'foo'"),
            # both failed deep inside the agent's construction (AttributeError on .low)
            ("env.name=CartPole-v1", "action space is Discrete\\(2\\), and the recipe's"),
            ("env.name=FrozenLake-v1", "observation space is Discrete\\(16\\)"),
        ],
    )
    def test_bad_value_named_before_training(self, override, message, tmp_path):
        cfg = make_cfg(*TINY, override)
        with pytest.raises(ValueError, match=message):
            rave_mujoco.train(cfg, str(tmp_path))
        assert not (tmp_path / "checkpoints").exists()

    def test_threads_key_sets_torch_threads(self, monkeypatch, tmp_path):
        calls = []
        monkeypatch.setattr(torch, "set_num_threads", calls.append)  # the suite's own stay
        cfg = make_cfg(*TINY, "algorithm=ddpg", "threads=1", "collector.total_frames=200")
        rave_mujoco.train(cfg, str(tmp_path))
        assert calls == [1]

    def test_unknown_preset_lists_choices(self):
        with pytest.raises(Exception, match="(?s)preset/fast.*Available options.*cpu.*paper"):
            make_cfg("preset=fast")

    def test_unknown_key(self):
        with pytest.raises(Exception, match="estimator.hoirzon"):
            make_cfg("estimator.hoirzon=3")

    def test_paper_preset_values(self):
        cfg = make_cfg("preset=paper")
        assert cfg.replay_buffer.batch_size == 512
        assert cfg.replay_buffer.size == 1_000_000
        assert cfg.world_model.pretrain_frames == 10_000
        assert world_model_sizes(cfg)["transition_layers"] == 8
        assert cfg.exploration.epsilon == 0.05
        assert cfg.estimator.alpha == 1.5 and cfg.estimator.horizon == 3
        # command-line overrides still win over the preset
        assert (
            make_cfg("preset=paper", "replay_buffer.batch_size=64").replay_buffer.batch_size == 64
        )


class _NaNAfter(gym.Wrapper):
    """Returns a NaN observation from the ``after``-th step on."""

    def __init__(self, env, after: int):
        super().__init__(env)
        self.steps, self.after = 0, after

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps += 1
        if self.steps >= self.after:
            obs = np.full_like(obs, np.nan)
        return obs, reward, terminated, truncated, info


def _nan_pendulum(after: int = 150):
    return _NaNAfter(gym.make("InvertedPendulum-v5"), after)


gym.register("NaNInvertedPendulum-v0", entry_point=_nan_pendulum, max_episode_steps=1000)


class _HugeAfter(_NaNAfter):
    """Observations scaled by 1e20 from the ``after``-th step on: finite, but beyond what
    float32 statistics can hold."""

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.steps += 1
        if self.steps >= self.after:
            obs = obs * 1e20 + 1e20
        return obs, reward, terminated, truncated, info


gym.register(
    "HugeInvertedPendulum-v0",
    entry_point=lambda after=150: _HugeAfter(gym.make("InvertedPendulum-v5"), after),
    max_episode_steps=1000,
)


class TestCheckpoints:
    def test_nan_observation_stops_with_checkpoint(self, tmp_path):
        # the policy is random for the first frames, so make episodes long with many
        # resets impossible to avoid: count steps across episodes in the wrapper
        cfg = make_cfg(*TINY, "env.name=NaNInvertedPendulum-v0", "algorithm=ddpg")
        with pytest.raises(NonFiniteEnvOutput, match="NaN/inf in .*observation"):
            rave_mujoco.train(cfg, str(tmp_path))
        checkpoint = RunCheckpoint(tmp_path)
        assert checkpoint.read("counters")["frames"] == 100  # the last good batch
        rb = make_replay_buffer(cfg, "cpu")
        checkpoint.load(replay_buffer=rb, restore_rng=False)
        assert len(rb) == 100
        assert torch.isfinite(rb[:100]["next", "observation"]).all()

    def test_a_groups_nan_stop_names_its_checkpoints(self, tmp_path):
        """The probe: a seed group's NaN stop said "checkpoint None holds everything"."""
        cfg = make_cfg(*TINY, "env.name=NaNInvertedPendulum-v0", "algorithm=ddpg", "seeds=[0,1]")
        with pytest.raises(NonFiniteEnvOutput, match="checkpoints .*seed0/checkpoints/"
                           "checkpoint-0+100, .*seed1/checkpoints/checkpoint-0+100 hold "
                           "everything up to that frame"):  # fmt: skip
            rave_mujoco.train(cfg, str(tmp_path))

    def test_huge_observations_stop_with_a_checkpoint_before_reaching_the_model(self, tmp_path):
        """Issue 39, defect 9: observations of 1e20 made the world model's normalisers
        non-finite and its parameters NaN after one step, with no error."""
        cfg = make_cfg(*TINY, "env.name=HugeInvertedPendulum-v0")
        with pytest.raises(NonFiniteEnvOutput, match=r"values up to [0-9.]+e\+20 \(beyond "
                           r"±1e\+18\) in .*observation.*frames 100-200"):  # fmt: skip
            rave_mujoco.train(cfg, str(tmp_path))
        checkpoint = RunCheckpoint(tmp_path)
        assert checkpoint.read("counters")["frames"] == 100
        state = checkpoint.read("world_model")
        assert all(torch.isfinite(v).all() for v in state.values() if torch.is_tensor(v))

    def test_nan_in_the_first_batch_is_reported_not_a_storage_error(self, tmp_path):
        """Nothing is stored yet when the first batch is bad: the run still says what went
        wrong (not TorchRL's "Cannot save a non-initialized storage"), checkpoints frame 0
        with an empty buffer, and that checkpoint resumes."""
        cfg = make_cfg(*TINY, "env.name=NaNInvertedPendulum-v0", "env.kwargs={after:3}")
        with pytest.raises(NonFiniteEnvOutput, match=r"NaN/inf in .*observation.*frames 0-100"):
            rave_mujoco.train(make_cfg(*TINY, "env.name=NaNInvertedPendulum-v0",
                                       "env.kwargs={after:3}", "algorithm=ddpg"), str(tmp_path))  # fmt: skip
        checkpoint = RunCheckpoint(tmp_path)
        assert checkpoint.read("counters")["frames"] == 0
        # the dropped batch's steps are in no replay buffer: a resume starts a new episode
        assert checkpoint.read("episode") == {"kept": False, "new_episode": True}
        names = [p.name for p in (tmp_path / "checkpoints").iterdir()]
        assert names == ["checkpoint-000000000000"]  # no staging left behind
        rb = make_replay_buffer(cfg, "cpu")
        checkpoint.load(replay_buffer=rb, restore_rng=False)
        assert len(rb) == 0

    def test_kill_and_resume_continues_exactly(self, tmp_path):
        """Kill a run (SIGKILL) after its first checkpoint, resume it, and check that frames,
        replay-buffer contents and optimiser state carry over exactly."""
        overrides = [
            *TINY,
            "algorithm=rave",
            "collector.total_frames=3000",
            "checkpoint.interval=300",
            "eval.interval=3000",
        ]
        f0 = kill_after_first_checkpoint(overrides, tmp_path)
        checkpointer = RunCheckpoint(tmp_path)
        first = checkpointer.root / f"checkpoint-{f0:012d}"
        saved_counters = checkpointer.read("counters", first)
        assert f0 % 300 == 0 and 300 <= f0 < 3000
        cfg = make_cfg(*overrides)
        saved_rb = make_replay_buffer(cfg, "cpu")
        checkpointer.load(replay_buffer=saved_rb, path=first, restore_rng=False)
        saved_obs = saved_rb[:f0]["observation"].clone()
        saved_steps = checkpointer.read("optim_critic", first)["state"][0]["step"].item()

        results = rave_mujoco.train(make_cfg(*overrides, f"resume={tmp_path}"), "unused")
        assert results["frames"] == 3000
        final = checkpointer.read("counters")
        assert final["frames"] == 3000
        rb = make_replay_buffer(cfg, "cpu")
        checkpointer.load(replay_buffer=rb, restore_rng=False)
        assert len(rb) == 3000
        assert torch.equal(rb[:f0]["observation"], saved_obs)  # old data kept, in place
        # Adam's step count carries on from the checkpoint: a reset optimiser would be
        # short by exactly the saved count.
        new_updates = round(0.1 * (3000 - f0))
        final_steps = checkpointer.read("optim_critic")["state"][0]["step"].item()
        assert final_steps == saved_steps + new_updates
        assert final["updates"] == saved_counters["updates"] + new_updates
        evals = read_scalar(tmp_path, "eval/return", "rave")
        assert evals[-1][0] == 3000

    @pytest.mark.parametrize(
        "stop, first_eval, workers",
        [
            (signal.SIGINT, "eval.interval=200", 0),
            (signal.SIGTERM, "eval.interval=100000", 0),
            (signal.SIGINT, "eval.interval=200", 2),
            (signal.SIGTERM, "eval.interval=200", 2),
        ],
        ids=[
            "ctrl-c",
            "sigterm-before-any-evaluation",
            "ctrl-c-to-a-run-with-workers",
            "sigterm-to-a-run-with-workers",
        ],
    )
    def test_a_stop_checkpoints_at_the_batch_end_and_exits_cleanly(
        self, stop, first_eval, workers, tmp_path
    ):
        """With worker processes, the signal goes to the whole process group, as a
        terminal sends a Ctrl-C and a batch scheduler (Slurm's ``scancel``) a SIGTERM: the
        workers leave it to the learner (one that died of a Ctrl-C left the learner
        waiting for it forever), and the checkpoint keeps their episodes."""
        overrides = [*TINY, "algorithm=ddpg", "collector.total_frames=100000", first_eval]
        if workers:
            overrides += ["collector.backend=process", f"collector.num_workers={workers}"]
        proc = subprocess.Popen(
            [
                sys.executable,
                str(RECIPES / "rave_mujoco.py"),
                *overrides,
                f"hydra.run.dir={tmp_path}",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            start_new_session=True,  # its own process group, as a terminal's foreground job
        )
        scalars = tmp_path / "ddpg" / "scalars" / "time" / "fps.csv"
        deadline = time.time() + 240
        while not scalars.exists() and proc.poll() is None and time.time() < deadline:
            time.sleep(0.2)
        if workers:
            os.killpg(proc.pid, stop)
        else:
            proc.send_signal(stop)
        out, _ = proc.communicate(timeout=240)
        assert proc.returncode == 0
        checkpoint = RunCheckpoint(tmp_path)
        frames = checkpoint.read("counters")["frames"]
        assert 0 < frames < 100000 and frames % 100 == 0  # a whole number of batches
        assert f"stopped at frame {frames}; resume with resume={tmp_path}" in out
        assert checkpoint.read("episode")["kept"]

    def test_resume_of_a_finished_run_reproduces_its_evaluation(self, tmp_path, capsys):
        # Resuming from the final checkpoint collects nothing and evaluates the restored
        # policy with the same evaluation seed: a policy not restored exactly would give a
        # different (continuous-valued) Hopper return.
        overrides = [*TINY, "algorithm=steve", "env.name=Hopper-v5", "collector.total_frames=300"]
        first = rave_mujoco.train(make_cfg(*overrides), str(tmp_path))
        capsys.readouterr()
        again = rave_mujoco.train(make_cfg(*overrides, f"resume={tmp_path}"), "unused")
        assert again["frames"] == 300 and again["updates"] == first["updates"]
        # and says so, with the key to raise
        assert "nothing to train: the run is at 300 frames and collector.total_frames=300" in (
            capsys.readouterr().out
        )
        assert again["eval/return"] == first["eval/return"]
        checkpoint = RunCheckpoint(tmp_path)
        # the world-model normalisers saw all 300 stored frames, and the resolved buffer
        # size is part of the saved config
        assert checkpoint.read("world_model")["obs_norm.count"].item() == 300
        assert OmegaConf.create(checkpoint.read("config")).replay_buffer.size == 300

    def test_a_moved_run_directory_resumes_in_its_new_place(self, tmp_path):
        """The logger's saved directory is the old path: resuming a moved run must write
        its new metrics where the run is now, and recreate nothing at the old path."""
        import shutil

        overrides = [*TINY, "algorithm=ddpg", "collector.total_frames=200"]
        old, new = tmp_path / "old", tmp_path / "new"
        rave_mujoco.train(make_cfg(*overrides), str(old))
        shutil.move(old, new)
        more = [*overrides[:-1], "collector.total_frames=400", f"resume={new}"]
        rave_mujoco.train(make_cfg(*more), "unused")
        assert not old.exists()
        assert [s for s, _ in read_scalar(new, "eval/return", "ddpg")] == [200, 400]

    def test_a_grid_resumes_an_interrupted_cell_started_with_a_preset(self, tmp_path):
        """The probe: a study cell (its overrides name ``preset=``) interrupted after a
        checkpoint was restarted with its overrides and ``resume=``, which refuses a preset:
        the cell failed at every later start. It must resume from its saved config."""
        from torchrl_rave.recipe.runs import Cell, cell_arguments, check_cells, launch_grid

        run_dir = tmp_path / "cell"
        overrides = ("preset=cpu", "algorithm=ddpg", *TINY[1:])
        first = Cell(run_dir, 200, overrides)  # as if stopped at 200 of 400 frames
        assert launch_grid(RECIPES / "rave_mujoco.py", [first]) == {first: 0}
        cell = Cell(run_dir, 400, overrides)
        assert not cell.finished() and cell.checkpoint_frame() == 200
        assert "preset=cpu" not in cell_arguments(cell)
        check_cells([cell], RECIPES)  # the saved config, read as resume= reads it: no problem
        assert launch_grid(RECIPES / "rave_mujoco.py", [cell]) == {cell: 0}
        assert cell.finished()
        assert [s for s, _ in read_scalar(run_dir, "eval/return", "ddpg")] == [200, 400]
        assert [s["from_frame"] for s in cell.starts()] == [0, 200]

    def test_resume_refuses_a_different_algorithm(self, tmp_path):
        overrides = [*TINY, "algorithm=ddpg", "collector.total_frames=200"]
        rave_mujoco.train(make_cfg(*overrides), str(tmp_path))
        with pytest.raises(
            ValueError, match="algorithm is 'td3' but the run was started with 'ddpg'"
        ):
            rave_mujoco.train(make_cfg(*overrides, "algorithm=td3", f"resume={tmp_path}"), "x")

    def test_a_new_run_into_a_run_directory_is_refused(self, tmp_path):
        # it overwrote the old run's checkpoints and appended a second run to its CSVs
        overrides = [*TINY, "algorithm=ddpg", "collector.total_frames=200"]
        single, group = tmp_path / "single", tmp_path / "group"
        rave_mujoco.train(make_cfg(*overrides), str(single))
        rave_mujoco.train(make_cfg(*overrides, "seeds=[0,1]"), str(group))
        written = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
        with pytest.raises(FileExistsError, match=re.escape(
            f"{single} holds a run already (its newest checkpoint is at 200 frames): pass "
            f"resume={single} to continue it"
        )):  # fmt: skip
            rave_mujoco.train(make_cfg(*overrides), str(single))
        for seeds in (["seeds=[0,1]"], []):  # a group, and one run into a group's directory
            with pytest.raises(FileExistsError, match="holds a seed group already: pass resume="):
                rave_mujoco.train(make_cfg(*overrides, *seeds), str(group))
        done = subprocess.run(
            [sys.executable, str(RECIPES / "rave_mujoco.py"), *overrides, f"hydra.run.dir={single}"],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 1 and "Traceback" not in done.stderr
        assert f"resume={single} to continue it" in done.stderr
        for path, content in written.items():  # not a byte changed
            if ".hydra" not in path.parts and path.name != "rave_mujoco.log":
                assert path.read_bytes() == content, path
        # a group stopped before every seed had a checkpoint has nothing to resume: it
        # starts afresh (as study.py's runner starts it)
        shutil.rmtree(group / "seed1" / "checkpoints")
        again = rave_mujoco.train(make_cfg(*overrides, "seeds=[0,1]"), str(group))
        assert "seed1/eval/return" in again
        assert RunCheckpoint(group / "seed1").read("counters")["frames"] == 200

    def test_resume_refuses_overrides_it_would_ignore(self, tmp_path):
        """A resumed run's buffer was allocated at its size, and its config is the saved
        one: replay_buffer.size= and preset= would change nothing, so they are refused."""
        from torchrl_rave.recipe.config import ConfigError

        overrides = [*TINY, "algorithm=ddpg", "collector.total_frames=200"]
        rave_mujoco.train(make_cfg(*overrides), str(tmp_path))
        resumed = make_cfg(*overrides, "replay_buffer.size=50", f"resume={tmp_path}")
        with pytest.raises(
            ConfigError, match="replay_buffer.size is 50 but the run was started with 200"
        ):
            rave_mujoco.train(resumed, "x")
        done = subprocess.run(
            [sys.executable, str(RECIPES / "rave_mujoco.py"), f"resume={tmp_path}", "preset=paper"],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 1 and "Traceback" not in done.stderr
        assert "preset= does not apply to a resumed run" in done.stderr
        assert RunCheckpoint(tmp_path).read("counters")["frames"] == 200  # nothing ran

    @pytest.mark.parametrize("total, end", [(250, 300), (300, 300), (50, 50)])
    def test_a_resumed_collector_ends_where_the_uninterrupted_one_does(self, total, end):
        """A total that is not a whole number of batches is rounded up to one, as TorchRL's
        collectors do: from any checkpoint on the batch grid, a resumed run collects the
        batches the uninterrupted run would have (not a short last batch of the bare
        remainder, which made a run killed within its last batch end at a frame, with a
        number of updates and an evaluation, that the uninterrupted run never had)."""
        from torchrl_rave.recipe.collect import make_collector

        cfg = make_cfg(*TINY, "algorithm=ddpg", f"collector.total_frames={total}")
        env = make_env(cfg, torch.device("cpu"))
        ends = {}
        for done in range(0, total, min(100, total)):  # TINY's batches are 100 frames
            collector = make_collector(cfg, env, None, torch.device("cpu"), done)
            ends[done] = done + sum(batch.numel() for batch in collector)
            collector.shutdown()
        env.close()
        assert set(ends.values()) == {end}, ends

    def test_extending_a_run_past_its_buffer_says_what_it_drops(self):
        """replay_buffer.size is fixed at the first start (by default its total frames):
        training a resumed run on past it drops transitions a longer run would keep."""
        import warnings

        from torchrl_rave.recipe.config import check_resumable

        saved = make_cfg(*TINY, "algorithm=ddpg", "collector.total_frames=200")
        saved.replay_buffer.size = 200  # as the first start fixes it
        with pytest.warns(UserWarning, match=r"holds 200 transitions.*total_frames=300 drops"):
            check_resumable(make_cfg(*TINY, "algorithm=ddpg", "collector.total_frames=300",
                                     "resume=run"), saved)  # fmt: skip
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            for total in (200, 150):  # a finished run, or a total within the buffer
                check_resumable(make_cfg(*TINY, "algorithm=ddpg", f"collector.total_frames={total}",
                                         "resume=run"), saved)  # fmt: skip
            for size in (100, None):  # dropped transitions from the start; sized on resume
                saved.replay_buffer.size = size
                check_resumable(make_cfg(*TINY, "algorithm=ddpg", "collector.total_frames=300",
                                         "resume=run"), saved)  # fmt: skip


class TestDeterminism:
    def test_same_seed_same_losses(self, tmp_path):
        overrides = [*TINY, "algorithm=rave", "collector.total_frames=300", "optim.utd_ratio=0.2"]
        for run in ("a", "b"):
            rave_mujoco.train(make_cfg(*overrides), str(tmp_path / run))
        for name in ("train/loss_critic", "train/loss_actor", "train/wm_transition_nll"):
            a = read_scalar(tmp_path / "a", name, "rave")
            b = read_scalar(tmp_path / "b", name, "rave")
            assert len(a) >= 1 and a == b, name
        c_dir = tmp_path / "c"
        rave_mujoco.train(make_cfg(*overrides, "env.seed=1"), str(c_dir))
        assert read_scalar(c_dir, "train/loss_critic", "rave") != read_scalar(
            tmp_path / "a", "train/loss_critic", "rave"
        )


class TestCompare:
    def test_grid_runs_skips_finished_and_tabulates(self, tmp_path, capsys):
        import compare

        tiny = [o for o in TINY if not o.startswith("collector.total_frames")]
        args = ["--envs", "InvertedPendulum-v5", "--algorithms", "ddpg", "--seeds", "0", "1"]
        args += ["--frames", "300", "--out", str(tmp_path), "--", *tiny]
        compare.main(args)
        printed = capsys.readouterr().out
        values = [
            value_logged_at(
                compare.run_dir(tmp_path, "InvertedPendulum-v5", "ddpg", s), "eval/return", 300
            )
            for s in (0, 1)
        ]
        assert all(v is not None for v in values)
        row = f"| InvertedPendulum-v5 | ddpg | {np.mean(values):.0f} ± {np.std(values):.0f} | 2 |"
        assert row in printed
        compare.main(args)  # both runs finished: nothing relaunched
        assert "runs to go" not in capsys.readouterr().out

    def test_every_run_is_checked_before_any_starts(self, tmp_path):
        """A mistake in a grid is one error naming each problem once and the cells that
        have it, before any run directory is made; not a failure per run."""
        import compare

        args = ["--envs", "Hoper-v5", "Pendulum-v1", "--algorithms", "ddpg", "dqn",
                "--seeds", "0", "-1", "--frames", "300", "--out", str(tmp_path / "grid")]  # fmt: skip
        with pytest.raises(SystemExit) as stop:
            compare.main(args)
        message = str(stop.value)
        assert message.startswith("3 problems in the config:")
        assert "env.name='Hoper-v5' is not a registered gymnasium id" in message
        assert "algorithm='dqn' is invalid" in message
        assert (
            f"env.seed=-1 is invalid: expected an integer >= 0 (in 4 cells: {tmp_path}" in message
        )
        good = ["--envs", "Pendulum-v1", "--algorithms", "ddpg", "--seeds", "0",
                "--frames", "300", "--out", str(tmp_path / "grid")]  # fmt: skip
        # a seed given twice would put two runs at once into one directory
        with pytest.raises(SystemExit, match=r"2 cells would write one run directory, "
                                             r".*grid/Pendulum-v1/ddpg/seed0 \(a seed"):  # fmt: skip
            compare.main([*good, "--seeds", "0", "0", "--jobs", "2"])
        with pytest.raises(SystemExit, match="Could not override 'estimator.hoirzon'"):
            compare.main([*good, "--", "estimator.hoirzon=3"])
        # each distinct env is built once: a space the learners cannot use, or a keyword
        # the env does not take, is found before any cell starts, not by every cell
        grid = ["--algorithms", "ddpg", "td3", "--seeds", "0", "--frames", "300",
                "--out", str(tmp_path / "grid")]  # fmt: skip
        with pytest.raises(SystemExit, match=r"'CartPole-v1': its action space is Discrete\(2\)"
                           r".* \(in 2 cells: "):  # fmt: skip
            compare.main([*grid, "--envs", "CartPole-v1", "Pendulum-v1"])
        with pytest.raises(SystemExit, match=r"Pendulum-v1 got an unexpected keyword argument "
                                             r"'foo' \(in 2 cells:"):  # fmt: skip
            compare.main([*grid, "--envs", "Pendulum-v1", "--", "env.kwargs={g:9.81,foo:1}"])
        assert not (tmp_path / "grid").exists()

    def test_reference_column_is_labelled(self, tmp_path):
        import compare

        text = compare.table(tmp_path, ["Hopper-v5"], ["ddpg", "rave"], [0], 1000)
        assert "not our runs" in text
        assert "| Hopper-v5 | ddpg | n/a | 0 | 904 / 1241 / 1604 |" in text
        assert "| Hopper-v5 | rave | n/a | 0 |  |" in text


class TestLearning:
    @pytest.mark.slow
    def test_rave_default_run_solves_inverted_pendulum(self, tmp_path):
        """The default command (RAVE, InvertedPendulum-v5, 15,000 frames, seed 0) reaches a
        mean deterministic return >= 900 (the maximum is 1000). About 5 minutes on 2 cores."""
        cfg = make_cfg("eval.episodes=10", "logger.progress_bar=false")
        assert cfg.collector.total_frames == 15_000 and cfg.algorithm == "rave"
        results = rave_mujoco.train(cfg, str(tmp_path))
        assert results["eval/return"] >= 900
        assert results["eval/falling_rate"] <= 0.1


class TestLoggers:
    def test_tensorboard_events_hold_the_evaluation(self, tmp_path):
        pytest.importorskip("tensorboard")
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

        cfg = make_cfg(*TINY, "algorithm=ddpg", "logger.backend=tensorboard")
        results = rave_mujoco.train(cfg, str(tmp_path))
        events = EventAccumulator(str(tmp_path / "ddpg")).Reload()
        scalars = events.Scalars("eval/return")
        assert [e.step for e in scalars] == [200, 400]
        assert scalars[-1].value == pytest.approx(results["eval/return"])

    def test_wandb_offline_run_resumes_same_run(self, tmp_path, monkeypatch):
        pytest.importorskip("wandb")
        monkeypatch.setenv("WANDB_MODE", "offline")
        monkeypatch.setenv("WANDB_DIR", str(tmp_path))
        monkeypatch.setenv("WANDB_SILENT", "true")
        overrides = [*TINY, "algorithm=ddpg", "logger.backend=wandb", "collector.total_frames=200"]
        rave_mujoco.train(make_cfg(*overrides), str(tmp_path))
        run_id = RunCheckpoint(tmp_path).read("logger")["local"]["id"]
        assert run_id
        overrides[-1] = "collector.total_frames=400"
        rave_mujoco.train(make_cfg(*overrides, f"resume={tmp_path}"), "unused")
        assert RunCheckpoint(tmp_path).read("logger")["local"]["id"] == run_id


def test_a_run_that_cannot_learn_is_warned_about_before_any_work(tmp_path):
    """The probe: ``collector.total_frames=600`` with 1,000 random frames collected 750
    frames and made 0 updates, which only the summary's "0 updates" gave away. A warning,
    not an error: a run that only collects is allowed."""
    from torchrl_rave.recipe.config import NoUpdatesWarning

    cfg = make_cfg("algorithm=ddpg", "collector.total_frames=600", "collector.frames_per_batch=250",
                   "collector.init_random_frames=1000", "eval.interval=750")  # fmt: skip
    with pytest.warns(NoUpdatesWarning, match=r"this run makes no update: it collects 750 frames "
                      r"\(collector.total_frames=600 in batches of 250\) and learning waits for "
                      r"1000 stored frames \(collector.init_random_frames=1000\)"):  # fmt: skip
        result = rave_mujoco.train(cfg, str(tmp_path / "run"))
    assert result["updates"] == 0
    model_based = make_cfg(*TINY, "algorithm=rave", "collector.total_frames=200")
    with pytest.warns(NoUpdatesWarning, match="world_model.pretrain_frames=200"):
        from torchrl_rave.recipe.config import warn_if_no_updates

        warn_if_no_updates(model_based)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", NoUpdatesWarning)
        warn_if_no_updates(make_cfg(*TINY, "algorithm=rave"))  # 400 frames: it learns


class TestBusyCores:
    """A run's torch threads against the cores other processes leave free: at
    ``threads=2`` with both cores of a 2-core machine busy, the main job's first 2,500
    frames took 242.9 s, against 46.8 s at ``threads=1`` (docs/performance.md)."""

    def test_each_listed_cores_ticks_are_read(self):
        from torchrl_rave.recipe.config import _core_ticks

        stat = (
            "cpu  30 1 15 140 14 0 0 0 5 0\n"
            "cpu0 10 1 5 80 4 0 0 0 0 0\n"
            "cpu1 20 0 10 60 10 0 0 0 5 0\n"  # the guest column is counted in user already
            "cpu12 1 1 1 1 1 1 1 1 0 0\n"
            "intr 12345 6 7\n"
            "ctxt 999\n"
            "\n"
        )
        assert _core_ticks(stat, {0, 1}) == {0: (100, 84), 1: (100, 70)}
        assert _core_ticks(stat, {12}) == {12: (8, 2)}

    @pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="Linux only")
    def test_a_busy_loop_on_the_one_core_a_process_may_use_is_seen(self):
        from torchrl_rave.recipe.config import busy_cores

        allowed = os.sched_getaffinity(0)
        core = min(allowed)
        loop = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        try:
            os.sched_setaffinity(loop.pid, {core})
            os.sched_setaffinity(0, {core})
            time.sleep(0.2)
            busy, cores = busy_cores(0.5)
        finally:
            os.sched_setaffinity(0, allowed)
            loop.kill()
            loop.wait()
        assert cores == 1
        assert 0.8 < busy <= 1.0

    def test_more_threads_than_free_cores_are_warned_about(self, monkeypatch):
        import warnings

        from torchrl_rave.recipe import config
        from torchrl_rave.recipe.config import BusyCoresWarning, apply_process_settings

        threads = torch.get_num_threads()
        cfg = make_cfg(*TINY, "threads=2", "keep_freed_memory=false")
        monkeypatch.setattr(config, "cpu_quota", lambda: None)  # whatever the test machine's
        try:
            monkeypatch.setattr(config, "busy_cores", lambda: (1.1, 2))
            with pytest.warns(BusyCoresWarning, match=r"torch runs 2 threads in this process, "
                              r"and other processes keep 1\.1 of the 2 cores.*threads=1 fits"):  # fmt: skip
                apply_process_settings(cfg)
            monkeypatch.setattr(config, "busy_cores", lambda: (0.3, 2))
            with warnings.catch_warnings():
                warnings.simplefilter("error", BusyCoresWarning)
                apply_process_settings(cfg)  # both cores free enough

            def not_measured():
                raise AssertionError("one thread needs no measurement")

            monkeypatch.setattr(config, "busy_cores", not_measured)
            cfg.threads = 1
            apply_process_settings(cfg)
        finally:
            torch.set_num_threads(threads)

    @staticmethod
    def _tree(root, files: dict) -> None:
        for name, text in files.items():
            (root / name).parent.mkdir(parents=True, exist_ok=True)
            (root / name).write_text(text)

    def test_a_cgroup_v2_quota_is_the_tightest_along_the_path(self, tmp_path):
        from torchrl_rave.recipe.config import cpu_quota

        self._tree(tmp_path, {
            "cpu.max": "max 100000\n",  # the root: no quota
            "jobs/cpu.max": "200000 100000\n",  # 2 cores
            "jobs/run7/cpu.max": "150000 50000\n",  # 3 cores
            "jobs/run7/one/cpu.max": "100000 100000\n",  # 1 core
            "jobs/run7/free/cpu.max": "max 100000\n",
        })  # fmt: skip
        assert cpu_quota(tmp_path, "0::/jobs/run7/one\n") == 1.0  # the leaf's own, tightest
        assert cpu_quota(tmp_path, "0::/jobs/run7/free\n") == 2.0  # a parent's, not the nearest
        assert cpu_quota(tmp_path, "0::/jobs\n") == 2.0
        assert cpu_quota(tmp_path, "0::/\n") is None
        # a container sees its own cgroup as the root, where the host's path is missing
        self._tree(tmp_path / "box", {"cpu.max": "250000 100000\n"})
        assert cpu_quota(tmp_path / "box", "0::/docker/0a1b2c\n") == 2.5
        self._tree(tmp_path / "bad", {"cpu.max": "\n", "a/cpu.max": "lots 100000\n"})
        assert cpu_quota(tmp_path / "bad", "0::/a\n") is None  # unreadable: no quota known

    def test_a_cgroup_v1_quota_is_read_from_the_cpu_controller_tree(self, tmp_path):
        from torchrl_rave.recipe.config import cpu_quota

        self._tree(tmp_path, {
            "cpu,cpuacct/cpu.cfs_quota_us": "-1\n",
            "cpu,cpuacct/cpu.cfs_period_us": "100000\n",
            "cpu,cpuacct/slurm/job1/cpu.cfs_quota_us": "200000\n",
            "cpu,cpuacct/slurm/job1/cpu.cfs_period_us": "100000\n",
            "memory/slurm/job1/cpu.cfs_quota_us": "100000\n",  # not the cpu controller's
            "memory/slurm/job1/cpu.cfs_period_us": "100000\n",
        })  # fmt: skip
        text = "5:memory:/slurm/job1\n3:cpu,cpuacct:/slurm/job1\n0::/\n"
        assert cpu_quota(tmp_path, text) == 2.0
        assert cpu_quota(tmp_path, "3:cpu,cpuacct:/\n") is None  # -1: no quota
        assert cpu_quota(tmp_path, "5:memory:/slurm/job1\n") is None

    def test_more_threads_than_the_cgroup_quota_are_warned_about(self, monkeypatch):
        import warnings

        from torchrl_rave.recipe import config
        from torchrl_rave.recipe.config import BusyCoresWarning, apply_process_settings

        threads = torch.get_num_threads()
        cfg = make_cfg(*TINY, "threads=2", "keep_freed_memory=false")
        monkeypatch.setattr(config, "busy_cores", lambda: (0.0, 2))
        try:
            monkeypatch.setattr(config, "cpu_quota", lambda: 1.5)
            with pytest.warns(BusyCoresWarning, match=r"torch runs 2 threads in this process, and "
                              r"its cgroup's CPU quota allows it 1\.5 cores' time.*threads=1 fits"):  # fmt: skip
                apply_process_settings(cfg)
            monkeypatch.setattr(config, "cpu_quota", lambda: 2.0)
            with warnings.catch_warnings():
                warnings.simplefilter("error", BusyCoresWarning)
                apply_process_settings(cfg)  # two cores' time for two threads
            cfg.threads = 4  # both limits at once: both named, the tighter one fits
            monkeypatch.setattr(config, "busy_cores", lambda: (1.6, 4))  # 2 free
            monkeypatch.setattr(config, "cpu_quota", lambda: 3.0)
            with pytest.warns(BusyCoresWarning, match=r"keep 1\.6 of the 4 cores it may use busy "
                              r"and its cgroup's CPU quota allows it 3 cores' time.*threads=2 fits"):  # fmt: skip
                apply_process_settings(cfg)
        finally:
            torch.set_num_threads(threads)
