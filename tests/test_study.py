"""study.py: the t-interval by hand, the report from results/ alone (resumed runs read
once), and a real one-cell study that exports its cell and skips it on the next run."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import study
import study_compare
import torch
from test_recipe import TINY

from torchrl_rave.recipe.config import ConfigError
from torchrl_rave.recipe.runs import read_scalar, relogged
from torchrl_rave.recipe.stats import interval95

RAVE_DIAGNOSTICS = ["rave_alpha", "wm_transition_mse"] + [f"horizon_weight_h{h}" for h in range(4)]


def write_study(tmp_path: Path, **fields) -> Path:
    spec = {
        "name": "tiny",
        "tasks": ["Hopper-v5"],
        "algorithms": ["rave", "ddpg"],
        "seeds": [0, 1],
        "frames": 200,
        **fields,
    }
    path = tmp_path / "tiny.yaml"
    path.write_text(json.dumps(spec))  # JSON is YAML
    return path


def write_cell(
    results: Path,
    algorithm: str,
    seed: int,
    metrics: dict[str, list],
    episodes: int = 10,
    task: str = "Hopper-v5",
    study: str = "tiny",
) -> None:
    cell = results / study / task / algorithm / f"seed{seed}"
    for metric, rows in metrics.items():
        csv = cell / algorithm / "scalars" / f"{metric}.csv"
        csv.parent.mkdir(parents=True, exist_ok=True)
        csv.write_text("".join(f"{step},{value}\n" for step, value in rows))
    (cell / "cell.json").write_text(json.dumps({"config": {"eval": {"episodes": episodes}}}))


def test_interval95_by_hand():
    mean, half = interval95(np.array([1.0, 2.0, 3.0]))
    assert mean == 2.0
    # t(0.975, 2) * s / sqrt(n); at 2 degrees of freedom the quantile has the closed form
    # (2p - 1) / sqrt(2 p (1 - p)), 4.3027 at p = 0.975
    assert half == pytest.approx(0.95 / np.sqrt(2 * 0.975 * 0.025) * 1.0 / np.sqrt(3))
    assert np.isnan(interval95(np.array([5.0]))[1])


def test_report_from_results_alone(tmp_path, capsys):
    results, figures = tmp_path / "results", tmp_path / "figures"
    diag = {f"train/{m}": [(100, 0.5), (200, 0.25)] for m in RAVE_DIAGNOSTICS}
    # seed 0 was resumed: step 100 was logged twice, the later value (10) counts
    write_cell(results, "rave", 0, {"eval/return": [(100, 99), (100, 10), (200, 20)],
                                    "eval/falling_rate": [(100, 1.0), (200, 0.5)], **diag})  # fmt: skip
    # seed 1 evaluated over 20 episodes: falls pool as 5 of 10 and 0 of 20, 5 / 30
    write_cell(results, "rave", 1, {"eval/return": [(100, 30), (200, 40)],
                                    "eval/falling_rate": [(100, 1.0), (200, 0.0)], **diag},
               episodes=20)  # fmt: skip
    write_cell(results, "ddpg", 0, {"eval/return": [(100, 7), (200, 8)],
                                    "eval/falling_rate": [(100, 1.0), (200, 1.0)]})  # fmt: skip
    # ddpg seed 1 has metrics but no cell.json: unfinished, left out
    write_cell(results, "ddpg", 1, {"eval/return": [(100, 1000), (200, 1000)],
                                    "eval/falling_rate": [(100, 0.0), (200, 0.0)]})  # fmt: skip
    (results / "tiny" / "Hopper-v5" / "ddpg" / "seed1" / "cell.json").unlink()
    study.main(["report", "--config", str(write_study(tmp_path)), "--results", str(results),
                "--figures", str(figures)])  # fmt: skip
    table = (figures / "tiny.md").read_text()
    # rave: [10, 30] at 100 and [20, 40] at 200: mean 20 / 30, half 12.706 * 14.14 / 1.414
    # the last quarter (after 150 frames) holds the 200-frame evaluations only
    # Wilson 95 %: 5 / 30 gives [0.073, 0.336], 10 / 10 gives [0.722, 1]
    assert "| Hopper-v5 | rave | 2 | 20 ± 127 | 30 ± 127 | 30 ± 127 | 0.17 [0.07, 0.34] |" in table
    row = "| Hopper-v5 | ddpg | 1 | 7 (1 seed) | 8 (1 seed) | 8 (1 seed) | 1.00 [0.72, 1.00] |"
    assert row in table
    # one ddpg seed: a difference, no interval
    assert "| Hopper-v5 | rave - ddpg | +13 (1 seed) | +22 (1 seed) |" in table
    # the published numbers are at 100k frames: no reference column beside a 200-frame study
    assert "reference" not in table
    # no time/*_s metrics in these cells: no cost table
    assert "What the finished cells cost" not in table
    assert table in capsys.readouterr().out
    for name in ("return", "falling_rate", "rave_diagnostics", "rave_model_error"):
        assert (figures / f"tiny_Hopper-v5_{name}.png").stat().st_size > 10_000


def test_run_exports_a_finished_cell_and_skips_it_next_time(tmp_path, capsys, monkeypatch):
    """One real cell (DDPG, 400 frames): its CSVs and cell.json land in results/, nothing
    of its checkpoints does, and a second run has nothing to do. Its commit is the one
    its run started at, though HEAD moves before the export (a runner committing its
    results into its own checkout)."""
    heads = iter(["a" * 40] + ["b" * 40] * 10)
    real_git = study.git
    monkeypatch.setattr(study, "git", lambda repo, *a: next(heads) if a == ("rev-parse", "HEAD")
                        else real_git(repo, *a))  # fmt: skip
    config = write_study(tmp_path, algorithms=["ddpg"], seeds=[0], frames=400,
                         overrides=[o for o in TINY if "total_frames" not in o])  # fmt: skip
    args = ["run", "--config", str(config), "--results", str(tmp_path / "results"),
            "--out", str(tmp_path / "runs"), "--jobs", "1"]  # fmt: skip
    study.main(args)
    cell = tmp_path / "results" / "tiny" / "Hopper-v5" / "ddpg" / "seed0"
    info = json.loads((cell / "cell.json").read_text())
    assert info["frames"] == 400 and info["commit"] == "a" * 40
    assert [(s["commit"], s["from_frame"]) for s in info["starts"]] == [(info["commit"], 0)]
    # the cell's own seconds: its batches' collection, update and evaluation times
    timed = sum(
        read_scalar(tmp_path / "runs" / "tiny" / "Hopper-v5" / "ddpg" / "seed0", m)[1].sum()
        for m in ("time/collect_s", "time/update_s", "time/eval_s")
    )
    assert info["train_s"] == round(timed) and info["runner_s"] >= info["train_s"]
    assert info["config"]["algorithm"] == "ddpg" and info["config"]["env"]["seed"] == 0
    assert info["machine"]["torch"] == torch.__version__ and info["machine"]["cpu"]
    assert info["starts"][-1]["machine"] == info["machine"]  # each start records its own
    steps, _ = read_scalar(cell, "eval/return")
    assert steps.tolist() == [200, 400]
    assert not list(cell.rglob("checkpoint*"))
    study.main(args)
    assert "tiny: 0 cells to go" in capsys.readouterr().out


def test_report_gives_rave_minus_each_algorithm_with_welch_intervals(tmp_path):
    results, figures = tmp_path / "results", tmp_path / "figures"
    falls = {"eval/falling_rate": [(100, 1.0), (200, 1.0)]}
    diag = {f"train/{m}": [(100, 0.5), (200, 0.25)] for m in RAVE_DIAGNOSTICS}
    for seed, (rave, ddpg) in enumerate([((10, 20), (0, 5)), ((30, 40), (10, 5))]):
        write_cell(results, "rave", seed, {"eval/return": [(100, rave[0]), (200, rave[1])], **falls, **diag})  # fmt: skip
        write_cell(results, "ddpg", seed, {"eval/return": [(100, ddpg[0]), (200, ddpg[1])], **falls})  # fmt: skip
    study.main(["report", "--config", str(write_study(tmp_path)), "--results", str(results),
                "--figures", str(figures)])  # fmt: skip
    table = (figures / "tiny.md").read_text()
    # at 100: 20 - 5, se = sqrt(200 / 2 + 50 / 2) = 11.18, times t(0.975, 1) = 12.706: 142;
    # at 200: 30 - 5, se = sqrt(200 / 2 + 0 / 2) = 10: 127
    assert "| task | difference | at 100 | at 200 |" in table
    assert "| Hopper-v5 | rave - ddpg | +15 ± 142 | +25 ± 127 |" in table


def test_difference95_by_hand():
    from torchrl_rave.recipe.stats import difference95, t975

    a, b = np.array([1.0, 4.0, 4.0, 7.0]), np.array([0.0, 2.0, 4.0])
    diff, half = difference95(a, b)
    # means 4 and 2; variances 6 and 4; se = sqrt(6 / 4 + 4 / 3); min(4, 3) - 1 = 2 dof
    t2 = 0.95 / np.sqrt(2 * 0.975 * 0.025)  # t(0.975, 2), closed form
    assert diff == 2.0 and half == pytest.approx(t2 * np.sqrt(6 / 4 + 4 / 3))
    assert np.isnan(difference95(a, np.array([1.0]))[1])
    # one degree of freedom is Cauchy's tan(pi (p - 1/2)); many approach the normal's 1.96
    assert t975(1) == pytest.approx(np.tan(np.pi * 0.475))
    assert t975(200) == pytest.approx(1.9719, abs=1e-4) and 1.96 < t975(200) < t975(20)
    with pytest.raises(ValueError, match="degree of freedom"):
        t975(0)


def test_report_puts_the_100k_reference_beside_a_100k_study(tmp_path):
    results, figures = tmp_path / "results", tmp_path / "figures"
    for seed in (0, 1):
        returns = [(50_000, 5 + seed), (80_000, 2 + 4 * seed), (100_000, 9)]
        write_cell(results, "ddpg", seed, {"eval/return": returns,
                                           "eval/falling_rate": [(50_000, 1.0), (100_000, 1.0)]})  # fmt: skip
    config = write_study(tmp_path, frames=100_000)
    study.main(["report", "--config", str(config), "--results", str(results),
                "--figures", str(figures)])  # fmt: skip
    table = (figures / "tiny.md").read_text()
    assert "| falling rate | reference at 100k (tianshou, gym v3; not ours) |" in table
    # after 75,000 frames: seed 0 (2 + 9) / 2 = 5.5, seed 1 (6 + 9) / 2 = 7.5; mean 6.5,
    # half-width 12.706 * 1.414 / 1.414 = 12.7. TianShou's DDPG on Hopper at 100k is 904
    # (recipes/compare.py); rave has no reference
    assert "| Hopper-v5 | ddpg | 2 | 6 ± 6 | 9 ± 0 | 6 ± 13 | 1.00 [0.84, 1.00] | 904 |" in table
    assert "| Hopper-v5 | rave | 0 | n/a | n/a | n/a | n/a |  |" in table


def test_report_sums_each_cells_own_seconds(tmp_path):
    results, figures = tmp_path / "results", tmp_path / "figures"
    ev = {"eval/return": [(100, 1.0), (200, 2.0)], "eval/falling_rate": [(100, 1.0), (200, 1.0)]}
    # seed 0: 60 + 120 s collecting, 600 + 1,200 s updating, 30 s evaluating = 2,010 s;
    # seed 1 was resumed at 100: the later 100-frame values count, (90 + 120) + (900 +
    # 1,200) + 30 = 2,340 s. 33.5 and 39 minutes, 1.2 hours in all
    write_cell(results, "ddpg", 0, {**ev, "time/collect_s": [(100, 60), (200, 120)],
               "time/update_s": [(100, 600), (200, 1200)], "time/eval_s": [(200, 30)]})  # fmt: skip
    write_cell(results, "ddpg", 1, {**ev, "time/collect_s": [(100, 5), (100, 90), (200, 120)],
               "time/update_s": [(100, 900), (200, 1200)], "time/eval_s": [(200, 30)]})  # fmt: skip
    config = write_study(tmp_path, algorithms=["ddpg"])
    study.main(["report", "--config", str(config), "--results", str(results),
                "--figures", str(figures)])  # fmt: skip
    table = (figures / "tiny.md").read_text()
    assert "| Hopper-v5 | ddpg | 2 | 34 | 39 | 1.2 |" in table


def test_missing_cells_run_interrupted_first_then_seed_by_seed_across_tasks(tmp_path):
    config = write_study(tmp_path, tasks=["Hopper-v5", "Walker2d-v5"], seeds=[0, 1])
    results, out = tmp_path / "results", tmp_path / "runs"
    write_cell(results, "rave", 0, {"eval/return": [(200, 1.0)]})  # Hopper rave seed 0: done
    loaded = study.load_study(config)
    first = study.missing_cells(loaded, results, out)
    # Walker2d ddpg seed 1 was interrupted: it has a checkpoint and resumes first
    (next(c for c in first if "Walker2d-v5/ddpg/seed1" in str(c.run_dir)).run_dir
     / "checkpoints" / "checkpoint-000000000100").mkdir(parents=True)  # fmt: skip
    order = ["/".join(c.run_dir.parts[-3:]) for c in study.missing_cells(loaded, results, out)]
    assert order == [
        "Walker2d-v5/ddpg/seed1",
        "Hopper-v5/ddpg/seed0",
        "Walker2d-v5/rave/seed0",
        "Walker2d-v5/ddpg/seed0",
        "Hopper-v5/rave/seed1",
        "Hopper-v5/ddpg/seed1",
        "Walker2d-v5/rave/seed1",
    ]


@pytest.mark.parametrize(
    "name, env", [("stochastic100k", "Hopper-v5"), ("stochastic100k_walker2d", "Walker2d-v5")]
)
def test_the_stochastic_study_has_its_36_cells_with_their_noise(name, env, tmp_path):
    config = Path(study.__file__).parent / "study" / f"{name}.yaml"
    loaded = study.load_study(config)
    cells = study.missing_cells(loaded, tmp_path / "results", tmp_path / "runs")
    assert len(cells) == 36
    by_dir = {"/".join(c.run_dir.parts[-3:]): c for c in cells}
    noisy = by_dir[f"{env}-noise0.3/mve/seed2"]
    assert f"env.name={env}" in noisy.overrides and "env.action_noise=0.3" in noisy.overrides
    assert noisy.frames == 100_000 and "eval.episodes=10" in noisy.overrides
    assert "env.action_noise=0" in by_dir[f"{env}-noise0/mve/seed2"].overrides
    assert cells[noisy] == tmp_path / f"results/{name}/{env}-noise0.3/mve/seed2"
    # seed 0 of both noise levels and all six algorithms come first
    first = ["/".join(c.run_dir.parts[-3:]) for c in list(cells)[:12]]
    assert all(name.endswith("seed0") for name in first)
    assert {name.split("/")[0] for name in first} == {f"{env}-noise0", f"{env}-noise0.3"}
    # every cell's overrides make a valid recipe config
    from test_recipe import make_cfg

    from torchrl_rave.recipe.config import check_config

    check_config(make_cfg(*noisy.overrides, f"collector.total_frames={noisy.frames}"))


def test_task_labels_must_differ(tmp_path):
    twice = {"label": "a", "env": "Hopper-v5"}
    with pytest.raises(ValueError, match="labels repeat"):
        study.load_study(write_study(tmp_path, tasks=[twice, twice]))
    with pytest.raises(ValueError, match="label and an env"):
        study.load_study(write_study(tmp_path, tasks=[{"env": "Hopper-v5"}]))


def test_run_queues_several_studies_in_one_grid(tmp_path, capsys, monkeypatch):
    seen = []
    monkeypatch.setattr(study, "launch_grid", lambda script, todo, jobs, **kw: seen.extend(todo))
    # 300 frames: a run's budget holds at least one batch of 250 (checked before any starts)
    a = write_study(tmp_path, name="a", algorithms=["ddpg"], seeds=[0], frames=300)
    b = tmp_path / "b.yaml"
    b.write_text(json.dumps({"name": "b", "tasks": ["Walker2d-v5"], "algorithms": ["td3"],
                             "seeds": [0, 1], "frames": 300}))  # fmt: skip
    study.main(["run", "--config", str(a), str(b), "--results", str(tmp_path / "results"),
                "--out", str(tmp_path / "runs")])  # fmt: skip
    assert ["/".join(c.run_dir.parts[-4:]) for c in seen] == [
        "a/Hopper-v5/ddpg/seed0",
        "b/Walker2d-v5/td3/seed0",
        "b/Walker2d-v5/td3/seed1",
    ]
    out = capsys.readouterr().out
    assert "a: 1 cells to go" in out and "b: 2 cells to go" in out


def test_report_of_value_error_contrasts_and_diagnostics_by_hand(tmp_path):
    """Two tasks paired in ``contrasts``, value-error metrics and RAVE's diagnostics; every
    number below is worked by hand (t(0.975, 1) = 12.706, two seeds)."""
    results, figures = tmp_path / "results", tmp_path / "figures"

    def two(v100, v200):  # per-seed values at 100 and 200 frames -> each seed's rows
        return [[(100, a), (200, b)] for a, b in zip(v100, v200, strict=True)]

    cells = {
        ("A", "rave"): dict(ret=two([10, 30], [20, 40]), fall=two([1, 1], [0.5, 0.5]),
                            bias=two([-10, -20], [-4, -6])),
        ("B", "rave"): dict(ret=two([0, 10], [10, 20]), fall=two([1, 1], [1, 0.8]),
                            bias=two([-30, -40], [-14, -16])),
        ("A", "ddpg"): dict(ret=two([0, 0], [0, 0]), fall=two([1, 1], [1, 1]),
                            bias=two([5, 15], [0, 10])),
    }  # fmt: skip
    diag = {  # after 150 frames (the last quarter) only the 200-frame values count
        "train/horizon_weight_h0": two([0, 0], [0.7, 0.5]),
        **{f"train/horizon_weight_h{h}": two([0, 0], [0.1, 1 / 6]) for h in (1, 2, 3)},
        "train/alpha": two([0, 0], [1.0, 1.2]),  # its earlier name: the report reads both
        "train/candidate_variance_h0": two([0, 0], [1, 2]),
        **{f"train/candidate_variance_h{h}": two([0, 0], [2, 3]) for h in (1, 2)},
        "train/candidate_variance_h3": two([0, 0], [4, 8]),
        "train/wm_transition_mse": two([0, 0], [0.01, 0.03]),
    }
    for (task, algorithm), c in cells.items():
        for seed in (0, 1):
            metrics = {"eval/return": c["ret"][seed], "eval/falling_rate": c["fall"][seed],
                       "eval/q_bias": c["bias"][seed],
                       "eval/q_rmse": [(f, abs(v)) for f, v in c["bias"][seed]],
                       "eval/q_corr": two([0.5, 0.7], [0.9, 0.9])[seed]}  # fmt: skip
            if algorithm == "rave":
                metrics.update({k: v[seed] for k, v in diag.items()})
            write_cell(results, algorithm, seed, metrics, task=task)
    config = write_study(
        tmp_path,
        tasks=[{"label": "A", "env": "Hopper-v5"},
               {"label": "B", "env": "Hopper-v5", "overrides": ["env.action_noise=0.3"]}],
        contrasts=[["A", "B"]],
    )  # fmt: skip
    study.main(["report", "--config", str(config), "--results", str(results),
                "--figures", str(figures)])  # fmt: skip
    table = (figures / "tiny.md").read_text()
    # q_bias at 100: mean -15, s = 7.071: 12.706 * 7.071 / 1.414 = 63.5; at 200: -5 ± 12.7;
    # q_rmse the same magnitudes; q_corr 0.6 ± 12.706 * 0.1414 / 1.414 = 1.27
    assert (
        "| A | rave | 2 | -15 ± 64 | -5 ± 13 | 15 ± 64 | 5 ± 13 | 0.60 ± 1.27 | 0.90 ± 0.00 |"
        in table
    )
    # B's rave minus A's: return -15 (variances 50 and 200: se 11.18, x 12.706 = 142);
    # falling rate 0.9 - 0.5 (se sqrt(0.02 / 2) = 0.1: 1.27); q_bias -35 + 15 = -20
    # (se sqrt(50 / 2 + 50 / 2) = 7.07: 89.8) and -15 + 5 = -10 (se sqrt(2): 18.0)
    assert ("| A | B | rave | -15 ± 142 | -15 ± 142 | +0.00 ± 0.00 | +0.40 ± 1.27 | "
            "-20 ± 90 | -10 ± 18 |") in table  # fmt: skip
    assert "| A | B | ddpg | n/a | n/a | n/a | n/a | n/a | n/a |" in table  # B has no ddpg
    # rave - ddpg on A: falling 0.5 - 1; q_bias -15 - 10 (se 7.07: 90) and -5 - 5
    # (se sqrt(2 / 2 + 50 / 2) = 5.10: 64.8)
    assert "| A | rave - ddpg | +0.00 ± 0.00 | -0.50 ± 0.00 | -25 ± 90 | -10 ± 65 |" in table
    # w_0 0.6 ± 1.27; w_1..3 (0.1 + 1/6) / 2 = 0.133, s = 0.0471: 0.42; alpha 1.1 ± 1.27;
    # V_3 / V_0 = 4 in both seeds; MSE 0.02, s = 0.01414: 0.127
    assert ("| A | rave | 2 | 0.60 ± 1.27 | 0.13 ± 0.42 | 0.13 ± 0.42 | 0.13 ± 0.42 | "
            "1.10 ± 1.27 | 4.0 ± 0.0 | 0.020 ± 0.127 |") in table  # fmt: skip
    assert (figures / "tiny_A_q_bias.png").stat().st_size > 10_000
    # a contrast must name two of the tasks
    with pytest.raises(ValueError, match="contrast"):
        study.load_study(write_study(tmp_path, contrasts=[["Hopper-v5", "C"]]))
    # seeds and the budget are checked before any cell starts
    for bad in ([], [0, 0], [0, -1], [0, 1.5]):
        with pytest.raises(ValueError, match="seeds must be distinct integers >= 0"):
            study.load_study(write_study(tmp_path, seeds=bad))
    for bad in (0, -100, 2.5):
        with pytest.raises(ValueError, match="frames must be an integer >= 1"):
            study.load_study(write_study(tmp_path, frames=bad))


def test_a_bad_study_file_is_one_message_naming_every_problem(tmp_path, capsys):
    """It was a traceback at the first problem; an empty task list ran nothing, and an
    unknown algorithm or a misspelt key was found only when a cell failed."""
    config = write_study(
        tmp_path, tasks=[], algorithms=["ddpg", "dqn"], seeds=[0, 0], frames=0, overide=["x=1"]
    )
    with pytest.raises(SystemExit) as stop:
        study.main(["run", "--config", str(config), "--out", str(tmp_path / "out")])
    message = str(stop.value)
    assert "unknown key 'overide'" in message
    config = write_study(tmp_path, tasks=[], algorithms=["ddpg", "dqn"], seeds=[0, 0], frames=0)
    with pytest.raises(SystemExit) as stop:
        study.main(["report", "--config", str(config), "--results", str(tmp_path)])
    message = str(stop.value)
    assert message.startswith("4 problems in the config:")
    for problem in ("tasks is empty", "among ['ddpg'", "got ['ddpg', 'dqn']",
                    "seeds must be distinct integers >= 0, got [0, 0]",
                    "frames must be an integer >= 1, got 0"):  # fmt: skip
        assert problem in message
    with pytest.raises(ConfigError, match="task 'A' has an unknown key 'overides'"):
        study.load_study(write_study(tmp_path, tasks=[{"label": "A", "env": "Hopper-v5",
                                                        "overides": ["x=1"]}]))  # fmt: skip
    # a cell's own config problem (an override the recipe has no key for) is one message too
    config = write_study(tmp_path, overrides=["eval.intervall=5"])
    with pytest.raises(SystemExit, match="eval.intervall"):
        study.main(["run", "--config", str(config), "--out", str(tmp_path / "out"),
                    "--results", str(tmp_path / "results")])  # fmt: skip
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.csv"))


def test_a_report_without_cells_or_a_bad_command_line_changes_nothing(tmp_path):
    """A results directory with none of the study's cells (a typo in --results) is an
    error before anything is written: the committed tables are not replaced by n/a."""
    figures = tmp_path / "figures"
    figures.mkdir()
    (figures / "tiny.md").write_text("the committed table")
    config = write_study(tmp_path)
    for results in (tmp_path / "missing", tmp_path):
        with pytest.raises(SystemExit, match="tiny: no finished cell under --results"):
            study.main(["report", "--config", str(config), "--results", str(results),
                        "--figures", str(figures)])  # fmt: skip
    assert [p.name for p in figures.iterdir()] == ["tiny.md"]
    assert (figures / "tiny.md").read_text() == "the committed table"
    for argv in (["report", "--config", str(tmp_path / "nope.yaml")],
                 ["run", "--config", str(config), "--jobs", "0"]):  # fmt: skip
        with pytest.raises(SystemExit):
            study.main(argv)


def test_report_at_chooses_the_table_frames_and_must_be_evaluation_frames(tmp_path):
    results, figures = tmp_path / "results", tmp_path / "figures"
    for seed, (a, b, c) in enumerate([(1, 2, 3), (3, 4, 5)]):
        write_cell(results, "ddpg", seed, {"eval/return": [(50, a), (100, b), (200, c)],
                                           "eval/falling_rate": [(50, 1), (100, 1), (200, 0)]})  # fmt: skip
    config = write_study(tmp_path, algorithms=["ddpg"], report_at=[50, 200])
    study.main(["report", "--config", str(config), "--results", str(results),
                "--figures", str(figures)])  # fmt: skip
    table = (figures / "tiny.md").read_text()
    # at 50: [1, 3], mean 2, half 12.706 * 1.414 / 1.414; at 200: [3, 5]; after 150: [3, 5]
    assert "| return at 50 | return at 200 | mean return after 150 |" in table
    assert "| Hopper-v5 | ddpg | 2 | 2 ± 13 | 4 ± 13 | 4 ± 13 | 0.00 [0.00, 0.16] |" in table
    # 75 is not a frame the cells evaluated at: an error that says so, not a column of n/a
    config = write_study(tmp_path, algorithms=["ddpg"], report_at=[75, 200])
    with pytest.raises(ValueError, match=r"no evaluation at \[75\] frames.*report_at"):
        study.main(["report", "--config", str(config), "--results", str(results),
                    "--figures", str(figures)])  # fmt: skip
    for bad in ([200, 100], [0, 100], [100, 300], [100, 100]):
        with pytest.raises(ValueError, match="report_at must be increasing"):
            study.load_study(write_study(tmp_path, report_at=bad))


def test_a_task_can_read_another_studys_cells_up_to_its_own_budget(tmp_path):
    """``cells_from``: the twin's cells are the longer study's; this study never runs
    them, and reads them to its own 200 frames (the 300-frame evaluation and the costs
    of the longer run are not this study's)."""
    results, figures = tmp_path / "results", tmp_path / "figures"
    for seed, (a, b, c) in enumerate([(1, 2, 50), (3, 4, 70)]):
        cell = results / "long" / "Twin" / "ddpg" / f"seed{seed}"
        for metric, rows in {"eval/return": [(100, a), (200, b), (300, c)],
                             "eval/falling_rate": [(100, 1), (200, 1), (300, 0)],
                             "time/update_s": [(100, 60), (200, 60), (300, 60)]}.items():  # fmt: skip
            csv = cell / "ddpg" / "scalars" / f"{metric}.csv"
            csv.parent.mkdir(parents=True, exist_ok=True)
            csv.write_text("".join(f"{step},{value}\n" for step, value in rows))
        (cell / "cell.json").write_text(json.dumps({"config": {"eval": {"episodes": 10}}}))
    config = write_study(tmp_path, algorithms=["ddpg"],
                         tasks=[{"label": "Twin", "env": "Hopper-v5", "cells_from": "long"}])  # fmt: skip
    loaded = study.load_study(config)
    assert study.missing_cells(loaded, results, tmp_path / "runs") == {}  # nothing to run
    study.main(["report", "--config", str(config), "--results", str(results),
                "--figures", str(figures)])  # fmt: skip
    table = (figures / "tiny.md").read_text()
    # at 100: [1, 3]; at 200: [2, 4]; after 150 up to 200: [2, 4]; falls at 200: all
    assert "| Twin | ddpg | 2 | 2 ± 13 | 3 ± 13 | 3 ± 13 | 1.00 [0.84, 1.00] |" in table
    assert "What the finished cells cost" not in table  # the longer study paid for them


def test_an_algorithm_can_read_another_studys_cells(tmp_path):
    """``algorithm_cells_from``: ddpg's cells are the other study's on every task; this
    study runs only its td3 cells, keeps them under its own name, and reads ddpg's there."""
    results = tmp_path / "results"
    for seed, (a, b) in enumerate([(1, 2), (3, 4)]):
        write_cell(results, "ddpg", seed, {"eval/return": [(100, a), (200, b)],
                   "time/update_s": [(100, 60), (200, 60)]}, study="base")  # fmt: skip
    config = write_study(tmp_path, algorithms=["td3", "ddpg"],
                         algorithm_cells_from={"ddpg": "base"})  # fmt: skip
    loaded = study.load_study(config)
    cells = study.missing_cells(loaded, results, tmp_path / "runs")
    # td3's cells, kept under this study's name
    assert sorted(d.relative_to(results).as_posix() for d in cells.values()) == [
        "tiny/Hopper-v5/td3/seed0", "tiny/Hopper-v5/td3/seed1"]  # fmt: skip
    grouped = study.missing_cells(loaded, results, tmp_path / "runs", group=True)
    assert [c.overrides[0] for c in grouped] == ["algorithm=td3"]
    assert study.result_dir(results, loaded, "Hopper-v5", "ddpg", 1) == (
        results / "base" / "Hopper-v5" / "ddpg" / "seed1"
    )
    for bad in ({"ppo": "base"}, {"ddpg": "tiny"}):
        with pytest.raises(ValueError, match="algorithm_cells_from maps one of"):
            study.load_study(write_study(tmp_path, algorithms=["td3", "ddpg"],
                                         algorithm_cells_from=bad))  # fmt: skip


def test_an_algorithm_can_read_another_studys_cells_under_other_labels(tmp_path):
    """``algorithm_cells_from: {td3: {study, tasks}}``: td3's Hopper-v5 cells are the
    other study's ``Hopper-v5-order`` cells (its arm of another setting), the report reads
    their numbers, and the mapping names only this study's labels, with a known key."""
    results = tmp_path / "results"
    for seed, (a, b) in enumerate([(10, 20), (30, 40)]):
        write_cell(results, "td3", seed, {"eval/return": [(100, a), (200, b)],
                   "eval/falling_rate": [(100, 1), (200, 1)]},
                   task="Hopper-v5-order", study="arms")  # fmt: skip
    mapped = {"td3": {"study": "arms", "tasks": {"Hopper-v5": "Hopper-v5-order"}}}
    config = write_study(tmp_path, algorithms=["td3"], algorithm_cells_from=mapped)
    loaded = study.load_study(config)
    assert study.missing_cells(loaded, results, tmp_path / "runs") == {}  # nothing to run
    assert study.result_dir(results, loaded, "Hopper-v5", "td3", 1) == (
        results / "arms" / "Hopper-v5-order" / "td3" / "seed1"
    )
    figures = tmp_path / "figures"
    study.main(["report", "--config", str(config), "--results", str(results),
                "--figures", str(figures)])  # fmt: skip
    # at 100: [10, 30]; at 200: [20, 40]
    assert "| Hopper-v5 | td3 | 2 | 20 ± 127 | 30 ± 127 |" in (figures / "tiny.md").read_text()
    for bad, match in (
        ({"td3": {"study": "arms", "tasks": {"Walker2d-v5": "x"}}}, "map some of the task labels"),
        ({"td3": {"study": "arms", "task": {"Hopper-v5": "x"}}}, "algorithm_cells_from maps one"),
        ({"td3": {"tasks": {"Hopper-v5": "x"}}}, "algorithm_cells_from maps one"),
    ):
        with pytest.raises(ValueError, match=match):
            study.load_study(write_study(tmp_path, algorithms=["td3"], algorithm_cells_from=bad))


@pytest.mark.parametrize(
    "name", sorted(p.stem for p in (Path(study.__file__).parent / "study").glob("*.yaml"))
)
def test_every_committed_study_makes_valid_cells(name, tmp_path):
    from test_recipe import make_cfg

    from torchrl_rave.recipe.config import check_config

    loaded = study.load_study(Path(study.__file__).parent / "study" / f"{name}.yaml")
    cells = study.missing_cells(loaded, tmp_path / "results", tmp_path / "runs")
    own = [
        (t.label, a)
        for t in study.tasks(loaded)
        for a in loaded.algorithms
        if not study.cells_elsewhere(loaded, t.label, a)
    ]  # a twin's cells run elsewhere
    expected = len(own) * len(loaded.seeds)
    assert len(cells) == expected
    for cell in cells:
        cfg = make_cfg(*cell.overrides, f"collector.total_frames={cell.frames}")
        check_config(cfg)
        assert cfg.collector.total_frames == loaded.frames


@pytest.mark.parametrize(
    "name", sorted(p.stem for p in (Path(study.__file__).parent / "study").glob("*.yaml"))
)
def test_committed_results_tables_are_what_the_report_writes_today(name, tmp_path, monkeypatch):
    """Each study's committed tables (docs/figures/<study>.md, which its results page
    includes) are exactly what ``study.py report`` writes today from the committed cells
    under results/: a change to the report, to its statistics or to a cell that moves a
    published number fails here until the pages are regenerated. The curves are left out
    (drawing every study's takes minutes); the tables read every cell they plot. A study
    still under way is left out too: its runner commits each cell as it finishes, before
    the page is rebuilt from it."""
    import study_report

    recipes = Path(study.__file__).parent
    loaded = study.load_study(recipes / "study" / f"{name}.yaml")
    if missing := study.missing_cells(loaded, recipes.parent / "results", tmp_path / "runs"):
        pytest.skip(f"{name} is under way: {len(missing)} cells to run")
    monkeypatch.setattr(study_report, "study_figures", lambda *args, **kwargs: None)
    study.main(["report", "--config", str(recipes / "study" / f"{name}.yaml"),
                "--figures", str(tmp_path)])  # fmt: skip
    committed = recipes.parent / "docs" / "figures" / f"{name}.md"
    assert (tmp_path / f"{name}.md").read_text() == committed.read_text(), (
        f"docs/figures/{name}.md is not what the report writes from results/ today; run "
        f"python recipes/study.py report --config recipes/study/{name}.yaml"
    )


def test_group_runs_a_task_and_algorithms_seeds_as_one_cell_committed_per_seed(tmp_path):
    """``run --group``: DDPG's two seeds train in one process (seeds=[0,1]) and still give
    one result directory per seed, each cell.json naming its own seed and the group; run
    again, nothing is left to do."""
    config = write_study(tmp_path, algorithms=["ddpg"], seeds=[0, 1], frames=400,
                         overrides=[o for o in TINY if "total_frames" not in o])  # fmt: skip
    args = ["run", "--config", str(config), "--results", str(tmp_path / "results"),
            "--out", str(tmp_path / "runs"), "--jobs", "1", "--group"]  # fmt: skip
    study.main(args)
    for seed in (0, 1):
        cell = tmp_path / "results" / "tiny" / "Hopper-v5" / "ddpg" / f"seed{seed}"
        info = json.loads((cell / "cell.json").read_text())
        assert info["group"] == {"seeds": [0, 1]}
        assert info["config"]["env"]["seed"] == seed and info["frames"] == 400
        assert [s["from_frame"] for s in info["starts"]] == [0]
        assert read_scalar(cell, "eval/return")[0].tolist() == [200, 400]
        assert not list(cell.rglob("checkpoint*"))
    assert (tmp_path / "runs" / "tiny" / "Hopper-v5" / "ddpg" / "group0-1" / "group.json").exists()
    study.main(args)


def test_group_leaves_what_a_group_cannot_train_as_single_cells(tmp_path, monkeypatch):
    seen = []
    monkeypatch.setattr(study, "launch_grid", lambda script, todo, jobs, **kw: seen.extend(todo))
    config = write_study(tmp_path, algorithms=["rave", "ppo"], seeds=[0, 1, 2], frames=300)
    done = tmp_path / "results" / "tiny" / "Hopper-v5" / "rave" / "seed1"
    done.mkdir(parents=True)
    (done / "cell.json").write_text("{}")
    study.main(["run", "--config", str(config), "--results", str(tmp_path / "results"),
                "--out", str(tmp_path / "runs"), "--group"])  # fmt: skip
    assert [("/".join(c.run_dir.parts[-2:]), c.seeds) for c in seen] == [
        ("rave/group0-2", (0, 2)),  # the missing seeds only
        ("ppo/seed0", ()), ("ppo/seed1", ()), ("ppo/seed2", ()),
    ]  # fmt: skip
    assert "seeds=[0,2]" in seen[0].overrides


def test_compare_finds_where_two_studies_cells_part(tmp_path, capsys):
    """``study.py compare``: per algorithm and seed both studies have, the first evaluation
    at which the metric differs, with each cell's machine and starts from its cell.json."""
    results = tmp_path / "results"

    def cell(study_name, task, algorithm, seed, rows, meta=None):
        run = results / study_name / task / algorithm / f"seed{seed}"
        csv = run / algorithm / "scalars" / "eval" / "return.csv"
        csv.parent.mkdir(parents=True)
        csv.write_text("".join(f"{step},{value}\n" for step, value in rows))
        (run / "cell.json").write_text(json.dumps({"commit": "0123456789abcdef", **(meta or {})}))

    mine = write_study(tmp_path, name="mine", seeds=[0, 1, 2],
                       tasks=[{"label": "T0", "env": "Hopper-v5",
                               "overrides": ["env.action_noise=0"]}])  # fmt: skip
    other = tmp_path / "other.yaml"
    other.write_text(json.dumps({"name": "other", "tasks": ["Hopper-v5"], "frames": 200,
                                 "algorithms": ["rave", "ddpg", "td3"], "seeds": [0, 1]}))  # fmt: skip
    machine = {"cpu": "AMD EPYC", "vector": "avx2"}
    starts = [{"from_frame": 0}, {"from_frame": 100}]
    cell("mine", "T0", "rave", 0, [(100, 1.5), (200, 2.25)], {"machine": machine, "starts": starts})
    losses = results / "mine" / "T0" / "rave" / "seed0" / "rave" / "scalars" / "train"
    losses.mkdir(parents=True)  # a resume from 100 frames: 150 and 200 logged again
    (losses / "loss_critic.csv").write_text("50,1.0\n100,2.0\n150,3.0\n200,4.0\n150,3.0\n200,4.5\n")
    cell("other", "Hopper-v5", "rave", 0, [(100, 1.5), (200, 2.25)])
    cell("mine", "T0", "ddpg", 0, [(100, 1.5), (200, 3.0)])
    cell("other", "Hopper-v5", "ddpg", 0, [(100, 1.5), (200, 3.5)])
    cell("mine", "T0", "rave", 1, [(100, 1.0), (200, 2.0)])
    cell("other", "Hopper-v5", "rave", 1, [(100, 2.0), (200, 2.0)])
    cell("mine", "T0", "ddpg", 1, [(100, 1.0)])  # no twin in the other study
    cell("mine", "T0", "rave", 2, [(100, 1.0)])  # a seed the other study lacks
    argv = ["compare", "--results", str(results), "--config", str(mine), "--task", "T0",
            "--against", str(other), "--against-task", "Hopper-v5"]  # fmt: skip
    text = study.main(argv)
    rows = {
        tuple(line.split(" | ")[:2]): line for line in text.splitlines() if line.startswith("| ")
    }
    assert rows[("| rave", "0")] == (
        "| rave | 0 | 2 | every evaluation |  | 0123456; AMD EPYC (avx2); 0, then 100; "
        "from 150 (other values) | 0123456; not recorded; not recorded; none |"
    )
    assert "| 100 frames | 200 frames: 3.00 vs 3.50 |" in rows[("| ddpg", "0")]
    assert "| none | 100 frames: 1.00 vs 2.00 |" in rows[("| rave", "1")]
    assert ("| ddpg", "1") not in rows and ("| rave", "2") not in rows
    assert "Not compared (a cell not finished in one of them): ddpg seed 1." in text

    nan = float("nan")
    steps = np.array([1, 2, 3])
    same_nan = study_compare.first_difference(
        (steps, np.array([nan, 1.0, 2.0])), (steps, np.array([nan, 1.0, 2.5]))
    )
    assert same_nan == (3, 2, (3, 2.0, 2.5))  # NaN rows equal as NaN, as a rerun logs them
    with pytest.raises(SystemExit, match="'T9' is not a task of"):
        study.main(argv[:5] + ["--task", "T9"] + argv[7:])


def test_relogged_finds_a_second_start_in_the_losses(tmp_path):
    scalars = tmp_path / "run" / "scalars"
    (scalars / "train").mkdir(parents=True)
    (scalars / "time").mkdir()

    def write(name, rows):
        (scalars / f"{name}.csv").write_text("".join(f"{s},{v}\n" for s, v in rows))

    write("train/loss_critic", [(10, 1.0), (20, 2.0), (30, 3.0)])
    # several episodes can end at one step, and timings differ between any two starts
    write("train/episode_reward", [(10, 5.0), (10, 6.0)])
    write("time/fps", [(10, 100.0), (20, 90.0), (10, 80.0)])
    assert relogged(tmp_path) == (None, False)
    write(
        "train/loss_actor",
        [(10, 1.0), (20, float("nan")), (30, 3.0), (20, float("nan")), (30, 3.0)],
    )
    assert relogged(tmp_path) == (20, False)  # a restart that repeated the first start
    write("train/loss_critic", [(10, 1.0), (20, 2.0), (30, 3.0), (40, 4.0), (30, 3.5)])
    assert relogged(tmp_path) == (20, True)  # the first step twice; a value that changed
    assert relogged(tmp_path, "train/loss_critic") == (30, True)


def test_calibration_sets_ours_beside_the_reference_run_here_and_the_published(tmp_path):
    """Two SAC seeds of ours and of a reference implementation at 100k frames, by hand:
    ours 1700 and 1900 (mean 1800, std 141), the reference's 1500 and 2500 (mean 2000,
    std 707): ours meets TianShou's bar on Hopper (2613 - 991 = 1622) and is within the
    reference's spread (2000 - 707 = 1293). Training episodes are each seed's mean per
    10,000 frames, then the mean over seeds."""
    results, figures = tmp_path / "results", tmp_path / "figures"
    for seed, (ours, theirs) in enumerate([(1700, 1500), (1900, 2500)]):
        write_cell(results, "sac", seed, {
            "eval/return": [(50_000, 100), (100_000, ours)],
            "eval/falling_rate": [(50_000, 1.0), (100_000, 0.0)],
            "train/episode_reward": [(95_000, 10 * seed), (100_000, 30)],
        })  # fmt: skip
        ref = results / "tiny_reference" / "Hopper-v5" / "sac" / f"seed{seed}"
        for metric, rows in (("eval/return", [(50_000, 200), (100_000, theirs)]),
                             ("train/episode_reward", [(92_000, 100 + seed)])):  # fmt: skip
            csv = ref / "reference" / "scalars" / f"{metric}.csv"
            csv.parent.mkdir(parents=True, exist_ok=True)
            csv.write_text("".join(f"{s},{v}\n" for s, v in rows))
        (ref / "reference.json").write_text("{}")
    config = write_study(tmp_path, frames=100_000, algorithms=["sac"],
                         reference_runs="tiny_reference")  # fmt: skip
    study.main(["report", "--config", str(config), "--results", str(results),
                "--figures", str(figures)])  # fmt: skip
    table = (figures / "tiny.md").read_text()
    assert ("| Hopper-v5 | sac | 1800 ± 141 (2) | 2000 ± 707 (2) | 2613 ± 991 | meets the bar "
            "1622; within the reference's spread (>= 1293) |") in table  # fmt: skip
    # the last 10k bin: seed 0 (0 + 30) / 2 = 15, seed 1 (10 + 30) / 2 = 20 -> 17.5 -> 18
    assert "| Hopper-v5 | sac | ours | " + "n/a | " * 9 + "18 |" in table
    assert "| Hopper-v5 | sac | reference | " + "n/a | " * 9 + "100 |" in table
    assert (figures / "tiny_Hopper-v5_calibration.png").is_file()
    # without the reference runs, half the bar stays unchecked, and the verdict says so
    shutil.rmtree(results / "tiny_reference")
    study.main(["report", "--config", str(config), "--results", str(results),
                "--figures", str(figures)])  # fmt: skip
    assert ("| Hopper-v5 | sac | 1800 ± 141 (2) | n/a | 2613 ± 991 | meets the bar 1622; "
            "reference not run yet |") in (figures / "tiny.md").read_text()  # fmt: skip
