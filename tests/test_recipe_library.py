"""torchrl_rave.recipe: run checkpoints (no pickle, two kept, old format refused),
load_policy from a run directory, the run-directory reader, and the house rules."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import rave_mujoco
import torch
from tensordict import TensorDict
from test_recipe import TINY, make_cfg

from torchrl_rave.recipe import load_agent, load_policy
from torchrl_rave.recipe.checkpoint import RunCheckpoint
from torchrl_rave.recipe.runs import read_scalar, train_seconds, value_logged_at

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def rave_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("rave_run")
    overrides = [*TINY, "algorithm=rave", "collector.total_frames=600", "checkpoint.interval=200"]
    rave_mujoco.train(make_cfg(*overrides), str(run))
    return run


class TestRunCheckpoint:
    def test_keeps_the_last_two_and_stores_no_pickle(self, rave_run):
        names = sorted(p.name for p in (rave_run / "checkpoints").iterdir())
        assert names == ["checkpoint-000000000400", "checkpoint-000000000600"]
        files = [p for p in (rave_run / "checkpoints").rglob("*") if p.is_file()]
        assert files and not [p for p in files if p.suffix in (".pt", ".pth", ".pkl", ".pickle")]
        # every tensor is a memory map, everything else JSON
        assert {p.suffix for p in files} <= {".json", ".memmap"}

    def test_reads_components_as_plain_data(self, rave_run):
        checkpoint = RunCheckpoint(rave_run)
        assert checkpoint.read("counters")["frames"] == 600
        assert checkpoint.read("config")["algorithm"] == "rave"
        critic = checkpoint.read("optim_critic")
        # 0.1 updates per frame once the 200 pretraining frames are stored
        assert critic["state"][0]["step"].item() == 0.1 * (600 - 200)
        with pytest.raises(KeyError, match="no component 'nope'"):
            checkpoint.read("nope")

    def test_a_checkpoint_from_before_the_redesign_is_refused(self, tmp_path):
        old = tmp_path / "checkpoints"
        (old / "000000000200").mkdir(parents=True)
        (old / "000000000200" / "state.pt").write_bytes(b"not to be unpickled")
        (old / "latest").write_text("000000000200")
        with pytest.raises(ValueError, match="before the torchrl.checkpoint redesign"):
            RunCheckpoint(tmp_path).latest()
        with pytest.raises(ValueError, match="pickled state.pt"):
            rave_mujoco.train(make_cfg(*TINY, f"resume={tmp_path}"), "unused")


class TestLoadPolicy:
    def test_the_loaded_policy_acts_as_the_trained_one(self, rave_run):
        policy = load_policy(rave_run)
        cfg, agent = load_agent(rave_run)
        assert cfg.algorithm == "rave" and agent.world_model is not None
        obs = torch.randn(5, 4)  # InvertedPendulum-v5
        action = policy(TensorDict(observation=obs, batch_size=[5]))["action"]
        assert action.shape == (5, 1) and (action.abs() <= 3.0).all()
        # the trained weights, not a fresh initialisation: the checkpoint's actor params
        saved = RunCheckpoint(rave_run).read("loss")
        for key, value in saved.items():
            if key.startswith("actor_network_params"):
                name = tuple(key.split(".")[1:])
                torch.testing.assert_close(agent.loss.actor_network_params.get(name), value)
        fresh = load_policy(rave_run)(TensorDict(observation=obs, batch_size=[5]))["action"]
        torch.testing.assert_close(fresh, action)
        assert policy.in_keys == ["observation"] and "action" in policy.out_keys

    @pytest.mark.parametrize(
        "observation, problem",
        [
            (
                torch.zeros(5, 11),
                r"entry 'observation' has shape \(5, 11\), expected last dimension 4",
            ),
            (torch.zeros(5, 4, dtype=torch.float64), "is torch.float64 but the model's parameters"),
            (torch.zeros(5, 4, dtype=torch.long), "is torch.int64, expected a floating-point"),
            (torch.full((5, 4), float("nan")), "entry 'observation' holds NaN"),
        ],
    )
    def test_the_loaded_policy_names_bad_observations(self, rave_run, observation, problem):
        # e.g. a Hopper observation (11 wide) fed to an InvertedPendulum policy (4 wide):
        # named, instead of torch's "mat1 and mat2 shapes cannot be multiplied"
        for explore in (False, True):
            with pytest.raises(ValueError, match=problem):
                load_policy(rave_run, explore=explore)(
                    TensorDict(observation=observation, batch_size=[5])
                )
        with pytest.raises(ValueError, match="no entry 'observation'"):
            load_policy(rave_run)(TensorDict(obs=torch.zeros(5, 4), batch_size=[5]))


class TestRunReader:
    def test_a_resumed_run_reads_like_an_uninterrupted_one(self, tmp_path):
        scalars = tmp_path / "rave" / "scalars" / "eval"
        scalars.mkdir(parents=True)
        # logged 200, 400, 600; killed; resumed from the 400 checkpoint: 600 and 800 again
        rows = [(200, 1.0), (400, 2.0), (600, 3.0), (600, 3.5), (800, 4.0)]
        (scalars / "return.csv").write_text("".join(f"{s},{v}\n" for s, v in rows))
        steps, values = read_scalar(tmp_path, "eval/return")
        np.testing.assert_array_equal(steps, [200, 400, 600, 800])
        np.testing.assert_array_equal(values, [1.0, 2.0, 3.5, 4.0])
        assert value_logged_at(tmp_path, "eval/return", 600) == 3.5
        assert value_logged_at(tmp_path, "eval/return", 1000) is None
        assert value_logged_at(tmp_path / "missing", "eval/return", 600) is None

    def test_train_seconds_sum_each_batch_once(self, tmp_path):
        timing = tmp_path / "rave" / "scalars" / "time"
        timing.mkdir(parents=True)
        # batch 200 logged twice (a resume): the later 2.5 counts; eval only at 400
        for name, rows in {
            "collect_s": [(200, 1.0), (200, 1.5), (400, 1.0)],
            "update_s": [(200, 9.0), (200, 10.0), (400, 11.0)],
            "eval_s": [(400, 3.25)],
        }.items():
            (timing / f"{name}.csv").write_text("".join(f"{s},{v}\n" for s, v in rows))
        assert train_seconds(tmp_path) == round(1.5 + 1.0 + 10.0 + 11.0 + 3.25)
        assert train_seconds(tmp_path / "missing") is None


class TestOtherLoggers:
    """The analyses read what every logger backend leaves in a run directory, or say why
    they cannot."""

    def test_a_tensorboard_run_reads_like_its_csv_twin(self, tmp_path):
        import plot_curves

        runs = {}
        for backend in ("csv", "tensorboard"):
            runs[backend] = tmp_path / backend
            cfg = make_cfg(*TINY, "algorithm=ddpg", f"logger.backend={backend}")
            rave_mujoco.train(cfg, str(runs[backend]))
        assert not list(runs["tensorboard"].glob("*/scalars"))  # nothing but events
        for metric in ("eval/return", "train/loss_critic", "eval/q_bias"):
            steps, values = read_scalar(runs["tensorboard"], metric)
            csv_steps, csv_values = read_scalar(runs["csv"], metric)
            assert steps.tolist() == csv_steps.tolist()
            np.testing.assert_allclose(values, csv_values, rtol=1e-6)  # events hold float32
        text = plot_curves.main([f"tb={runs['tensorboard']}", "--out", str(tmp_path / "c.png")])
        assert "| tb | 1 |" in text

    def test_an_mlflow_run_reads_like_its_csv_twin_across_a_resume(self, tmp_path):
        """TorchRL's MLflow logger on a store inside the run directory; a resumed run is a
        second MLflow run there, and the reader joins them (the later value of a step wins)."""
        runs = {b: tmp_path / b for b in ("csv", "mlflow")}
        for backend, run in runs.items():
            first = [
                *TINY,
                "algorithm=ddpg",
                f"logger.backend={backend}",
                "collector.total_frames=200",
            ]
            rave_mujoco.train(make_cfg(*first), str(run))
            more = [*first[:-1], "collector.total_frames=400", f"resume={run}"]
            rave_mujoco.train(make_cfg(*more), "unused")
        assert (runs["mlflow"] / "mlflow.db").is_file() and not list(
            runs["mlflow"].glob("*/scalars")
        )
        from mlflow.tracking import MlflowClient

        client = MlflowClient(tracking_uri=f"sqlite:///{runs['mlflow'] / 'mlflow.db'}")
        (exp,) = [e for e in client.search_experiments() if e.name == "ddpg"]
        assert len(client.search_runs([exp.experiment_id])) == 2  # one per start
        for metric in ("eval/return", "train/loss_critic", "eval/q_rmse"):
            steps, values = read_scalar(runs["mlflow"], metric)
            csv_steps, csv_values = read_scalar(runs["csv"], metric)
            assert steps.tolist() == csv_steps.tolist() and steps[-1] == 400
            np.testing.assert_array_equal(values, csv_values)

    def test_a_run_logged_nowhere_is_refused_with_the_reason(self, tmp_path):
        rave_mujoco.train(make_cfg(*TINY, "algorithm=ddpg", "logger.backend="), str(tmp_path))
        with pytest.raises(
            FileNotFoundError, match=r"logged its metrics nowhere .*csv, tensorboard or mlflow"
        ):
            read_scalar(tmp_path, "eval/return")


def test_a_misspelt_metric_is_named_with_the_close_ones(tmp_path):
    # it said "no CSV or TensorBoard metrics here" of a run full of them
    for metric, value in (
        ("eval/return", 1.0),
        ("eval/return_std", 0.0),
        ("train/loss_critic", 2.0),
    ):
        path = tmp_path / "ddpg" / "scalars" / f"{metric}.csv"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(f"100,{value}\n")
    with pytest.raises(FileNotFoundError, match=re.escape(
        "no 'eval/retrun' logged; did you mean ['eval/return', 'eval/return_std']?"
    )):  # fmt: skip
        read_scalar(tmp_path, "eval/retrun")
    with pytest.raises(FileNotFoundError, match=re.escape(
        "no 'zzz' logged; it logged ['eval/return', 'eval/return_std', 'train/loss_critic']"
    )):  # fmt: skip
        read_scalar(tmp_path, "zzz")
    assert read_scalar(tmp_path, "train/loss_critic")[1].tolist() == [2.0]


def test_no_sys_path_edits_anywhere():
    offenders = [
        str(p.relative_to(ROOT))
        for p in ROOT.glob("*/**/*.py")
        if ".venv" not in p.parts and re.search(r"sys\.path\.(insert|append)", p.read_text())
    ]
    assert offenders == []


def test_recipe_files_stay_small():
    sizes = {p.name: len(p.read_text().splitlines()) for p in (ROOT / "recipes").glob("*.py")}
    assert max(sizes.values()) <= 300, sizes
