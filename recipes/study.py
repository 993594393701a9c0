"""A multi-session study: run its missing cells, keep their metrics, and report.

python recipes/study.py run --jobs 2 --commit      # the cells still missing, two at a time
python recipes/study.py run --config recipes/study/a.yaml recipes/study/b.yaml  # a's, then b's
python recipes/study.py report                     # tables and figures from results/ only
python recipes/study.py compare --config a.yaml --task T --against b.yaml --against-task U
                                                   # the same cells of two studies, the same runs?

To keep editing the project while cells run, run them from a frozen checkout of one commit
and point ``--results`` at the working repository: ``git worktree add ../study HEAD``, then
``PYTHONPATH=../study python ../study/recipes/study.py run --commit --results results``.

A study (``recipes/study/<name>.yaml``) is a grid of tasks x algorithms x seeds of ordinary
``rave_mujoco.py`` runs at one frame budget. Runs live under ``--out`` (not kept); as each
cell finishes, its metric CSVs are copied to ``results/<name>/<task>/<algorithm>/seed<k>/``
with ``cell.json`` (the commit and the full config it ran with; ``starts``, the commit and
first frame and machine of each start, where a cell resumed in a later session; ``train_s``, the cell's
own collection, update and evaluation seconds; ``runner_s``, the runner's age when the cell
ended; ``machine``, the CPU and torch of its last start; ``group``, the seeds of a seed group it
ran in) and, with
``--commit``, committed at once. A cell with a ``cell.json`` is done and never rerun; an
interrupted one resumes from its last checkpoint when its run directory survived.
Checkpoints and buffers are never copied.
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import subprocess
import time
from pathlib import Path

import torch
from compare import cell
from study_compare import compare
from study_report import report

from torchrl_rave.recipe.checkpoint import RunCheckpoint
from torchrl_rave.recipe.config import ConfigError
from torchrl_rave.recipe.group import GROUP_ALGORITHMS
from torchrl_rave.recipe.runs import Cell, GridStopped, check_cells, launch_grid, train_seconds
from torchrl_rave.recipe.studies import cells_elsewhere, load_study, result_dir, tasks

ROOT = Path(__file__).resolve().parents[1]
RECIPE = Path(__file__).resolve().parent / "rave_mujoco.py"
DEFAULT = Path(__file__).resolve().parent / "study" / "mujoco100k.yaml"


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


def machine() -> dict:
    """What ran the cell, as far as it changes float rounding: the CPU model and its widest
    vector extension (BLAS picks its kernels by them), the platform and torch's version."""
    cpu, flags = platform.processor(), set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
            elif line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                break
    except OSError:
        pass
    vector = next((f for f in ("avx512f", "avx2", "avx", "sse4_2") if f in flags), None)
    return {"cpu": cpu, "vector": vector, "platform": platform.platform(),
            "torch": torch.__version__}  # fmt: skip


def export(run: Cell, dest: Path, started: float, commit: bool, group: Cell | None = None) -> None:
    """Copies a finished cell's metric CSVs and writes its cell.json (the commit of the
    code that ran it: this script's checkout at the cell's last start, not at export,
    since a runner that commits its results into its own checkout moves ``HEAD`` while
    its cells run); commits them. A seed of a ``group`` says so in its cell.json
    (``group``: the seeds that ran together)."""
    for csv in run.run_dir.glob("*/scalars/**/*.csv"):
        target = dest / csv.relative_to(run.run_dir)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(csv, target)
    starts = (group or run).starts()
    last = starts[-1] if starts else {}
    info = {
        "commit": last.get("commit") or git(ROOT, "rev-parse", "HEAD"),
        "frames": run.frames,
        "overrides": list(run.overrides),
        "config": RunCheckpoint(run.run_dir).config(),
        "starts": starts,
        "train_s": train_seconds(run.run_dir),
        "runner_s": round(time.time() - started),
        "finished": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
    }
    info["machine"] = last.get("machine") or machine()
    if group is not None:
        info["group"] = {"seeds": list(group.seeds)}
    (dest / "cell.json").write_text(json.dumps(info, indent=1) + "\n")
    if commit:
        commit_cell(dest)


def interrupted(c: Cell) -> bool:
    return c.checkpoint_frame() is not None


def missing_cells(study, results: Path, out: Path, group: bool = False) -> dict[Cell, Path]:
    """The cells without a ``cell.json``, in the order they run: interrupted ones first
    (they resume), then seed by seed, every task's and algorithm's seed 0 before any
    seed 1, so that a study cut short by the budget still covers every task and
    algorithm. With ``group``, the missing seeds of each (task, algorithm) that a seed
    group can train run as one cell (``seeds=[...]``); its value is then the seeds'
    result directories by seed."""
    if group:
        return _missing_groups(study, results, out)
    cells = {}
    for seed in study.seeds:
        for task in tasks(study):
            for algorithm in study.algorithms:
                if cells_elsewhere(study, task.label, algorithm):
                    continue  # another study runs them
                dest = result_dir(results, study, task.label, algorithm, seed)
                if (dest / "cell.json").exists():
                    continue  # done in an earlier session
                extra = [*study.get("overrides", []), *task.overrides]
                run = cell(out / study.name, task.env, algorithm, seed, study.frames, extra,
                           label=task.label)  # fmt: skip
                cells[run] = dest
    order = sorted(cells, key=lambda c: not interrupted(c))  # stable: the order above otherwise
    return {c: cells[c] for c in order}


def _missing_groups(study, results: Path, out: Path) -> dict[Cell, dict[int, Path] | Path]:
    cells = {}
    for task in tasks(study):
        for algorithm in study.algorithms:
            if cells_elsewhere(study, task.label, algorithm):
                continue  # another study runs them
            dests = {
                seed: result_dir(results, study, task.label, algorithm, seed)
                for seed in study.seeds
            }
            missing = [s for s, d in dests.items() if not (d / "cell.json").exists()]
            if not missing:
                continue
            extra = [*study.get("overrides", []), *task.overrides]
            if algorithm not in GROUP_ALGORITHMS or len(missing) == 1:
                for seed in missing:
                    c = cell(out / study.name, task.env, algorithm, seed, study.frames, extra,
                             label=task.label)  # fmt: skip
                    cells[c] = dests[seed]
                continue
            overrides = (f"algorithm={algorithm}", f"env.name={task.env}",
                         f"logger.exp_name={algorithm}", *extra,
                         f"seeds=[{','.join(map(str, missing))}]")  # fmt: skip
            where = (
                out / study.name / task.label / algorithm / f"group{'-'.join(map(str, missing))}"
            )
            cells[Cell(where, study.frames, overrides, tuple(missing))] = {
                s: dests[s] for s in missing
            }
    order = sorted(cells, key=lambda c: not interrupted(c))
    return {c: cells[c] for c in order}


def run(args) -> None:
    """The missing cells of every ``--config`` study, one queue in their order, sharing
    ``--jobs`` slots; interrupted cells of any of them first."""
    cells = {}
    for config in args.config:
        study = load_study(config)
        todo = missing_cells(study, args.results, args.out, group=args.group)
        print(f"{study.name}: {len(todo)} cells to go, {args.jobs} at a time", flush=True)
        cells.update(todo)
    cells = {c: cells[c] for c in sorted(cells, key=lambda c: not interrupted(c))}
    started = time.time()

    def done(c: Cell, code: int) -> None:
        if code == 0 and c.finished() and c.seeds:  # one cell per seed of the group
            for seed, member in zip(c.seeds, c.members(), strict=True):
                export(member, cells[c][seed], started, args.commit, group=c)
                print(f"done: {cells[c][seed]} (in a group of {len(c.seeds)})", flush=True)
        elif code == 0 and c.finished():
            export(c, cells[c], started, args.commit)
            print(f"done: {cells[c]}", flush=True)
        else:
            print(f"exit code {code}: {c.run_dir / 'stdout.log'}", flush=True)

    # cells whose runs finished but were not exported (a stop between the two)
    for c in [c for c in cells if c.finished()]:
        done(c, 0)
    try:
        todo = [c for c in cells if not c.finished()]
        check_cells(todo, RECIPE.parent)  # every cell's config, before any starts
        # written down at each start: a cell resumed in another session may have run on
        # another machine, whose rounding changes its numbers from there on
        record = {"commit": git(ROOT, "rev-parse", "HEAD"), "machine": machine()}
        launch_grid(RECIPE, todo, args.jobs, on_done=done, record=record)
    except GridStopped as stop:
        raise SystemExit(str(stop)) from None


def main(argv: list[str] | None = None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("run", "report", "compare"):
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
    sub.choices["run"].add_argument(
        "--group",
        action="store_true",
        help="run the missing seeds of each (task, algorithm) as one seed group "
        f"({', '.join(GROUP_ALGORITHMS)}; seeds=[...]), still one committed cell per seed",
    )
    sub.choices["report"].add_argument("--figures", type=Path, default=ROOT / "docs" / "figures")
    cmp = sub.choices["compare"]
    cmp.add_argument("--config", type=Path, required=True, help="the study's YAML")
    cmp.add_argument("--task", required=True, help="a task label of --config")
    cmp.add_argument("--against", type=Path, required=True, help="the other study's YAML")
    cmp.add_argument("--against-task", required=True, help="a task label of --against")
    cmp.add_argument("--metric", default="eval/return", help="the metric compared")
    args = parser.parse_args(argv)
    configs = args.config if args.command == "run" else [args.config]
    if args.command == "compare":
        configs.append(args.against)
    for config in configs:
        if not config.is_file():
            parser.error(f"--config {config}: no such file")
    if args.command == "run" and args.jobs < 1:
        parser.error(f"--jobs must be at least 1, got {args.jobs}")
    try:
        return {"run": run, "report": report, "compare": compare}[args.command](args)
    except ConfigError as err:  # a study file's or a cell's config problems: the message
        raise SystemExit(str(err)) from None


if __name__ == "__main__":
    main()
