"""The recipe with ``seeds=[...]``: S ordinary runs from one process, a group of one is the
single run, and a killed group resumes."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest
import torch
from test_recipe import TINY, kill_after_first_checkpoint, make_cfg, undocumented_metrics

from torchrl_rave.recipe.agent import load_policy, make_replay_buffer
from torchrl_rave.recipe.checkpoint import (
    DamagedCheckpoint,
    DamagedCheckpointWarning,
    RunCheckpoint,
)
from torchrl_rave.recipe.config import ConfigError
from torchrl_rave.recipe.loop import train
from torchrl_rave.recipe.runs import read_scalar

PENDULUM = [*TINY, "env.name=InvertedPendulum-v5", "collector.total_frames=600"]


def scalars(exp_dir: Path) -> dict[str, list[tuple[int, float]]]:
    out = {}
    for f in sorted((exp_dir / "scalars").rglob("*.csv")):
        name = str(f.relative_to(exp_dir / "scalars").with_suffix(""))
        if not name.startswith("time/"):  # wall-clock times differ run to run
            with open(f) as fh:
                out[name] = [(int(s), float(v)) for s, v in csv.reader(fh)]
    return out


@pytest.mark.parametrize("seeds", [[3], [5, 3]], ids=["one", "two"])
@pytest.mark.parametrize("algorithm", ["ddpg", "td3", "sac", "rave"])
def test_each_seed_of_a_group_is_its_single_run(algorithm, seeds, tmp_path):
    """Every seed of ``seeds=[...]`` logs what ``env.seed=<seed>`` logs alone: each draws from
    its own random stream, so neither a group of one nor the seed's place in a group of
    two changes what it draws. A group of one of DDPG, TD3 or SAC logs it bit for bit.
    Otherwise float rounding differs: the model-based update batches its world-model and
    critic calls differently (one ``baddbmm`` over seeds x members where the single
    learner broadcasts), and a batch of two seeds' matrices is not always rounded as one
    alone is, by parts in 1e-6 after a few hundred updates (DDPG's two-seed group: its
    actor loss and the evaluation's value error). So there: the same frames, returns and
    episode lengths, every other metric within 1e-3."""
    exact = len(seeds) == 1 and algorithm != "rave"
    group = ",".join(map(str, seeds))
    train(make_cfg(*PENDULUM, f"algorithm={algorithm}", f"seeds=[{group}]"), str(tmp_path / "g"))
    for seed in seeds:
        train(make_cfg(*PENDULUM, f"algorithm={algorithm}", f"env.seed={seed}"),
              str(tmp_path / f"one{seed}"))  # fmt: skip
        single = scalars(tmp_path / f"one{seed}" / algorithm)
        grouped = scalars(tmp_path / "g" / f"seed{seed}" / algorithm)
        assert single.keys() == grouped.keys()
        for name, rows in single.items():
            if exact or name in ("eval/return", "eval/episode_length"):
                assert grouped[name] == rows, f"seed {seed}: {name}"
            else:
                assert [s for s, _ in grouped[name]] == [s for s, _ in rows], name
                got = torch.tensor([v for _, v in grouped[name]], dtype=torch.float64)
                want = torch.tensor([v for _, v in rows], dtype=torch.float64)
                torch.testing.assert_close(got, want, rtol=1e-3, atol=1e-5,
                                           msg=f"seed {seed}: {name}")  # fmt: skip


def test_each_seed_is_an_ordinary_run(tmp_path, capsys):
    """Two seeds in one process: each seed directory is a run every reader takes as it is
    (its metrics documented, its checkpoint's config naming its seed, its policy loadable),
    and the seeds learned apart (different critics)."""
    out = train(make_cfg(*PENDULUM, "algorithm=steve", "seeds=[0,1]"), str(tmp_path))
    assert set(out) >= {"seed0/eval/return", "seed1/eval/return", "eval/return"}
    assert out["eval/return"] == pytest.approx(
        (out["seed0/eval/return"] + out["seed1/eval/return"]) / 2
    )
    losses = []
    for seed in (0, 1):
        run = tmp_path / f"seed{seed}"
        assert undocumented_metrics(run / "steve") == []
        steps, values = read_scalar(run, "eval/return")
        assert list(steps) == [200, 400, 600]
        assert values[-1] == out[f"seed{seed}/eval/return"]
        checkpoint = RunCheckpoint(run)
        assert checkpoint.read("config")["env"]["seed"] == seed
        assert checkpoint.read("counters")["frames"] == 600
        policy = load_policy(run)
        assert policy is not None
        losses.append(read_scalar(run, "train/loss_critic")[1])
    assert not (losses[0] == losses[1]).all()
    # resuming the finished group trains nothing, says so, and evaluates each seed's
    # restored policy as its last evaluation did
    again = train(make_cfg(*PENDULUM, "algorithm=steve", "seeds=[0,1]", f"resume={tmp_path}"),
                  "unused")  # fmt: skip
    assert "nothing to train: the group is at 600 frames" in capsys.readouterr().out
    for seed in (0, 1):
        assert again[f"seed{seed}/eval/return"] == out[f"seed{seed}/eval/return"]
    # the group's own directory is not a run: the errors say what to pass instead
    with pytest.raises(FileNotFoundError, match=r"group's directory.*one of them.*seed0.*seed1"):
        load_policy(tmp_path)
    steve = [*PENDULUM, "algorithm=steve", "collector.total_frames=800"]
    with pytest.raises(ConfigError, match=r"seeds is \[0, 2\] but the group was started with "
                                          r"\[0, 1\]"):  # fmt: skip
        train(make_cfg(*steve, "seeds=[0,2]", f"resume={tmp_path}"), "unused")
    with pytest.raises(ConfigError, match="holds one run, not a seed group"):
        train(make_cfg(*steve, "seeds=[0,1]", f"resume={tmp_path / 'seed0'}"), "unused")
    assert RunCheckpoint(tmp_path / "seed0").read("counters")["frames"] == 600  # untouched


def test_refuses_what_a_group_cannot_run():
    with pytest.raises(ConfigError, match="algorithm=ppo runs one seed per process"):
        train(make_cfg(*PENDULUM, "algorithm=ppo", "seeds=[0,1]"), "unused")
    with pytest.raises(ConfigError, match="distinct seeds"):
        train(make_cfg(*PENDULUM, "algorithm=ddpg", "seeds=[1,1]"), "unused")
    # gymnasium refuses a negative seed only at the first reset; the config says so first
    with pytest.raises(ConfigError, match=r"seeds=\[0, -1\] is invalid: expected null or a list"):
        train(make_cfg(*PENDULUM, "algorithm=ddpg", "seeds=[0,-1]"), "unused")


def test_kill_and_resume_continues_every_seed(tmp_path):
    """SIGKILL a group of two after its first checkpoints; ``resume=`` continues both seeds
    from the newest checkpoint they share: replay buffers kept, each seed's Adam state
    carried on (its step count, and moments that differ between the seeds)."""
    overrides = [*PENDULUM, "algorithm=rave", "seeds=[0,1]", "collector.total_frames=1200",
                 "checkpoint.interval=300", "eval.interval=1200"]  # fmt: skip
    f0 = kill_after_first_checkpoint(overrides, tmp_path, ("seed0", "seed1"))
    checkpoints = [RunCheckpoint(tmp_path / f"seed{s}") for s in (0, 1)]
    assert f0 % 300 == 0 and 300 <= f0 < 1200
    cfg = make_cfg(*overrides)
    saved = []
    for c in checkpoints:
        path = c.root / f"checkpoint-{f0:012d}"
        rb = make_replay_buffer(cfg, "cpu")
        c.load(replay_buffer=rb, path=path, restore_rng=False)
        state = c.read("optim_critic", path)["state"][0]
        saved.append((rb[:f0]["observation"].clone(), state["step"].item(), state["exp_avg"]))
    assert not torch.equal(saved[0][2], saved[1][2])  # each seed has its own moments

    out = train(make_cfg(*overrides, f"resume={tmp_path}"), "unused")
    assert set(out) >= {"seed0/eval/return", "seed1/eval/return"}
    new_updates = round(0.1 * (1200 - f0))
    for c, (obs, steps, _) in zip(checkpoints, saved, strict=True):
        assert c.read("counters")["frames"] == 1200
        rb = make_replay_buffer(cfg, "cpu")
        c.load(replay_buffer=rb, restore_rng=False)
        assert len(rb) == 1200
        assert torch.equal(rb[:f0]["observation"], obs)
        assert c.read("optim_critic")["state"][0]["step"].item() == steps + new_updates


def test_a_damaged_group_directory_is_named(tmp_path):
    """One seed's damaged newest checkpoint is set aside with a warning that names it
    (as a single run's resume does); a group file that is not one, or that names a seed
    with no directory, is named before anything is written; with nothing in common the
    error says which checkpoints are damaged and why."""
    group = [*PENDULUM, "algorithm=ddpg", "seeds=[0,1]", "collector.total_frames=300",
             "checkpoint.interval=100", "eval.interval=300"]  # fmt: skip
    trained = tmp_path / "trained"
    train(make_cfg(*group), str(trained))

    def copy(name):
        shutil.copytree(trained, tmp_path / name)
        return tmp_path / name

    def damage(checkpoint):
        (checkpoint / "checksums.json").write_text("{}")

    run = copy("one_damaged")
    damage(run / "seed1" / "checkpoints" / "checkpoint-000000000300")
    more = make_cfg(*group, "collector.total_frames=400", f"resume={run}")
    with pytest.warns(DamagedCheckpointWarning, match="seed1/checkpoints/checkpoint-0+300.*"
                      "resumes from frame 200"):  # fmt: skip
        train(more, "unused")
    assert (run / "seed1" / "checkpoints" / "damaged" / "checkpoint-000000000300").is_dir()
    assert RunCheckpoint(run / "seed1").read("counters")["frames"] == 400

    run = copy("all_damaged")
    for checkpoint in RunCheckpoint(run / "seed1").checkpoints():
        damage(checkpoint)
    with pytest.raises(FileNotFoundError, match="no checkpoint that every seed .* damaged: "
                       ".*seed1/checkpoints/checkpoint-0+300.* is unreadable"):  # fmt: skip
        train(make_cfg(*group, f"resume={run}"), "unused")

    run = copy("bad_file")
    (run / "group.json").write_text("{not json")
    with pytest.raises(DamagedCheckpoint, match="group.json is not a seed group's file"):
        train(make_cfg(*group, f"resume={run}"), "unused")

    run = copy("unknown_seed")
    data = json.loads((run / "group.json").read_text())
    data["config"]["seeds"] = [0, 1, 7]
    (run / "group.json").write_text(json.dumps(data))
    with pytest.raises(ConfigError, match=r"names seed\(s\) \[7\] that have no seed<s>/"):
        train(make_cfg(*group[:-3], "seeds=[0,1,7]", f"resume={run}"), "unused")
    assert not (run / "seed7").exists()
