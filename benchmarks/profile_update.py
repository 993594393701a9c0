"""Where does a default-size RAVE update spend its time? A torch.profiler table.

    python benchmarks/profile_update.py                       # full update, 1 thread
    python benchmarks/profile_update.py --target-only --threads 2

Builds the recipe's update exactly as ``update_throughput.py`` does (same builders, same
Hopper-v5 shapes), warms it up, then profiles ``--steps`` updates on the CPU and prints
the operators by self time, twice: summed over shapes, and split by input shape (which
names the network each call belongs to: ``[4, 1664, 64]`` is the K = 4 critics on the
M (1 + N H) = 1664 rows of the target, ``[4, 1536, 64]`` the reward members on N M H rows,
``[4, 128, 64]`` a training batch). Per-update milliseconds are timed outside the profiler.
"""

from __future__ import annotations

import argparse
import time

import torch
from torch.profiler import ProfilerActivity, profile
from update_throughput import batches, recipe_update

from torchrl_rave.training.memory import keep_freed_memory


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--algorithm", default="rave")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--steps", type=int, default=20, help="updates profiled")
    parser.add_argument("--target-only", action="store_true", help="the value target alone")
    parser.add_argument("--rows", type=int, default=15, help="rows per table")
    parser.add_argument(
        "--default-malloc",
        action="store_true",
        help="leave glibc's malloc thresholds alone (default: keep_freed_memory(), as the "
        "recipe and update_throughput.py run; without it the large target tensors fault "
        "in fresh pages at every update)",
    )
    args = parser.parse_args(argv)
    malloc_kept = False if args.default_malloc else keep_freed_memory()

    torch.set_num_threads(args.threads)
    device = torch.device("cpu")
    step, cfg, _ = recipe_update(args.algorithm, [], device, target_only=args.target_only)
    data = batches(cfg.replay_buffer.batch_size, device)

    def run(n: int) -> None:
        for i in range(n):
            with torch.set_grad_enabled(not args.target_only):
                step(data[i % len(data)])

    run(20)  # warm-up: allocator, planned calls, optimiser state
    start = time.perf_counter()
    run(3 * args.steps)
    ms = (time.perf_counter() - start) / (3 * args.steps) * 1e3
    with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
        run(args.steps)
    what = "value target" if args.target_only else "update"
    out = [
        f"{args.algorithm} {what}, default sizes, {args.threads} thread(s), "
        f"{'keep_freed_memory()' if malloc_kept else 'default malloc'}: {ms:.1f} ms each",
        prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.rows),
        prof.key_averages(group_by_input_shape=True).table(
            sort_by="self_cpu_time_total",
            row_limit=args.rows,
            max_name_column_width=22,
            max_shapes_column_width=60,
        ),
    ]
    text = "\n".join(out)
    print(text)
    return text


if __name__ == "__main__":
    main()
