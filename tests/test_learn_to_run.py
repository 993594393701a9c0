"""osim-rl's 2017 running task, ``LearnToRun-v0`` (the ``osim`` extra): the env, and the
recipe on it."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import rave_mujoco
import torch
from test_recipe import TINY, make_cfg

from torchrl_rave.envs import OSIM_IDS, import_env_family
from torchrl_rave.recipe.agent import make_env

L = pytest.importorskip("torchrl_rave.envs.learn_to_run", reason="needs the osim extra")
ALL_ALGORITHMS = ["ddpg", "mve", "steve", "rave", "rave_constant", "td3", "sac", "ppo"]


def make(**kwargs) -> L.LearnToRunEnv:
    return gym.make("LearnToRun-v0", **kwargs)


def test_spaces_and_the_standing_start():
    env = make()
    obs, info = env.reset(seed=0)
    assert env.action_space.shape == (18,)
    assert (env.action_space.low == 0).all() and (env.action_space.high == 1).all()
    assert obs.shape == (36,) == env.observation_space.shape and obs.dtype == np.float64
    assert np.isfinite(obs).all()
    # pelvis x, y = 0, 0.91 (the model's default), pelvis velocities 0, 18 muscles a side each
    assert obs[1] == 0 and obs[2] == pytest.approx(0.91) and info["pelvis_height"] == obs[2]
    assert (obs[3:6] == 0).all()
    names = env.unwrapped.muscle_names
    assert len(names) == 18 and sum(n.endswith("_r") for n in names) == 9
    # the body positions block ends with the ankles, which the reward measures
    assert np.allclose(obs[[32, 34]], env.unwrapped.leg_x())
    assert env.spec.max_episode_steps == 1000


def test_opensim_writes_no_log_into_the_package(tmp_path):
    """OpenSim would open opensim.log beside the first model it loads: the package's
    assets. A fresh process builds and steps the env; nothing appears there."""
    import subprocess
    import sys

    assets = Path(L.model_path()).parent
    log = assets / "opensim.log"
    log.unlink(missing_ok=True)
    # the env logs errors only; a model loaded at OpenSim's default level logs plenty
    code = ("import gymnasium as gym, opensim, torchrl_rave.envs.learn_to_run as L; "
            "e = gym.make('LearnToRun-v0'); e.reset(seed=0); e.step(e.action_space.sample()); "
            "opensim.Logger.setLevelString('info'); opensim.Model(L.model_path()).initSystem()")  # fmt: skip
    subprocess.run([sys.executable, "-c", code], cwd=tmp_path, check=True, capture_output=True)
    assert not log.exists() and not list(tmp_path.iterdir())


def test_same_seed_same_start_and_same_steps():
    a, b = make(), make()
    first_a, _ = a.reset(seed=3)
    first_b, _ = b.reset(seed=3)
    other, _ = b.reset(seed=4)
    np.testing.assert_array_equal(first_a, first_b)
    assert not np.array_equal(first_a, other)
    # the noise is on the six leg angles only, within its scale
    moved = np.flatnonzero(first_a != other)
    assert set(moved) >= set(range(6, 12)) and np.abs(first_a[6:12] - other[6:12]).max() <= 0.02
    b.reset(seed=3)
    action = np.linspace(0.0, 1.0, 18)
    for _ in range(3):
        step_a, step_b = a.step(action), b.step(action)
        np.testing.assert_array_equal(step_a[0], step_b[0])
        assert step_a[1] == step_b[1]


def test_reward_from_two_known_states():
    """Pose A is the default standing pose; pose B moves the pelvis 0.1 m forward and flexes
    the left hip by 0.2 rad. By planar geometry the right ankle moves 0.1 m and the left
    ankle 0.1 m plus its rotation about the hip centre: r = max(d_l, d_r) + 0.5."""
    env = make(reset_noise_scale=0.0).unwrapped
    env.reset(seed=0)
    hip = np.array(env._body_xy("femur_l"))
    ankle = np.array(env._body_xy("talus_l"))
    before = env.leg_x()
    assert before[0] == before[1]  # standing straight, both ankles level in x
    env.set_coordinates({"pelvis_tx": 0.1, "hip_flexion_l": 0.2})
    after = env.leg_x()
    v = ankle - hip
    rotated_x = hip[0] + np.cos(0.2) * v[0] - np.sin(0.2) * v[1]
    d_l, d_r = rotated_x + 0.1 - ankle[0], 0.1
    assert after - before == pytest.approx([d_l, d_r], abs=1e-9)
    assert d_l > 0.25  # the hip flexion swings the left foot forward by ~0.16 m
    assert env.reward(before, after) == pytest.approx(max(d_l, d_r) + 0.5, abs=1e-9)
    assert L.LearnToRunEnv.reward(np.array([0.0, 0.0]), np.array([-0.2, -0.1])) == 0.4


def test_steps_reward_what_the_legs_did_and_clip_actions():
    env = make()
    env.reset(seed=1)
    legs = env.unwrapped.leg_x()
    obs, reward, terminated, truncated, info = env.step(np.full(18, 0.3))
    assert reward == pytest.approx(np.max(env.unwrapped.leg_x() - legs) + 0.5)
    assert np.isfinite(obs).all() and not terminated and not truncated
    assert info["pelvis_height"] == obs[2] > 0.8
    # out-of-box excitations are clipped to [0, 1]: the same as the box's corners
    a, b = make(), make()
    a.reset(seed=1)
    b.reset(seed=1)
    high, low = np.r_[np.full(9, 2.0), np.full(9, -1.0)], np.r_[np.ones(9), np.zeros(9)]
    np.testing.assert_array_equal(a.step(high)[0], b.step(low)[0])


def test_a_fall_terminates_when_the_pelvis_is_below_0_65():
    env = make()
    env.reset(seed=0)
    terminated, steps = False, 0
    while not terminated and steps < 400:  # no excitation: the runner folds in about 1.3 s
        obs, _, terminated, truncated, _ = env.step(np.zeros(18))
        steps += 1
        assert terminated == (obs[2] < 0.65) and not truncated
    assert terminated and 50 < steps < 400, steps


def test_bad_actions_are_named():
    env = make()
    with pytest.raises(RuntimeError, match="reset"):
        env.unwrapped.step(np.zeros(18))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"18 muscle excitations.*\(17,\)"):
        env.unwrapped.step(np.zeros(17))
    with pytest.raises(ValueError, match="non-finite"):
        env.unwrapped.step(np.r_[np.zeros(17), np.nan])
    with pytest.raises(KeyError, match="no coordinate 'hip_r'"):
        env.unwrapped.set_coordinates({"hip_r": 0.0})


def test_torchrl_env_through_the_recipe_factory():
    env = make_env(make_cfg("env.name=LearnToRun-v0"), torch.device("cpu"))
    env.set_seed(0)
    rollout = env.rollout(5, break_when_any_done=False)
    assert rollout["next", "observation"].shape == (5, 36)
    assert rollout["next", "observation"].dtype == torch.float32
    assert ((rollout["action"] >= 0) & (rollout["action"] <= 1)).all()
    assert (rollout["next", "reward"] > 0.3).all()  # alive bonus 0.5 and small leg moves


@pytest.mark.parametrize("algorithm", ALL_ALGORITHMS)
def test_every_algorithm_trains_on_learn_to_run(algorithm, tmp_path):
    cfg = make_cfg(
        *TINY, f"algorithm={algorithm}", "env.name=LearnToRun-v0", "collector.total_frames=200",
        "env.kwargs={fall_height:0.85}",  # short episodes: falls end before the stiff contact
        "eval.interval=200", "eval.episodes=1", "world_model.pretrain_frames=100", "ppo.rollout_frames=100",
        "ppo.minibatch_size=50", "ppo.epochs=1",
    )  # fmt: skip
    results = rave_mujoco.train(cfg, str(tmp_path))
    assert results["frames"] == 200 and results["updates"] > 0
    assert results["eval/return"] > 0 and results["eval/falling_rate"] in (0.0, 1.0)


def test_the_id_is_listed_and_its_extra_named(hide_modules, tmp_path):
    assert OSIM_IDS == ("LearnToRun-v0", "LearnToMove-v0", "LearnToMove2D-v0")
    with pytest.raises(ValueError, match="(?s)not a registered gymnasium id.*LearnToRun-v0"):
        rave_mujoco.train(make_cfg(*TINY, "env.name=LearnToRun-v1"), str(tmp_path))
    hide_modules("torchrl_rave.envs.learn_to_run")
    with pytest.raises(ImportError, match=r"'opensim'.*pip install 'torchrl-rave\[osim\]'"):
        import_env_family("LearnToRun-v0")


def test_plot_runner_draws_an_episode(tmp_path, capsys):
    import plot_runner

    out = tmp_path / "runner.png"
    episode = plot_runner.main(["--excitation", "0.2", "--max-steps", "20", "--out", str(out)])
    assert len(episode["heights"]) == len(episode["frames"]) == 21 and not episode["fell"]
    # 20 steps of the alive bonus plus the legs' small forward moves
    assert 9.5 < episode["return"] < 10.5
    assert [len(line) for line in episode["frames"][0]] == [3, 6, 6]
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # no steps to draw is named, not an empty figure with a return of 0
    with pytest.raises(SystemExit, match="2"):
        plot_runner.main(["--max-steps", "0", "--out", str(tmp_path / "none.png")])
    assert "--max-steps must be >= 1, got 0" in capsys.readouterr().err
    assert not (tmp_path / "none.png").exists()
