"""Where does a default-size RAVE update spend its time? A torch.profiler table.

    python benchmarks/profile_update.py                       # full update, 1 thread
    python benchmarks/profile_update.py --target-only --threads 2

Builds the recipe's update exactly as ``update_throughput.py`` does (same builders, same
Hopper-v5 shapes), warms it up, then profiles ``--steps`` updates on the CPU and prints
the operators by self time, twice: summed over shapes, and split by input shape (which
names the network each call belongs to: ``[4, 1664, 64]`` is the K = 4 critics on the
M (1 + N H) = 1664 rows of the target, ``[4, 1536, 64]`` the reward members on N M H rows,
``[4, 128, 64]`` a training batch). Per-update milliseconds are timed outside the profiler.

``--ops`` counts the ATen operators one step makes (forward, backward and optimiser
steps alike), with a ``TorchDispatchMode``: at these sizes their number, more than the
arithmetic, sets the time.

``--seeds S`` profiles a :class:`~torchrl_rave.trainers.SeedGroup` of ``S`` learners
instead (``seed_group.py`` builds it): ``--ops --seeds 8`` shows that a group's update makes
as many ATen calls as a group of one.

``--floor`` is a lower bound on the step's time: it records every matmul kernel one step
calls (``mm``, ``addmm``, ``bmm``, ``baddbmm``, forward and backward, with their operands'
shapes and strides) and replays exactly that list back to back on operands of the same
layout, with nothing else in between, against the dense matmul peak measured in the same
process. No update that does these products with these kernels can be faster; the
replay's operands stay warm in cache, which only makes the bound lower.

``--matmuls`` times the forward matmuls in place instead, without the profiler: the four
Python-level entry points the networks call (``torch.bmm``, ``torch.baddbmm``,
``torch.matmul``, ``F.linear``) are wrapped with a ``perf_counter`` pair (well under a
microsecond each) and summed by input shape. On this CPU ``torch.profiler`` reports the
large target matmuls several times slower than they run (benchmarks/README.md); this table
is the check. Backward matmuls run inside autograd and are not in it.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import torch
from cli_types import count
from torch.nn import functional as F
from torch.profiler import ProfilerActivity, profile
from update_throughput import Case, CountOps, batches, measure, recipe_update, record_matmuls

from torchrl_rave.recipe.memory import keep_freed_memory

_MATMULS = ((torch, "bmm"), (torch, "baddbmm"), (torch, "matmul"), (F, "linear"))


def matmul_table(run, steps: int, rows: int) -> str:
    """``run()`` with the forward matmul entry points wrapped: time per update by shape."""
    acc: dict[tuple, list] = defaultdict(lambda: [0, 0.0])

    def timed(name, fn):
        def call(*args, **kwargs):
            start = time.perf_counter()
            out = fn(*args, **kwargs)
            key = (name, tuple(tuple(a.shape) for a in args if isinstance(a, torch.Tensor)))
            acc[key][0] += 1
            acc[key][1] += time.perf_counter() - start
            return out

        return call

    saved = [(owner, name, getattr(owner, name)) for owner, name in _MATMULS]
    try:
        for owner, name, fn in saved:
            setattr(owner, name, timed(name, fn))
        run()
    finally:
        for owner, name, fn in saved:
            setattr(owner, name, fn)
    total = sum(t for _, t in acc.values()) / steps * 1e3
    lines = [f"forward matmuls in place: {total:.2f} ms per call of the step", ""]
    lines.append(f"{'ms/step':>8} {'calls':>6} {'us/call':>8}  op, input shapes")
    for (name, shapes), (n, t) in sorted(acc.items(), key=lambda kv: -kv[1][1])[:rows]:
        lines.append(f"{t / steps * 1e3:8.3f} {n / steps:6.1f} {t / n * 1e6:8.1f}  {name} {shapes}")
    return "\n".join(lines)


def op_table(run, steps: int, rows: int) -> str:
    """``run()`` under a dispatch mode that counts ATen calls: calls per step by operator."""
    with CountOps() as mode:
        run()
    total = sum(mode.counts.values()) / steps
    lines = [f"ATen calls: {total:.0f} per step", "", f"{'calls/step':>10}  operator"]
    for name, n in mode.counts.most_common(rows):
        lines.append(f"{n / steps:10.1f}  {name}")
    return "\n".join(lines)


def cheapest_call_us(n: int = 20_000, rounds: int = 5) -> float:
    """Microseconds of about the cheapest ATen call Python can make: an in-place add on a
    one-element tensor (median of ``rounds`` loops of ``n``)."""
    x = torch.zeros(1)
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(n):
            x.add_(1.0)
        times.append((time.perf_counter() - start) / n * 1e6)
    return sorted(times)[rounds // 2]


def matmul_floor(run, steps: int, seconds: float = 1.0) -> dict:
    """``run()`` (``steps`` steps) recorded (:func:`update_throughput.record_matmuls`),
    then one step's matmuls replayed back to back and timed as ``update_throughput``
    times its workloads (median of interleaved rounds over about ``seconds``):
    ``{"calls", "other_calls", "gflop", "ms"}`` per step."""
    rec = record_matmuls(run, steps)
    case = Case("matmuls alone", rec.replay, [None])
    measure([case], torch.device("cpu"), seconds)
    return {
        "calls": rec.kernels,
        "other_calls": rec.other_calls,
        "gflop": rec.flops / 1e9,
        "ms": case.seconds * 1e3,
    }


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--algorithm", default="rave")
    parser.add_argument("--threads", type=count(), default=1)
    parser.add_argument("--steps", type=count(), default=20, help="updates profiled")
    parser.add_argument("--target-only", action="store_true", help="the value target alone")
    parser.add_argument("--rows", type=count(), default=15, help="rows per table")
    parser.add_argument(
        "--matmuls",
        action="store_true",
        help="time the forward matmuls in place (wrapped entry points) instead of profiling",
    )
    parser.add_argument("--ops", action="store_true", help="count ATen calls per step instead")
    parser.add_argument(
        "--seeds",
        type=count(0),
        default=0,
        help="profile a SeedGroup of this many learners instead (ddpg, mve, steve, rave; "
        "one step updates every seed, as in seed_group.py)",
    )
    parser.add_argument(
        "--floor",
        action="store_true",
        help="replay one step's matmul kernels back to back: a lower bound on its time",
    )
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
    if args.seeds:
        from seed_group import group_case

        case, group = group_case(args.algorithm, args.seeds, device)
        step, data = case._step, case.data
        if args.target_only:
            step = group.value_target
    else:
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
    what = "value target" if args.target_only else "update"
    if args.seeds:
        what = f"{what} of a group of {args.seeds} seeds"
    out = [
        f"{args.algorithm} {what}, default sizes, {args.threads} thread(s), "
        f"{'keep_freed_memory()' if malloc_kept else 'default malloc'}: {ms:.1f} ms each"
    ]
    if args.floor:
        from update_throughput import matmul_peak

        peak = matmul_peak(device)
        f = matmul_floor(lambda: run(args.steps), args.steps)
        budget = f["gflop"] / (0.4 * peak) * 1e3
        left = (budget - f["ms"]) * 1e3 / f["other_calls"]
        out.append(
            f"matmul peak {peak:.1f} GFLOP/s; one step: {f['calls']} matmul kernels, "
            f"{f['gflop']:.3f} GFLOP\n"
            f"  the step as it runs:   {ms:6.2f} ms = {f['gflop'] / ms * 1e5 / peak:5.1f} % of peak\n"
            f"  its matmuls alone:     {f['ms']:6.2f} ms = "
            f"{f['gflop'] / f['ms'] * 1e5 / peak:5.1f} % of peak ({f['ms'] / ms:.0%} of the step)\n"
            f"  40 % of peak would be: {budget:6.2f} ms, which leaves {left:.2f} us for each of "
            f"its {f['other_calls']} other ATen calls;\n"
            f"  the cheapest ATen call from Python (add_ on one element) takes "
            f"{cheapest_call_us():.2f} us"
        )
    elif args.ops:
        out.append(op_table(lambda: run(args.steps), args.steps, args.rows))
    elif args.matmuls:
        out.append(matmul_table(lambda: run(args.steps), args.steps, args.rows))
    else:
        with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
            run(args.steps)
        out += [
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
