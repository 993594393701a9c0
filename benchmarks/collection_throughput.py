"""Collection throughput (frames/s) of the recipe's collector backends.

    python benchmarks/collection_throughput.py                    # Hopper-v5, 1 2 4 workers
    python benchmarks/collection_throughput.py --env InvertedPendulum-v5 --workers 1 2
    python benchmarks/collection_throughput.py --backends process     # without Ray
    python benchmarks/collection_throughput.py --record-cost          # the episode record
    python benchmarks/collection_throughput.py --vector-env 5         # one batched env of 5

It builds the recipe's env and exploration policy (an untrained RAVE actor with its
Gaussian noise) from ``recipes/config.yaml`` and times ``collector.backend=direct``, then
each of ``--backends`` (``process``, ``ray``) with each ``--workers`` count: frames/s over
``--batches`` batches of ``--frames-per-batch`` frames after one warm-up batch (worker
start-up is not counted), with a weight push after every batch as in training; the best
of ``--repeats`` rounds, since a shared 2-core machine's noise only ever slows a round. Ray runs
a fresh local instance per row, with as many CPUs as workers. No learning happens, so this
is the collector's ceiling.

The ``direct`` row's env keeps the episode in progress for the checkpoints, as a training
run's does (:class:`~torchrl_rave.envs.EpisodeReplay`). ``--record-cost`` times only the
direct backend, with and without that record, rounds interleaved, and writes
``episode_record_cost.json``.

``--vector-env S`` asks whether one batched env would step a seed group's S envs for less:
env steps per second (random actions from the spec, ``step_and_maybe_reset``, no policy)
of S TorchRL ``GymEnv`` stepped one after the other, as a group's collectors step them,
against one TorchRL ``GymWrapper`` over gymnasium's ``SyncVectorEnv`` of S (same-step
autoreset, the mode ``GymWrapper`` takes), rounds interleaved, the best of ``--repeats``;
written to ``vector_env_cost.json``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import time
from pathlib import Path

import torch
from cli_types import count
from provenance import provenance
from update_throughput import recipe_config

from torchrl_rave.recipe.agent import make_actor, make_env
from torchrl_rave.recipe.collect import make_collector, push_policy_weights
from torchrl_rave.recipe.config import check_config

ROOT = Path(__file__).resolve().parents[1]


def measure(
    env_name: str,
    backend: str,
    workers: int,
    frames_per_batch: int,
    batches: int,
    record_episode: bool = False,
):
    cfg = recipe_config(
        [
            f"env.name={env_name}",
            f"collector.backend={backend}",
            f"collector.num_workers={workers}",
            f"collector.frames_per_batch={frames_per_batch}",
            f"collector.total_frames={frames_per_batch * (batches + 1)}",
            "collector.init_random_frames=0",
            f"ray.num_cpus={max(workers, os.cpu_count() or 1)}",
        ]
    )
    algo = check_config(cfg)
    env = make_env(cfg, torch.device("cpu"), record_episode=record_episode)
    _, policy = make_actor(cfg, env, algo)
    collector = make_collector(cfg, env, policy, torch.device("cpu"))
    try:
        iterator = iter(collector)
        next(iterator)  # warm-up: worker start, first resets
        start, frames = time.perf_counter(), 0
        for data in iterator:
            frames += data.numel()
            push_policy_weights(collector, policy)  # as the training loop does
        return frames / (time.perf_counter() - start)
    finally:
        collector.shutdown()


def vector_env_cost(env_name: str, num_envs: int, steps: int, repeats: int) -> dict:
    """Env steps per second (every env's steps counted) of ``num_envs`` ``GymEnv`` stepped
    in turn and of one ``GymWrapper`` over a ``SyncVectorEnv`` of them; the best of
    ``repeats`` interleaved rounds of ``steps`` steps each."""
    import gymnasium as gym
    from torchrl.envs import GymEnv, GymWrapper

    singles = [GymEnv(env_name) for _ in range(num_envs)]
    vector = GymWrapper(
        gym.vector.SyncVectorEnv(
            [lambda: gym.make(env_name) for _ in range(num_envs)],
            autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
        )
    )

    def in_turn() -> float:
        tds = [e.reset() for e in singles]
        start = time.perf_counter()
        for _ in range(steps):
            for i, e in enumerate(singles):
                tds[i]["action"] = e.action_spec.rand()
                _, tds[i] = e.step_and_maybe_reset(tds[i])
        return steps * num_envs / (time.perf_counter() - start)

    def batched() -> float:
        td = vector.reset()
        start = time.perf_counter()
        for _ in range(steps):
            td["action"] = vector.action_spec.rand()
            _, td = vector.step_and_maybe_reset(td)
        return steps * num_envs / (time.perf_counter() - start)

    best = {"in_turn": 0.0, "vector": 0.0}
    for _ in range(repeats):
        best["in_turn"] = max(best["in_turn"], in_turn())
        best["vector"] = max(best["vector"], batched())
    for e in [*singles, vector]:
        e.close()
    return {
        "num_envs": num_envs,
        "steps": steps,
        "in_turn_steps_per_s": best["in_turn"],
        "vector_steps_per_s": best["vector"],
        "vector_over_in_turn": best["vector"] / best["in_turn"],
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--workers", nargs="+", type=count(), default=[1, 2, 4])
    parser.add_argument(
        "--backends",
        nargs="+",
        choices=["process", "ray"],
        default=["process", "ray"] if importlib.util.find_spec("ray") else ["process"],
    )
    parser.add_argument("--frames-per-batch", type=count(), default=1000)
    parser.add_argument("--batches", type=count(), default=5)
    parser.add_argument("--repeats", type=count(), default=2)
    parser.add_argument(
        "--record-cost",
        action="store_true",
        help="the direct backend with and without the episode record, alone",
    )
    parser.add_argument(
        "--vector-env",
        type=count(),
        default=None,
        metavar="S",
        help="instead: S envs stepped in turn against one GymWrapper over a SyncVectorEnv of S",
    )
    parser.add_argument(
        "--steps", type=count(), default=1000, help="with --vector-env: steps per round"
    )
    parser.add_argument("--json", default=None, help="default: benchmarks/<what was timed>.json")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # the learner's share; workers are single-threaded processes
    if args.vector_env is not None:
        row = vector_env_cost(args.env, args.vector_env, args.steps, args.repeats)
        print(
            f"{args.env}, {row['num_envs']} envs: {row['in_turn_steps_per_s']:.0f} env steps/s "
            f"stepped in turn, {row['vector_steps_per_s']:.0f} as one SyncVectorEnv "
            f"(x{row['vector_over_in_turn']:.2f}), best of {args.repeats}"
        )
        record = {**provenance("collection_throughput.py", argv), "env": args.env, **row}
        out = Path(args.json or ROOT / "benchmarks" / "vector_env_cost.json")
        out.write_text(json.dumps(record, indent=2))
        return row
    # (name, backend, workers, whether the learner's env keeps the episode, as training's
    # direct env does; workers' envs never do)
    runs = [("direct", "direct", 1, True)]
    if args.record_cost:
        runs.append(("direct, unrecorded", "direct", 1, False))
    else:
        runs += [(f"{b} x{n}", b, n, False) for b in args.backends for n in args.workers]
    rows = {}
    for _ in range(args.repeats):  # rounds interleave the settings, so drifts hit all alike
        for name, backend, n, record in runs:
            fps = measure(
                args.env,
                backend,
                n,
                args.frames_per_batch - args.frames_per_batch % n,
                args.batches,
                record_episode=record,
            )
            rows[name] = max(rows.get(name, 0.0), fps)
    print(
        f"{args.env}: frames/s over {args.batches} batches of {args.frames_per_batch}, "
        f"best of {args.repeats}"
    )
    for name, fps in rows.items():
        print(f"  {name:<20}{fps:9.0f}   x{fps / rows['direct']:.2f} vs direct")
    record = {**provenance("collection_throughput.py", argv), "env": args.env, "frames_per_s": rows}
    default = "episode_record_cost.json" if args.record_cost else "collection_throughput.json"
    Path(args.json or ROOT / "benchmarks" / default).write_text(json.dumps(record, indent=2))
    return rows


if __name__ == "__main__":
    main()
