"""What does one Adam step cost on the recipe's small networks? Fused, foreach and the
per-tensor loop, timed in one process on the parameters a default-size RAVE agent steps.

    python benchmarks/optimizer_step.py              # about 20 s
    python benchmarks/optimizer_step.py --threads 1

The parameters are copies of the recipe's own (``make_agent`` at the default CPU sizes, the
world model's 28 tensors, the K = 4 critics' 8 and the actor's 10), each with a gradient
of the same shape. One row times a single small tensor, which shows the fixed cost of a
``step()`` call before any arithmetic. Median over interleaved rounds; writes
``optimizer_step.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch
from cli_types import count
from provenance import provenance
from update_throughput import _Spec, recipe_config

from torchrl_rave.recipe.agent import make_agent
from torchrl_rave.recipe.config import check_config
from torchrl_rave.recipe.memory import keep_freed_memory

VARIANTS = {"fused": {"fused": True}, "foreach": {"foreach": True}, "loop": {"foreach": False}}


def parameter_sets() -> dict[str, list[torch.Tensor]]:
    """The shapes each of a default-size RAVE update's optimisers steps."""
    cfg = recipe_config(["algorithm=rave"])
    check_config(cfg)
    torch.manual_seed(0)
    agent = make_agent(cfg, _Spec(torch.device("cpu")), "cpu")
    sets = {"world model": list(agent.world_model_trainer.optimizer.param_groups[0]["params"])}
    for name in ("critic", "actor"):
        sets[name] = [p for g in agent.optimizers[name].param_groups for p in g["params"]]
    sets["one small tensor"] = sets["world model"][:1]
    # the actor's list also holds its action bounds (buffers, never given a gradient, so
    # Adam skips them): only what a step updates is timed
    return {name: [p for p in params if p.requires_grad] for name, params in sets.items()}


def timed_optimizer(shapes: list[torch.Size], kwargs: dict):
    params = [torch.nn.Parameter(torch.randn(s)) for s in shapes]
    for p in params:
        p.grad = torch.randn_like(p) * 1e-3
    opt = torch.optim.Adam(params, lr=3e-4, **kwargs)
    for _ in range(5):  # state allocated
        opt.step()
    return opt


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--threads", type=count(), default=None, help="torch threads")
    parser.add_argument("--steps", type=count(), default=200, help="steps per round")
    parser.add_argument("--rounds", type=count(), default=7)
    parser.add_argument(
        "--json", type=Path, default=Path(__file__).with_name("optimizer_step.json")
    )
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    keep_freed_memory()
    sets = parameter_sets()
    rows = []
    for set_name, params in sets.items():
        shapes = [p.shape for p in params]
        opts = {v: timed_optimizer(shapes, kw) for v, kw in VARIANTS.items()}
        times = {v: [] for v in opts}
        for _ in range(args.rounds):
            for v, opt in opts.items():
                start = time.perf_counter()
                for _ in range(args.steps):
                    opt.step()
                times[v].append((time.perf_counter() - start) / args.steps * 1e6)
        row = {
            "parameters": set_name,
            "tensors": len(shapes),
            "elements": sum(s.numel() for s in shapes),
            **{f"{v}_us": round(statistics.median(t), 1) for v, t in times.items()},
        }
        rows.append(row)
    result = {
        **provenance("optimizer_step.py", argv),
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "rows": rows,
    }
    print(f"Adam step, {result['threads']} thread(s), microseconds per step (median):")
    print(
        f"{'parameters':18s} {'tensors':>7s} {'elements':>9s} {'fused':>8s} {'foreach':>8s} {'loop':>8s}"
    )
    for r in rows:
        print(
            f"{r['parameters']:18s} {r['tensors']:7d} {r['elements']:9d} "
            f"{r['fused_us']:8.1f} {r['foreach_us']:8.1f} {r['loop_us']:8.1f}"
        )
    args.json.write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
