"""Does ``keep_freed_memory`` pay? The same updates with glibc's default malloc and with
``torchrl_rave.recipe.keep_freed_memory()``, side by side.

    python benchmarks/malloc_reuse.py              # about 2 min on 2 cores
    python benchmarks/malloc_reuse.py --help

malloc's settings belong to the whole process, so every measurement runs in a fresh
worker process (this script with ``--worker plain|kept``); the two kinds alternate over
``--rounds`` rounds and the median of each is reported. Each worker times the recipe's full
``rave`` update, the RAVE target alone, the recipe's ``ddpg`` and the plain-PyTorch DDPG
of ``update_throughput.py`` at the default sizes, and counts the minor page faults per
update (``getrusage``). It also runs 20 seeded updates of ``rave`` and ``ddpg`` from the
same start and hashes every parameter afterwards: equal hashes in both kinds of worker
show the setting changes no number.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from cli_types import count
from provenance import provenance

ROOT = Path(__file__).resolve().parents[1]
CASES = ("ours: rave", "target only: rave", "ours: ddpg", "plain PyTorch DDPG")


def _faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def worker(kind: str, seconds: float) -> dict:
    """One worker process: its timings, faults and parameter hashes as a dict."""
    import torch
    from update_throughput import batches, plain_ddpg_update, recipe_config, recipe_update

    from torchrl_rave.recipe.memory import keep_freed_memory

    took = keep_freed_memory() if kind == "kept" else False
    device = torch.device("cpu")
    cfg = recipe_config([])
    data = batches(cfg.replay_buffer.batch_size, device)
    steps = {
        "ours: rave": recipe_update("rave", [], device)[0],
        "target only: rave": recipe_update("rave", [], device, target_only=True)[0],
        "ours: ddpg": recipe_update("ddpg", [], device)[0],
        "plain PyTorch DDPG": plain_ddpg_update(cfg, device),
    }
    out = {"kind": kind, "malloc_setting_applied": took, "cases": {}, "hashes": {}}
    for name, step in steps.items():
        for i in range(5):  # warm-up: the heap grows to its working size here
            step(data[i % len(data)])
        n, started, faults = 0, time.perf_counter(), _faults()
        while time.perf_counter() - started < seconds:
            step(data[n % len(data)])
            n += 1
        elapsed, faults = time.perf_counter() - started, _faults() - faults
        out["cases"][name] = {"ms_per_update": 1e3 * elapsed / n, "faults_per_update": faults / n}
    for algo in ("rave", "ddpg"):  # the numbers themselves, from one seeded start
        step, _, loss = recipe_update(algo, [], device)
        for i in range(20):
            step(data[i % len(data)])
        digest = hashlib.sha256()
        for p in loss.parameters():
            digest.update(p.detach().contiguous().numpy().tobytes())
        out["hashes"][algo] = digest.hexdigest()
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=count(), default=4, help="worker pairs (default 4)")
    parser.add_argument(
        "--seconds", type=float, default=4.0, help="timed seconds per case per worker (default 4)"
    )
    parser.add_argument("--worker", choices=("plain", "kept"), help=argparse.SUPPRESS)
    parser.add_argument(
        "--json",
        default=str(ROOT / "benchmarks" / "malloc_reuse.json"),
        help="where to write the results",
    )
    args = parser.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker, args.seconds)))
        return {}

    started = time.perf_counter()
    runs: dict[str, list[dict]] = {"plain": [], "kept": []}
    for r in range(args.rounds):
        for kind in ("plain", "kept") if r % 2 == 0 else ("kept", "plain"):
            proc = subprocess.run(
                [sys.executable, __file__, "--worker", kind, "--seconds", str(args.seconds)],
                capture_output=True,
                text=True,
                check=True,
                cwd=ROOT,
            )
            runs[kind].append(json.loads(proc.stdout.strip().splitlines()[-1]))
            print(f"round {r + 1}/{args.rounds}: {kind} done", flush=True)

    def median(kind, case, key):
        return statistics.median(run["cases"][case][key] for run in runs[kind])

    rows = {
        case: {
            kind: {
                "ms_per_update": median(kind, case, "ms_per_update"),
                "faults_per_update": median(kind, case, "faults_per_update"),
            }
            for kind in runs
        }
        for case in CASES
    }
    hashes = [run["hashes"] for kind in runs for run in runs[kind]]
    result = {
        **provenance("malloc_reuse.py", argv),
        "device": f"cpu: {platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "malloc_setting_applied": all(run["malloc_setting_applied"] for run in runs["kept"]),
        "rounds": args.rounds,
        "rows": rows,
        "kept / plain": {
            case: rows[case]["kept"]["ms_per_update"] / rows[case]["plain"]["ms_per_update"]
            for case in CASES
        },
        "identical_parameters": all(h == hashes[0] for h in hashes),
        "wall_s": time.perf_counter() - started,
    }
    print(f"\n{result['device']}; setting applied: {result['malloc_setting_applied']}")
    print(f"{'workload':<22}{'plain ms':>10}{'kept ms':>10}{'kept/plain':>12}"
          f"{'plain faults':>14}{'kept faults':>13}")  # fmt: skip
    for case in CASES:
        p, k = rows[case]["plain"], rows[case]["kept"]
        print(
            f"{case:<22}{p['ms_per_update']:>10.2f}{k['ms_per_update']:>10.2f}"
            f"{result['kept / plain'][case]:>12.2f}{p['faults_per_update']:>14.0f}"
            f"{k['faults_per_update']:>13.0f}"
        )
    print(f"parameters after 20 seeded updates identical: {result['identical_parameters']}")
    print(f"wall time {result['wall_s']:.0f} s; results in {args.json}")
    Path(args.json).write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
