"""Whole runs: frames per second and peak memory of seed groups against single runs on
this machine's cores, each layout timed end to end (collection, updates, evaluation).

    python benchmarks/seed_group_runs.py                     # Hopper-v5 RAVE, 4 seeds, about 12 min
    python benchmarks/seed_group_runs.py --frames 6000 --algorithm ddpg

The same four seeds of ``python recipes/rave_mujoco.py`` (``collector.total_frames=--frames``,
the recipe's defaults otherwise) run in five layouts, one after the other:

- *singles, two at a time*: four single runs, two processes side by side at one thread
  each, the way ``study.py run --jobs 2`` runs cells;
- *one group of four*: ``seeds=[0,1,2,3]`` in one process at two threads;
- *two groups of two*: ``seeds=[0,1]`` and ``seeds=[2,3]`` side by side at one thread each;
- *singles one after another*: the four single runs in turn, one process at one thread;
- *one group of four at one thread*: what a group gains on one core alone
  (``speedup_vs_serial``: the serial singles' time over the layout's).

Reported per layout: the wall-clock seconds until its last process ends, the frames per
second of all seeds together (4 x frames / seconds), and the peak resident memory of its
largest process (``wait4``'s ``ru_maxrss``) against a single run's, and each seed's last
evaluation return (every seed draws from its own random stream, so a seed's run is the same
in every layout up to float rounding). Results go to stdout and
``benchmarks/seed_group_runs.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cli_types import count
from provenance import provenance

from torchrl_rave.recipe.group import GROUP_ALGORITHMS
from torchrl_rave.recipe.runs import read_scalar

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "rave_mujoco.py"


def start(overrides: list[str], run_dir: Path, threads: int) -> subprocess.Popen:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    args = [*overrides, f"threads={threads}", "logger.progress_bar=false",
            f"hydra.run.dir={run_dir}"]  # fmt: skip
    return subprocess.Popen(
        [sys.executable, str(RECIPE), *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env=env,
    )


def wait_all(procs: list[subprocess.Popen]) -> list[int]:
    """Each process's peak resident memory in MiB; raises if one failed."""
    peaks = []
    for proc in procs:
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode != 0:
            raise RuntimeError(f"{proc.args} exited with {proc.returncode}")
        peaks.append(usage.ru_maxrss / 1024)  # KiB on Linux
    return peaks


def layout(name: str, batches: list[list[tuple[list[str], int, list[int]]]], tmp: Path) -> dict:
    """Runs ``batches`` one after the other, the processes of each side by side; each
    process is ``(overrides, threads, seeds)``, a group when ``seeds`` has several."""
    t = time.perf_counter()
    peaks, returns = [], {}
    for i, batch in enumerate(batches):
        dirs = [tmp / f"{name}-{i}-{j}" for j in range(len(batch))]
        procs = [start(o, d, threads) for d, (o, threads, _) in zip(dirs, batch, strict=True)]
        peaks += wait_all(procs)
        for d, (o, _, seeds) in zip(dirs, batch, strict=True):
            grouped = any(x.startswith("seeds=") for x in o)
            for seed in seeds:  # each seed's last evaluation
                _, values = read_scalar(d / f"seed{seed}" if grouped else d, "eval/return")
                returns[seed] = float(values[-1])
    return {
        "seconds": time.perf_counter() - t,
        "peak_rss_mib": max(peaks),
        "final_return": {str(s): returns[s] for s in sorted(returns)},
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--algorithm", default="rave", choices=GROUP_ALGORITHMS)
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--frames", type=count(), default=4000)
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "seed_group_runs.json")
    args = parser.parse_args(argv)
    base = [f"algorithm={args.algorithm}", f"env.name={args.env}",
            f"collector.total_frames={args.frames}", f"eval.interval={args.frames}"]  # fmt: skip

    def single(seed):
        return ([*base, f"env.seed={seed}"], 1, [seed])

    def group(seeds, threads):
        return ([*base, f"seeds=[{','.join(map(str, seeds))}]"], threads, seeds)

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        rows = {
            "singles, two at a time": layout(
                "singles", [[single(0), single(1)], [single(2), single(3)]], tmp
            ),
            "one group of four, 2 threads": layout("group4", [[group([0, 1, 2, 3], 2)]], tmp),
            "two groups of two, 1 thread each": layout(
                "group2", [[group([0, 1], 1), group([2, 3], 1)]], tmp
            ),
            # one core's layouts: the seed group's own gain, without a second process
            "singles one after another, 1 thread": layout(
                "serial", [[single(0)], [single(1)], [single(2)], [single(3)]], tmp
            ),
            "one group of four, 1 thread": layout("group4t1", [[group([0, 1, 2, 3], 1)]], tmp),
        }
    single_rss = rows["singles, two at a time"]["peak_rss_mib"]
    baseline = rows["singles, two at a time"]["seconds"]
    serial = rows["singles one after another, 1 thread"]["seconds"]
    for name, row in rows.items():
        row["fps"] = 4 * args.frames / row["seconds"]
        row["speedup"] = baseline / row["seconds"]
        row["speedup_vs_serial"] = serial / row["seconds"]
        row["peak_rss_vs_single"] = row["peak_rss_mib"] / single_rss
        print(f"{name:34s} {row['seconds']:7.1f} s  {row['fps']:6.1f} frames/s  "
              f"x{row['speedup']:.2f} (x{row['speedup_vs_serial']:.2f} of serial)  peak RSS {row['peak_rss_mib']:.0f} MiB "
              f"({row['peak_rss_vs_single']:.2f}x a single run's)  final eval/return "
              f"{[round(v, 1) for v in row['final_return'].values()]}", flush=True)  # fmt: skip
    result = {
        **provenance("seed_group_runs.py", argv),
        "algorithm": args.algorithm,
        "env": args.env,
        "frames_per_seed": args.frames,
        "layouts": rows,
    }
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
