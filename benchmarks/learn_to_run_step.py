"""Simulation cost of the OpenSim tasks (OpenSim 4.6) per 0.01 s step, by integrator accuracy.

    python benchmarks/learn_to_run_step.py                       # LearnToRun-v0: 5e-5 1e-3 5e-3
    python benchmarks/learn_to_run_step.py --accuracy 1e-3 --episodes 10
    python benchmarks/learn_to_run_step.py --env LearnToMove-v0 LearnToMove2D-v0

For each ``--accuracy`` it runs ``--episodes`` episodes (seeds 0, 1, ...) of two fixed
excitation policies on the raw gymnasium env, one process, one thread:

- ``random``: uniform excitations in [0, 1] (seeded), what a fresh learner sends;
- ``zero``: no excitation; the body folds and falls, the stiff foot contact at its worst.

It reports seconds per step over the whole episodes, the same over the first 50 steps of
each (standing, before the fall's contact), the episode lengths and returns. The returns
show how much the tolerance changes the dynamics; the cost shows what it buys. Episodes
end at a fall (pelvis below 0.65 m for ``LearnToRun-v0``, 0.6 m for ``LearnToMove-v0``
and its planar ``LearnToMove2D-v0``, at difficulty 2), which these policies reach in
1-2 s. The JSON (``learn_to_run_step.json``, or ``learn_to_move_step.json`` for the 2019
task) records the command and the commit.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
from cli_types import count
from provenance import provenance

ROOT = Path(__file__).resolve().parents[1]
# each env's keywords besides the accuracy: the 2019 task at round 1's hardest field
KWARGS = {
    "LearnToRun-v0": {},
    "LearnToMove-v0": {"difficulty": 2},
    "LearnToMove2D-v0": {"difficulty": 2},
}


def run_episode(env, policy: str, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    size = env.action_space.shape[0]
    times, total, terminated, truncated = [], 0.0, False, False
    while not (terminated or truncated):
        action = rng.uniform(0.0, 1.0, size) if policy == "random" else np.zeros(size)
        start = time.perf_counter()
        _, reward, terminated, truncated, _ = env.step(action)
        times.append(time.perf_counter() - start)
        total += reward
    return {"steps": len(times), "seconds": sum(times), "first50": sum(times[:50]), "return": total}


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--accuracy", nargs="+", type=float, default=[5e-5, 1e-3, 5e-3])
    parser.add_argument(
        "--policies", nargs="+", choices=["random", "zero"], default=["random", "zero"]
    )
    parser.add_argument("--episodes", type=count(), default=3)
    parser.add_argument("--env", nargs="+", choices=list(KWARGS), default=["LearnToRun-v0"])
    parser.add_argument("--json", help="default: benchmarks/learn_to_run_step.json, or "
                        "learn_to_move_step.json for the 2019 task")  # fmt: skip
    args = parser.parse_args(argv)
    import torch

    from torchrl_rave.envs import import_env_family

    torch.set_num_threads(1)
    rows = []
    for env_id in args.env:
        import_env_family(env_id)
        rows += measure(env_id, args)
    name = "learn_to_run_step" if args.env == ["LearnToRun-v0"] else "learn_to_move_step"
    out = Path(args.json or ROOT / "benchmarks" / f"{name}.json")
    out.write_text(
        json.dumps({**provenance("learn_to_run_step.py", argv), "rows": rows}, indent=1) + "\n"
    )
    return rows


def measure(env_id: str, args) -> list[dict]:
    rows = []
    for accuracy in args.accuracy:
        env = gym.make(env_id, integrator_accuracy=accuracy, **KWARGS[env_id])
        for policy in args.policies:
            episodes = [run_episode(env, policy, seed) for seed in range(args.episodes)]
            steps = sum(e["steps"] for e in episodes)
            row = {
                "env": env_id,
                "accuracy": accuracy,
                "policy": policy,
                "episodes": args.episodes,
                "ms_per_step": 1e3 * sum(e["seconds"] for e in episodes) / steps,
                "ms_per_step_first50": 1e3
                * sum(e["first50"] for e in episodes)
                / (50 * len(episodes)),
                "lengths": [e["steps"] for e in episodes],
                "returns": [round(e["return"], 3) for e in episodes],
            }
            rows.append(row)
            print(
                f"{env_id} accuracy {accuracy:g} {policy:6s}: {row['ms_per_step']:6.1f} ms/step "
                f"({row['ms_per_step_first50']:5.1f} over the first 50), lengths "
                f"{row['lengths']}, returns {row['returns']}",
                flush=True,
            )
        env.close()
    return rows


if __name__ == "__main__":
    main()
