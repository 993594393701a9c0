"""Run a grid of ``rave_mujoco.py`` trainings and print the results table.

python recipes/compare.py --envs Hopper-v5 HalfCheetah-v5 --algorithms rave steve ddpg \
    --seeds 0 1 --frames 20000 --jobs 2 --out outputs/compare

Each run lives in ``<out>/<env>/<algorithm>/seed<k>`` and is an ordinary recipe run (resume,
CSV metrics, checkpoints). Finished runs are skipped and interrupted ones resumed, so the
command can be repeated until the grid is complete. The table reports the final evaluation
return (mean ± std over seeds of each seed's mean over ``eval.episodes`` episodes) next to
reference numbers from other implementations, labelled as such. Extra ``key=value`` arguments
after ``--`` go to every run.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from torchrl_rave.recipe.runs import Cell, GridStopped, check_cells, launch_grid, value_logged_at

RECIPE = Path(__file__).resolve().parent / "rave_mujoco.py"

# tianshou's published MuJoCo benchmark (gym v3, 10 seeds, deterministic
# evaluation), mean return at 100k / 300k / 1M environment steps. Not our runs.
REFERENCE = {
    "Hopper": {
        "sac": "2613 / 3388 / 3532",
        "td3": "597 / 1583 / 3133",
        "ddpg": "904 / 1241 / 1604",
    },
    "HalfCheetah": {
        "sac": "6515 / 9059 / 12122",
        "td3": "5336 / 7546 / 10127",
        "ddpg": "6308 / 9137 / 11653",
    },
    "Walker2d": {
        "sac": "1305 / 3387 / 4961",
        "td3": "483 / 1663 / 3842",
        "ddpg": "113 / 175 / 916",
    },
}


def run_dir(out: Path, env: str, variant: str, seed: int) -> Path:
    return out / env / variant / f"seed{seed}"


def cell(
    out: Path, env: str, algorithm: str, seed: int, frames: int, extra=(), variant=None, label=None
):
    """The grid cell of one (env, algorithm, seed); ``variant`` names its directory and
    experiment when it is not the algorithm (the alpha ablation's constant-alpha runs),
    ``label`` the env's directory when it is not the env id (a study's task variants)."""
    variant = variant or algorithm
    overrides = (
        f"algorithm={algorithm}",
        f"env.name={env}",
        f"env.seed={seed}",
        f"logger.exp_name={variant}",
        *extra,
    )
    return Cell(run_dir(out, label or env, variant, seed), frames, overrides)


def run(cells: list[Cell], jobs: int) -> None:
    """Launches the unfinished cells; stops with the first failure's log named."""
    todo = [c for c in cells if not c.finished()]
    if not todo:
        return
    if jobs < 1:
        raise SystemExit(f"--jobs must be at least 1, got {jobs}")
    try:
        check_cells(todo, RECIPE.parent)  # every run's config, before any starts
    except ValueError as bad:
        raise SystemExit(str(bad)) from None
    print(f"{len(todo)} runs to go, {jobs} at a time, logs in <run dir>/stdout.log")

    def report(c: Cell, code: int) -> None:
        print(f"{c.run_dir}: {'done' if code == 0 else f'exit code {code}'}", flush=True)

    try:
        codes = launch_grid(RECIPE, todo, jobs, on_done=report)
    except GridStopped as stop:
        raise SystemExit(str(stop)) from None
    failed = [c for c, code in codes.items() if code != 0]
    if failed:
        raise SystemExit(f"{len(failed)} run(s) failed; see {failed[0].run_dir / 'stdout.log'}")


def table(out: Path, envs, algorithms, seeds, frames) -> str:
    lines = [
        f"| env | algorithm | eval return at {frames:,} frames (mean ± std over seeds) "
        "| seeds | reference at 100k / 300k / 1M (tianshou, gym v3; not our runs) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for env in envs:
        for algorithm in algorithms:
            values = [
                value_logged_at(run_dir(out, env, algorithm, s), "eval/return", frames)
                for s in seeds
            ]
            values = [v for v in values if v is not None]
            cell = f"{np.mean(values):.0f} ± {np.std(values):.0f}" if values else "n/a"
            ref = REFERENCE.get(env.split("-")[0], {}).get(algorithm, "")
            lines.append(f"| {env} | {algorithm} | {cell} | {len(values)} | {ref} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    argv = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--envs", nargs="+", default=["Hopper-v5", "HalfCheetah-v5"])
    parser.add_argument("--algorithms", nargs="+", default=["rave", "steve", "ddpg"])
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path("outputs/compare"))
    parser.add_argument("--table-only", action="store_true", help="print the table, run nothing")
    args = parser.parse_args(argv)

    cells = [
        cell(args.out, env, algorithm, seed, args.frames, extra)
        for env in args.envs
        for algorithm in args.algorithms
        for seed in args.seeds
    ]
    if not args.table_only:
        run(cells, args.jobs)
    print(table(args.out, args.envs, args.algorithms, args.seeds, args.frames))


if __name__ == "__main__":
    main()
