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
import csv
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

RECIPE = Path(__file__).resolve().parent / "rave_mujoco.py"

# SPEC.md section 4: tianshou's MuJoCo benchmark (gym v3, 10 seeds, deterministic
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


def run_dir(out: Path, env: str, algorithm: str, seed: int) -> Path:
    return out / env / algorithm / f"seed{seed}"


def final_eval(path: Path, algorithm: str, frames: int) -> float | None:
    """The evaluation return logged at ``frames``, or ``None`` if the run has not got there."""
    scalars = path / algorithm / "scalars" / "eval" / "return.csv"
    if not scalars.exists():
        return None
    with open(scalars) as f:
        rows = [(int(s), float(v)) for s, v in csv.reader(f)]
    done = [v for s, v in rows if s == frames]
    return done[-1] if done else None


def launch(path: Path, env: str, algorithm: str, seed: int, frames: int, extra: list[str]) -> int:
    args = [
        f"algorithm={algorithm}",
        f"env.name={env}",
        f"env.seed={seed}",
        f"collector.total_frames={frames}",
        "logger.progress_bar=false",
        f"hydra.run.dir={path}",
        *extra,
    ]
    if (path / "checkpoints" / "latest").exists():
        args.append(f"resume={path}")
    path.mkdir(parents=True, exist_ok=True)
    # one thread per run: the grid runs --jobs trainings side by side
    environ = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with open(path / "stdout.log", "a") as log:
        return subprocess.call(
            [sys.executable, str(RECIPE), *args], stdout=log, stderr=subprocess.STDOUT, env=environ
        )


def table(out: Path, envs, algorithms, seeds, frames) -> str:
    lines = [
        f"| env | algorithm | eval return at {frames:,} frames (mean ± std over seeds) "
        "| seeds | reference at 100k / 300k / 1M (tianshou, gym v3; not our runs) |",
        "| --- | --- | --- | --- | --- |",
    ]
    for env in envs:
        for algorithm in algorithms:
            values = [final_eval(run_dir(out, env, algorithm, s), algorithm, frames) for s in seeds]
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

    todo = [
        (env, algorithm, seed)
        for env in args.envs
        for algorithm in args.algorithms
        for seed in args.seeds
        if final_eval(run_dir(args.out, env, algorithm, seed), algorithm, args.frames) is None
    ]
    if not args.table_only and todo:
        print(f"{len(todo)} runs to go, {args.jobs} at a time, logs in <run dir>/stdout.log")
        with ThreadPoolExecutor(args.jobs) as pool:
            codes = pool.map(
                lambda job: launch(run_dir(args.out, *job), *job, args.frames, extra), todo
            )
            for job, code in zip(todo, codes, strict=True):
                print(f"{job}: {'done' if code == 0 else f'exit code {code}'}")
    print(table(args.out, args.envs, args.algorithms, args.seeds, args.frames))


if __name__ == "__main__":
    main()
