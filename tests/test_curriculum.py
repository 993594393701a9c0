"""The curriculum: stage by stage by hand, the recipe's ``curriculum`` keys rebuilding the
envs at each stage, and a resume that continues the stage it was in."""

from __future__ import annotations

import pytest
import rave_mujoco
import terms_env  # noqa: F401  registers LevelPendulum-v0
from test_recipe import TINY, make_cfg

from torchrl_rave.recipe import loop
from torchrl_rave.recipe.config import ConfigError, check_config
from torchrl_rave.recipe.runs import read_scalar
from torchrl_rave.trainers import Curriculum


def test_stages_advance_on_their_own_thresholds_and_the_last_stays():
    c = Curriculum([[2.5, 3.5], [1.5, 2.5], [0.8, 1.8]], thresholds=[100.0, 200.0])
    assert c.value == [2.5, 3.5]
    assert not c.update({}) and not c.update({"eval/return": 99.0}) and c.stage == 0
    assert c.update({"eval/return": 150.0}) and c.value == [1.5, 2.5]
    assert not c.update({"eval/return": 150.0})  # stage 1 ends at 200
    assert c.update({"eval/return": 200.0}) and c.stage == 2
    assert not c.update({"eval/return": 1e9}) and c.value == [0.8, 1.8]
    c.load_state_dict({"stage": 1})
    assert c.value == [1.5, 2.5]
    with pytest.raises(ValueError, match="stage 3"):
        c.load_state_dict({"stage": 3})
    with pytest.raises(ValueError, match="needs 2 thresholds, got 1"):
        Curriculum([1, 2, 3], thresholds=[1.0])
    assert Curriculum([1, 2, 3], thresholds=5.0, metric="eval/falling_rate").thresholds == [
        5.0,
        5.0,
    ]


def test_bad_curriculum_keys_are_named():
    with pytest.raises(ConfigError) as err:
        check_config(make_cfg(*TINY, "curriculum.kwarg=level", "curriculum.stages=[1,2,3]",
                              "curriculum.thresholds=[0]", "curriculum.metric=eval/speed"))  # fmt: skip
    text = str(err.value)
    assert "curriculum.thresholds" in text and "2 finite numbers" in text
    assert "curriculum.metric" in text and "eval/return" in text
    with pytest.raises(ConfigError, match="curriculum.stages"):
        check_config(make_cfg(*TINY, "curriculum.stages=[1,2]"))  # no key


def test_each_stage_builds_its_envs_and_a_resume_continues_the_stage(tmp_path):
    """Thresholds every return passes: the stage moves on at each evaluation (every 100
    frames) but the run's last. The evaluation return per step is the level the eval env
    was built with: 4 at 100 frames (the first stage's, not the env's default of 1), 2 at
    200 (the end of the first run, which stays in stage 1), and after the resume 2 at 300
    (the stage came back from the checkpoint) and 3 at 400."""
    run = tmp_path / "run"
    args = [*TINY, "env.name=terms_env:LevelPendulum-v0", "algorithm=ddpg", "eval.interval=100",
            "eval.episodes=1", "checkpoint.interval=100", "curriculum.kwarg=level",
            "curriculum.stages=[4.0,2.0,3.0]", "curriculum.thresholds=[-1e9,-1e9]"]  # fmt: skip
    rave_mujoco.train(make_cfg(*args, "collector.total_frames=200"), str(run))
    rave_mujoco.train(make_cfg(*args, f"resume={run}", "collector.total_frames=400"), str(run))
    steps, returns = read_scalar(run, "eval/return")
    _, lengths = read_scalar(run, "eval/episode_length")
    assert steps.tolist() == [100, 200, 300, 400]
    assert (returns / lengths).tolist() == pytest.approx([4.0, 2.0, 2.0, 3.0])
    # the stage each batch was collected in
    steps, stages = read_scalar(run, "train/curriculum_stage")
    assert steps.tolist() == [100, 200, 300, 400] and stages.tolist() == [0, 1, 1, 2]


def test_the_first_stage_builds_the_training_and_evaluation_envs(tmp_path, monkeypatch):
    """The direct backend's training env and the evaluation env carry the first stage's
    value from the start (they were once built from the config alone, so stage 0 ran at
    the env's default), and a keyword the env does not take fails before any frame."""
    built = []
    make_env = loop.make_env

    def recording_make_env(cfg, *args, **kwargs):
        built.append(dict(cfg.env.kwargs or {}))
        return make_env(cfg, *args, **kwargs)

    monkeypatch.setattr(loop, "make_env", recording_make_env)
    args = [*TINY, "env.name=terms_env:LevelPendulum-v0", "algorithm=ddpg", "eval.interval=100",
            "eval.episodes=1", "curriculum.kwarg=level", "curriculum.stages=[4.0,2.0]",
            "curriculum.thresholds=[1e9]", "collector.total_frames=200"]  # fmt: skip
    rave_mujoco.train(make_cfg(*args), str(tmp_path / "run"))
    assert built == [{"level": 4.0}, {"level": 4.0}]  # training env, evaluation env
    steps, returns = read_scalar(tmp_path / "run", "eval/return")
    _, lengths = read_scalar(tmp_path / "run", "eval/episode_length")
    assert (returns / lengths).tolist() == pytest.approx([4.0, 4.0])
    monkeypatch.setattr(loop, "make_env", make_env)
    with pytest.raises(Exception, match="speed") as err:
        rave_mujoco.train(make_cfg(*args[:-4], "curriculum.kwarg=speed",
                                   "curriculum.stages=[4.0,2.0]", "curriculum.thresholds=[1e9]",
                                   "collector.total_frames=200"), str(tmp_path / "bad"))  # fmt: skip
    assert not any((tmp_path / "bad").glob("*/scalars/train/*.csv")), err.value


def test_a_checkpoint_whose_stage_is_not_a_stage_is_named(tmp_path):
    """The probe: a tampered ``curriculum_stage`` gave a ValueError traceback."""
    from test_trust import component, rechecksum

    from torchrl_rave.recipe.checkpoint import RunCheckpoint

    run = tmp_path / "run"
    args = [*TINY, "env.name=terms_env:LevelPendulum-v0", "algorithm=ddpg", "eval.interval=100",
            "eval.episodes=1", "curriculum.kwarg=level", "curriculum.stages=[4.0,2.0]",
            "curriculum.thresholds=[1e9]"]  # fmt: skip
    rave_mujoco.train(make_cfg(*args, "collector.total_frames=100"), str(run))
    for checkpoint in RunCheckpoint(run).checkpoints():
        path = component(checkpoint, "counters") / "value.json"
        path.write_text(path.read_text().replace('"curriculum_stage": 0', '"curriculum_stage": 7'))
        rechecksum(checkpoint)
    with pytest.raises(ValueError, match="checkpoint-0+100: its counters hold curriculum_stage="
                       "7, not a stage of curriculum.stages \\(2 stages"):  # fmt: skip
        rave_mujoco.train(make_cfg(*args, f"resume={run}", "collector.total_frames=200"), "x")
