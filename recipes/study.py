"""A multi-session study: run its missing cells, keep their metrics, and report.

python recipes/study.py run --jobs 2 --commit      # the cells still missing, two at a time
python recipes/study.py run --config recipes/study/a.yaml recipes/study/b.yaml  # a's, then b's
python recipes/study.py report                     # tables and figures from results/ only

To keep editing the project while cells run, run them from a frozen checkout of one commit
and point ``--results`` at the working repository: ``git worktree add ../study HEAD``, then
``PYTHONPATH=../study python ../study/recipes/study.py run --commit --results results``.

A study (``recipes/study/<name>.yaml``) is a grid of tasks x algorithms x seeds of ordinary
``rave_mujoco.py`` runs at one frame budget. Runs live under ``--out`` (not kept); as each
cell finishes, its metric CSVs are copied to ``results/<name>/<task>/<algorithm>/seed<k>/``
with ``cell.json`` (the commit and the full config it ran with; ``starts``, the commit and
first frame of each start, where a cell resumed in a later session; ``train_s``, the cell's
own collection, update and evaluation seconds; ``runner_s``, the runner's age when the cell
ended) and, with
``--commit``, committed at once. A cell with a ``cell.json`` is done and never rerun; an
interrupted one resumes from its last checkpoint when its run directory survived.
Checkpoints and buffers are never copied.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
from compare import REFERENCE, cell
from plot_curves import seeds, study_figures

from torchrl_rave.training.checkpoint import RunCheckpoint
from torchrl_rave.training.runs import Cell, GridStopped, launch_grid, read_scalar, train_seconds
from torchrl_rave.training.stats import difference95, interval95, wilson_interval
from torchrl_rave.training.studies import load_study, result_dir, tasks

ROOT = Path(__file__).resolve().parents[1]
RECIPE = Path(__file__).resolve().parent / "rave_mujoco.py"
DEFAULT = Path(__file__).resolve().parent / "study" / "mujoco100k.yaml"
RAVE_DIAGNOSTICS = ["alpha", "wm_transition_mse", *(f"horizon_weight_h{h}" for h in range(4))]


def git(repo: Path, *args: str) -> str:
    return subprocess.run(
        ["git", "-C", str(repo), *args], capture_output=True, text=True, check=True
    ).stdout.strip()


def commit_cell(dest: Path) -> None:
    """Commits one cell's results, and only them, in the repository holding them; a busy
    index (another git command) is retried, and a failure leaves the files for later."""
    repo = Path(git(dest, "rev-parse", "--show-toplevel"))
    rel = str(dest.resolve().relative_to(repo))
    for attempt in range(5):
        try:
            git(repo, "add", "--", rel)
            git(repo, "commit", "-q", "-m", f"results: {rel.removeprefix('results/')}", "--", rel)
            return
        except subprocess.CalledProcessError as err:
            print(f"git commit of {rel} failed ({err.stderr.strip()}); retrying", flush=True)
            time.sleep(5 * (attempt + 1))
    print(f"{rel} is not committed: commit it by hand", flush=True)


def export(run: Cell, dest: Path, started: float, commit: bool) -> None:
    """Copies a finished cell's metric CSVs and writes its cell.json (the commit of the
    code that ran it, read from this script's checkout); commits them."""
    for csv in run.run_dir.glob("*/scalars/**/*.csv"):
        target = dest / csv.relative_to(run.run_dir)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(csv, target)
    info = {
        "commit": git(ROOT, "rev-parse", "HEAD"),
        "frames": run.frames,
        "overrides": list(run.overrides),
        "config": RunCheckpoint(run.run_dir).config(),
        "starts": run.starts(),
        "train_s": train_seconds(run.run_dir),
        "runner_s": round(time.time() - started),
        "finished": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }
    (dest / "cell.json").write_text(json.dumps(info, indent=1) + "\n")
    if commit:
        commit_cell(dest)


def interrupted(c: Cell) -> bool:
    return any((c.run_dir / "checkpoints").glob("checkpoint-*"))


def missing_cells(study, results: Path, out: Path) -> dict[Cell, Path]:
    """The cells without a ``cell.json``, in the order they run: interrupted ones first
    (they resume), then seed by seed, every task's and algorithm's seed 0 before any
    seed 1, so that a study cut short by the budget still covers every task and
    algorithm."""
    cells = {}
    for seed in study.seeds:
        for task in tasks(study):
            for algorithm in study.algorithms:
                dest = result_dir(results, study, task.label, algorithm, seed)
                if (dest / "cell.json").exists():
                    continue  # done in an earlier session
                extra = [*study.get("overrides", []), *task.overrides]
                run = cell(out / study.name, task.env, algorithm, seed, study.frames, extra,
                           label=task.label)  # fmt: skip
                cells[run] = dest
    order = sorted(cells, key=lambda c: not interrupted(c))  # stable: the order above otherwise
    return {c: cells[c] for c in order}


def run(args) -> None:
    """The missing cells of every ``--config`` study, one queue in their order, sharing
    ``--jobs`` slots; interrupted cells of any of them first."""
    cells = {}
    for config in args.config:
        study = load_study(config)
        todo = missing_cells(study, args.results, args.out)
        print(f"{study.name}: {len(todo)} cells to go, {args.jobs} at a time", flush=True)
        cells.update(todo)
    cells = {c: cells[c] for c in sorted(cells, key=lambda c: not interrupted(c))}
    started = time.time()

    def done(c: Cell, code: int) -> None:
        if code == 0 and c.finished():
            export(c, cells[c], started, args.commit)
            print(f"done: {cells[c]}", flush=True)
        else:
            print(f"exit code {code}: {c.run_dir / 'stdout.log'}", flush=True)

    # cells whose runs finished but were not exported (a stop between the two)
    for c in [c for c in cells if c.finished()]:
        done(c, 0)
    try:
        todo = [c for c in cells if not c.finished()]
        record = {"commit": git(ROOT, "rev-parse", "HEAD")}  # written down at each start
        launch_grid(RECIPE, todo, args.jobs, on_done=done, record=record)
    except GridStopped as stop:
        raise SystemExit(str(stop)) from None


def fmt_interval(mean: float, half: float, sign: str = "") -> str:
    """``mean ± half``, or ``mean (1 seed)`` where one seed leaves no interval (NaN)."""
    return f"{mean:{sign}.0f}" + (" (1 seed)" if np.isnan(half) else f" ± {half:.0f}")


def group(study, results: Path, task: str, algorithm: str) -> list[Path]:
    dirs = [result_dir(results, study, task, algorithm, s) for s in study.seeds]
    return [d for d in dirs if (d / "cell.json").exists()]


def eval_episodes(run: Path) -> int:
    """Episodes per evaluation of a finished cell, from the config in its cell.json."""
    return int(json.loads((run / "cell.json").read_text())["config"]["eval"]["episodes"])


def series(runs: list[Path], metric: str) -> tuple[np.ndarray, np.ndarray]:
    data = [read_scalar(r, metric) for r in runs]
    common = sorted(set.intersection(*(set(s.tolist()) for s, _ in data)))
    return np.array(common), np.stack([v[np.searchsorted(s, common)] for s, v in data])


def report(args) -> str:
    study = load_study(args.config)
    out = args.figures
    out.mkdir(parents=True, exist_ok=True)
    at = [study.frames // 2, study.frames]
    # the published reference is at 100k frames: beside a shorter study it would mislead
    with_ref = study.frames >= 100_000
    # one evaluation is 10 episodes of one policy snapshot; the evaluations of the last
    # quarter of the budget, averaged per seed, say more about where a run has got to
    tail_from = study.frames * 3 // 4
    lines = [
        f"Evaluation return ({study.name}): mean ± 95 % t-interval half-width over the seeds "
        "that finished; the last-quarter column first averages each seed's evaluations after "
        f"{tail_from:,} frames; falling rate pooled over seeds at the last evaluation, "
        "with its 95 % Wilson interval.",
        "",
        "| task | algorithm | seeds | "
        + " | ".join(f"return at {f:,}" for f in at)
        + f" | mean return after {tail_from:,} | falling rate |"
        + (" reference at 100k (tianshou, gym v3; not ours) |" if with_ref else ""),
        "| --- " * (5 + len(at) + with_ref) + "|",
    ]
    cost, versus = [], []  # the cells' own minutes; RAVE minus each other algorithm
    for entry in tasks(study):
        task = entry.label
        curves, diag, falling, at_frames = {}, {}, {}, {}
        for algorithm in study.algorithms:
            runs = group(study, args.results, task, algorithm)
            minutes = [m / 60 for m in map(train_seconds, runs) if m is not None]
            if minutes:
                cost.append(
                    f"| {task} | {algorithm} | {len(minutes)} | {min(minutes):.0f} | "
                    f"{max(minutes):.0f} | {sum(minutes) / 60:.1f} |"
                )
            ref = (
                REFERENCE.get(entry.env.split("-")[0], {}).get(algorithm, "")
                if entry.reference
                else ""
            )
            ref = (f" {ref.split(' / ')[0]} |" if ref else "  |") if with_ref else ""
            if not runs:
                lines.append(f"| {task} | {algorithm} | 0 |" + " n/a |" * (len(at) + 2) + ref)
                continue
            steps, values = series(runs, "eval/return")
            cells = []
            for frame in at:
                hit = np.flatnonzero(steps == frame)
                at_frames[algorithm, frame] = values[:, hit[0]] if hit.size else None
                cells.append(
                    "n/a" if not hit.size else fmt_interval(*interval95(values[:, hit[0]]))
                )
            last = steps > tail_from
            cells.append(
                fmt_interval(*interval95(values[:, last].mean(1))) if last.any() else "n/a"
            )
            fall_steps, falls = series(runs, "eval/falling_rate")
            falling[algorithm] = (fall_steps, falls.mean(0), falls.min(0), falls.max(0))
            episodes = [eval_episodes(r) for r in runs]
            fell = round(float(falls[:, -1] @ np.array(episodes)))
            lo, hi = wilson_interval(fell, sum(episodes))
            lines.append(
                f"| {task} | {algorithm} | {len(runs)} | "
                + " | ".join(cells)
                + f" | {fell / sum(episodes):.2f} [{lo:.2f}, {hi:.2f}] |{ref}"
            )
            lo, hi = values.min(0), values.max(0)
            curves[f"{algorithm} ({seeds(len(runs))})"] = (steps, values.mean(0), lo, hi)
            if algorithm == "rave":
                diag = {m: series(runs, f"train/{m}") for m in RAVE_DIAGNOSTICS}
        rave = [at_frames.get(("rave", f)) for f in at]
        for other in (a for a in study.algorithms if a != "rave"):
            theirs = [at_frames.get((other, f)) for f in at]
            if all(v is not None for v in rave + theirs):
                row = " | ".join(fmt_interval(*difference95(r, o), "+") for r, o in zip(rave, theirs, strict=True))  # fmt: skip
                versus.append(f"| {task} | rave - {other} | {row} |")
        study_figures(out / f"{study.name}_{task}", f"{task}, {study.name}", curves, diag, falling)
    if versus:
        lines += [
            "",
            "RAVE's mean minus each other algorithm's, with the 95 % interval of the "
            "difference (Welch's standard error, min(seeds) - 1 degrees of freedom); an "
            "interval that contains 0 does not separate the two.",
            "",
            "| task | difference | " + " | ".join(f"at {f:,}" for f in at) + " |",
            "| --- " * (2 + len(at)) + "|",
            *versus,
        ]
    if cost:
        lines += [
            "",
            "What the finished cells cost: their own collection, update and evaluation time "
            "(`time/*_s`, summed), in minutes per cell, and hours in all.",
            "",
            "| task | algorithm | cells | min | max | hours |",
            "| --- | --- | --- | --- | --- | --- |",
            *cost,
        ]
    text = "\n".join(lines)
    (out / f"{study.name}.md").write_text(text + "\n")
    print(text)
    return text


def main(argv: list[str] | None = None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("run", "report"):
        p = sub.add_parser(name)
        p.add_argument("--results", type=Path, default=ROOT / "results")
    sub.choices["run"].add_argument("--config", type=Path, nargs="+", default=[DEFAULT],
                                    help="the studies' YAML files, queued in this order")  # fmt: skip
    sub.choices["report"].add_argument(
        "--config", type=Path, default=DEFAULT, help="the study's YAML"
    )
    sub.choices["run"].add_argument("--jobs", type=int, default=2)
    sub.choices["run"].add_argument("--out", type=Path, default=ROOT / "outputs" / "study")
    sub.choices["run"].add_argument("--commit", action="store_true", help="git-commit each cell")
    sub.choices["report"].add_argument("--figures", type=Path, default=ROOT / "docs" / "figures")
    args = parser.parse_args(argv)
    return run(args) if args.command == "run" else report(args)


if __name__ == "__main__":
    main()
