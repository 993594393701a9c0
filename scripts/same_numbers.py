"""A refactor changes no number: short fixed-seed runs of every algorithm, metrics compared.

python scripts/same_numbers.py --out before.json                       # at the old commit
python scripts/same_numbers.py --out after.json --compare before.json  # at the new one

Each algorithm trains for a few hundred updates on Hopper-v5 (seed 0, one thread, the
recipe's command line exactly as a user types it); every metric it logs except the
``time/*`` ones is kept, step by step. ``--compare`` lists every metric whose values differ
(or that one side lacks), and exits 1 if any does; ``--rename OLD=NEW`` compares a renamed
metric under its new name.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from torchrl_rave.recipe.config import ALGORITHMS

ROOT = Path(__file__).resolve().parents[1]
OVERRIDES = [
    "env.name=Hopper-v5",
    "env.seed=0",
    "collector.total_frames=1200",
    "collector.frames_per_batch=200",
    "collector.init_random_frames=200",
    "world_model.pretrain_frames=400",
    "world_model.pretrain_updates=10",
    "optim.utd_ratio=0.25",
    "ppo.rollout_frames=400",
    "ppo.epochs=2",
    "eval.interval=600",
    "eval.episodes=2",
    "checkpoint.interval=600",
    "logger.progress_bar=false",
]


def run(algorithm: str, run_dir: Path, extra: list[str]) -> dict[str, list]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    cmd = [sys.executable, str(ROOT / "recipes" / "rave_mujoco.py"), f"algorithm={algorithm}",
           *OVERRIDES, *extra, f"hydra.run.dir={run_dir}"]  # fmt: skip
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{algorithm} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    metrics = {}
    for path in sorted(run_dir.glob("*/scalars/**/*.csv")):
        name = str(path.relative_to(next(run_dir.glob("*/scalars")))).removesuffix(".csv")
        if not name.startswith("time/"):
            with open(path) as f:
                metrics[name] = [[int(s), float(v)] for s, v in csv.reader(f)]
    return metrics


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="JSON of every run's metrics")
    parser.add_argument("--compare", type=Path, help="an earlier --out to compare against")
    parser.add_argument("--algorithms", nargs="+", default=list(ALGORITHMS))
    parser.add_argument(
        "--rename",
        nargs="*",
        default=[],
        metavar="OLD=NEW",
        help="metrics renamed since --compare's run: compared under NEW",
    )
    parser.add_argument("extra", nargs="*", help="more recipe overrides for every run")
    args = parser.parse_args(argv)
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for algorithm in args.algorithms:
            results[algorithm] = run(algorithm, Path(tmp) / algorithm, args.extra)
            print(f"{algorithm}: {len(results[algorithm])} metrics", flush=True)
    args.out.write_text(json.dumps(results, indent=0) + "\n")
    if args.compare is None:
        return 0
    before = json.loads(args.compare.read_text())
    renames = dict(r.split("=", 1) for r in args.rename)
    before = {a: {renames.get(k, k): v for k, v in m.items()} for a, m in before.items()}
    differ = []
    for algorithm, metrics in results.items():
        old = before.get(algorithm, {})
        for name in sorted(set(metrics) | set(old)):
            if metrics.get(name) != old.get(name):
                differ.append(f"{algorithm} {name}")
    values = sum(len(rows) for m in results.values() for rows in m.values())
    print(f"{values} values of {sum(map(len, results.values()))} metrics compared")
    print("identical" if not differ else "differ:\n  " + "\n  ".join(differ))
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
