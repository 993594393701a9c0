"""Many seeds in one learner: per-seed updates per second of a :class:`SeedGroup` of S
learners against S separate single-learner updates, measured side by side in one process.

    python benchmarks/seed_group.py                      # rave and ddpg, S = 1, 2, 4, 8, 1 and 2 threads
    python benchmarks/seed_group.py --device cuda        # on a GPU
    python benchmarks/seed_group.py --algorithms rave --seeds 1 4 --threads 2
    python benchmarks/seed_group.py --algorithms rave --seeds 4 8 --threads 2 --repeats 5
    python benchmarks/seed_group.py --streams-cost --algorithms rave --seeds 4 8 --threads 2
    python benchmarks/seed_group.py --sampling --algorithms rave --seeds 1 2 4 8 --threads 1 2
    git show <commit>:torchrl_rave/trainers/seed_group.py > /tmp/seed_group_old.py
    python benchmarks/seed_group.py --against /tmp/seed_group_old.py --algorithms rave --seeds 8 --threads 2

For each algorithm, thread count and S, two workloads run interleaved (the median of
several rounds, as in ``update_throughput.py``):

- *separate*: S learners built by the recipe (``make_agent``, default sizes, Hopper-v5
  shapes, seeds 0..S-1), each taking its own update in turn: the world-model step
  (``WorldModelTrainer.update``) and the agent update (``agent_update``), exactly what a
  single run does per update;
- *group*: the same S learners fused into one :class:`~torchrl_rave.trainers.SeedGroup`
  with a random stream per seed (:class:`~torchrl_rave.trainers.SeedStreams`), as the
  recipe builds it, taking ``update_world_model`` and ``update`` on a ``[S, B]`` batch.

Reported per S: per-seed updates per second of each, their ratio (the group's speed-up),
the ATen calls one group update makes (a ``TorchDispatchMode`` count, forward, backward
and optimiser steps; only the random draws, one call per seed each, grow with S), and the share of the dense matmul peak
(counted matmul FLOPs x updates per second / peak, measured in the same process).
With ``--repeats n`` each S is measured n times over (the separate learners' speed moves
between runs on a shared machine); a row then reports the repeat with the median ratio
and lists every repeat's ratio (``speedup_repeats``).
Results go to stdout and ``benchmarks/seed_group.json`` (``--out``).

``--sampling`` times how a group's update gets its ``[S, B]`` batch in a run: the recipe's
``GroupSampler`` against ``rb.sample()`` per seed and a stack of the samples, from replay
buffers laid out as a Hopper-v5 run's, with the group's update in the same rounds.

``--library-losses`` (``td3`` only) times the alternative to the group's own update math:
TorchRL's ``TD3Loss`` itself, built over copies of a learner's actor and critic whose
linear layers hold all S seeds' weights (``[S, out, in]``, one ``baddbmm`` per layer),
on the ``[S, B]`` batch with ``reduction="none"`` and each seed's mean summed, stepped
by fused Adam and :class:`~torchrl_rave.objectives.ForeachSoftUpdate` in the preset's
order, against the :class:`SeedGroup` of the same learners, in paired rounds as
``--against``. Before timing it checks that the library loss's actor loss equals each
learner's own on its slice of a batch (``max_abs_difference``).

``--against FILE`` times a change to the group itself: the group of this checkout against
the same group built from another copy of ``torchrl_rave/trainers/seed_group.py`` (an
older commit's, say), in paired rounds in one process, each round timing both in turn
(the order alternating), so that the machine's drift cancels in each round's ratio.
"""

from __future__ import annotations

import argparse
import copy
import importlib.util
import json
import statistics
import time
from pathlib import Path

import torch
from cli_types import count
from provenance import provenance
from tensordict import TensorDict
from torchrl.objectives import TD3Loss
from update_throughput import (
    Case,
    CountOps,
    batches,
    matmul_peak,
    measure,
    recipe_agent,
    recipe_config,
    sync,
)

from torchrl_rave.modules import ensemble_affine
from torchrl_rave.objectives import ForeachSoftUpdate
from torchrl_rave.recipe.agent import make_seed_group
from torchrl_rave.recipe.group import GROUP_ALGORITHMS
from torchrl_rave.recipe.memory import keep_freed_memory
from torchrl_rave.recipe.update import make_agent_step
from torchrl_rave.trainers import SeedGroup, SeedStreams
from torchrl_rave.trainers.seed_group import _gaussian_draw

ROOT = Path(__file__).resolve().parents[1]


#: the recipe overrides every learner is built with (``--preset`` sets the preset)
OVERRIDES: list[str] = []


def learners(algorithm: str, S: int, device):
    """S recipe learners of ``algorithm`` (seeds 0..S-1, normalisers fitted on random
    data) and their config, at :data:`OVERRIDES`."""
    agents = [recipe_agent(algorithm, OVERRIDES, device, seed)[0] for seed in range(S)]
    return recipe_config([f"algorithm={algorithm}", *OVERRIDES]), agents


def separate_case(algorithm: str, S: int, device) -> Case:
    cfg, agents = learners(algorithm, S, device)
    steps = []
    for agent in agents:
        agent_step = make_agent_step(cfg, agent.loss, agent.optimizers, agent.target_updater)
        steps.append((agent.world_model_trainer, agent_step))
    data = batches(cfg.replay_buffer.batch_size, device)

    def step(batch):
        for wm_trainer, agent_step in steps:
            if wm_trainer is not None:
                wm_trainer.update(batch)
            agent_step(batch)

    return Case(f"{algorithm} separate x{S}", step, data)


def group_batches(B: int, S: int, device) -> list[TensorDict]:
    """:func:`update_throughput.batches` of ``S x B`` rows as ``[S, B]`` group batches."""
    return [
        TensorDict.maybe_dense_stack(list(b.split(B))) if S > 1 else b.unsqueeze(0)
        for b in batches(B * S, device)
    ]


def group_case(algorithm: str, S: int, device) -> tuple[Case, SeedGroup]:
    cfg, agents = learners(algorithm, S, device)
    model_based = agents[0].world_model is not None
    streams = SeedStreams(S, device)  # each seed's own random stream, as the recipe's
    for i in range(S):
        torch.manual_seed(i)
        streams.capture(i)
    group = make_seed_group(cfg, agents, streams=streams)
    data = group_batches(cfg.replay_buffer.batch_size, S, device)

    def step(batch):
        if model_based:
            group.update_world_model(batch)
        group.update(batch)

    return Case(f"{algorithm} group x{S}", step, data), group


def aten_calls(case: Case, steps: int = 3) -> float:
    case.step()  # lazily built state (optimiser moments) out of the count
    with CountOps() as mode:
        for _ in range(steps):
            case.step()
    return sum(mode.counts.values()) / steps


def _settings(algorithms, seeds, threads, device):
    """Each ``(threads, algorithm, S)`` in turn, with torch's CPU threads set to it."""
    for n_threads in threads:
        if device.type == "cpu":
            torch.set_num_threads(n_threads)
        for algorithm in algorithms:
            for S in seeds:
                yield n_threads, algorithm, S


def run(algorithms, seeds, threads, device, seconds: float, repeats: int = 1) -> dict:
    peak = {}
    rows = []
    for n_threads, algorithm, S in _settings(algorithms, seeds, threads, device):
        if n_threads not in peak:  # measured once per thread count, at that count
            peak[n_threads] = matmul_peak(device)
        separate = separate_case(algorithm, S, device)
        group, _ = group_case(algorithm, S, device)
        group.count_flops()
        calls = aten_calls(group)
        separate_calls = aten_calls(separate)
        runs = []  # (separate seconds, group seconds) of each repeat
        for _ in range(repeats):
            measure([separate, group], device, seconds)
            sync(device)
            runs.append((separate.seconds, group.seconds))
        ratios = [sep / grp for sep, grp in runs]
        # the repeat with the median ratio (the lower one of an even count)
        median = sorted(range(repeats), key=ratios.__getitem__)[(repeats - 1) // 2]
        sep_s, group_s = runs[median]
        per_seed_group = S / group_s
        per_seed_separate = S / sep_s
        row = {
            "algorithm": algorithm,
            "threads": n_threads,
            "seeds": S,
            "separate_per_seed_updates_per_s": per_seed_separate,
            "group_per_seed_updates_per_s": per_seed_group,
            "speedup": per_seed_group / per_seed_separate,
            "speedup_repeats": ratios,
            "group_ms": group_s * 1e3,
            "separate_ms": sep_s * 1e3,
            "group_aten_calls": calls,
            "separate_aten_calls": separate_calls,
            "group_gflop": group.flops / 1e9,
            "group_share_of_peak": group.flops / group_s / 1e9 / peak[n_threads],
            "separate_share_of_peak": group.flops / sep_s / 1e9 / peak[n_threads],
        }
        rows.append(row)
        spread = f" (repeats {', '.join(f'{r:.2f}' for r in ratios)})" if repeats > 1 else ""
        print(
            f"{algorithm:5s} threads={n_threads} S={S}: per-seed updates/s "
            f"separate {per_seed_separate:7.1f}  group {per_seed_group:7.1f}  "
            f"x{row['speedup']:.2f}{spread}   ATen calls/update {calls:.0f} "
            f"(separate {separate_calls:.0f})   "
            f"{row['group_share_of_peak']:.1%} of peak "
            f"(separate {row['separate_share_of_peak']:.1%})",
            flush=True,
        )
    return {"matmul_peak_gflops": peak, "rows": rows}


def streams_cost(algorithms, seeds, threads, device, seconds: float) -> dict:
    """A group with its per-seed random streams (as the recipe builds it) against the same
    group drawing each random tensor as one call from the process's shared stream, timed
    in the same interleaved rounds: what the streams cost."""
    rows = []
    for n_threads, algorithm, S in _settings(algorithms, seeds, threads, device):
        own, _ = group_case(algorithm, S, device)
        shared, group = group_case(algorithm, S, device)
        group.streams = None
        if group.world_model is not None:
            group.world_model.draw = _gaussian_draw(None)
        measure([own, shared], device, seconds, rounds=7)
        row = {
            "algorithm": algorithm,
            "threads": n_threads,
            "seeds": S,
            "own_streams_ms": own.seconds * 1e3,
            "shared_stream_ms": shared.seconds * 1e3,
            "ratio": own.seconds / shared.seconds,
        }
        rows.append(row)
        print(
            f"{algorithm:5s} threads={n_threads} S={S}: own streams "
            f"{row['own_streams_ms']:.1f} ms, one shared stream "
            f"{row['shared_stream_ms']:.1f} ms, ratio {row['ratio']:.3f}",
            flush=True,
        )
    return {"rows": rows}


def recipe_transitions(n: int, seed: int, device) -> TensorDict:
    """``n`` transitions laid out as the recipe's replay buffer stores a Hopper-v5 run's
    (every entry its collector writes, with its dtype and width; random values)."""
    g = torch.Generator().manual_seed(seed)
    obs, act = 11, 3

    def flags():
        return torch.rand(n, 1, generator=g) < 0.01

    def step_side():
        return {"observation": torch.randn(n, obs, generator=g), "done": flags(),
                "terminated": flags(), "truncated": flags(),
                "episode_reward": torch.randn(n, 1, generator=g),
                "step_count": torch.randint(1000, (n, 1), generator=g)}  # fmt: skip

    return TensorDict(
        {
            **step_side(),
            "action": torch.rand(n, act, generator=g) * 2 - 1,
            "param": torch.randn(n, act, generator=g),
            "index": torch.arange(n),
            "collector": {"traj_ids": torch.randint(100, (n,), generator=g)},
            "next": {**step_side(), "reward": torch.randn(n, 1, generator=g)},
        },
        [n],
    ).to(device)


def sampling_cost(algorithms, seeds, threads, device, seconds: float, frames: int) -> dict:
    """The batch a group's update takes, as the recipe samples it from the seeds' replay
    buffers of ``frames`` transitions each (``GroupSampler``), against ``rb.sample()`` per
    seed under its stream and a stack of the samples; the group's update (world-model step
    and agent update) timed in the same rounds, for scale."""
    from torchrl_rave.recipe.agent import make_replay_buffer
    from torchrl_rave.recipe.group import GroupSampler

    rows = []
    for n_threads, algorithm, S in _settings(algorithms, seeds, threads, device):
        update, group = group_case(algorithm, S, device)
        cfg = recipe_config([f"algorithm={algorithm}"])
        rbs = []
        for i in range(S):
            rb = make_replay_buffer(cfg, device)
            rb.extend(recipe_transitions(frames, i, device))
            rbs.append(rb)
        sampler, stacked = GroupSampler(rbs, group), GroupSampler(rbs, group)
        assert sampler.keys is not None
        stacked.keys = None  # its way for other buffers: rb.sample() per seed, stacked
        old = Case(f"rb.sample() x{S}, stacked", lambda _batch, f=stacked: f(), [None])
        new = Case(f"GroupSampler x{S}", lambda _batch, f=sampler: f(), [None])
        measure([old, new, update], device, seconds, rounds=7)
        batches = 2 if group.world_model is not None else 1  # per update, in a run

        def share(case, batches=batches, update=update):
            return batches * case.seconds / (update.seconds + batches * case.seconds)

        row = {
            "algorithm": algorithm,
            "threads": n_threads,
            "seeds": S,
            "stacked_samples_us": old.seconds * 1e6,
            "group_sampler_us": new.seconds * 1e6,
            "ratio": new.seconds / old.seconds,
            "group_update_ms": update.seconds * 1e3,
            "batches_per_update": batches,
            "stacked_share_of_update_step": share(old),
            "group_sampler_share_of_update_step": share(new),
        }
        rows.append(row)
        print(
            f"{algorithm:5s} threads={n_threads} S={S}: a batch by rb.sample() x{S} and a "
            f"stack {row['stacked_samples_us']:.0f} us, by GroupSampler "
            f"{row['group_sampler_us']:.0f} us (ratio {row['ratio']:.2f}); group update "
            f"{row['group_update_ms']:.1f} ms; sampling's share of an update step "
            f"{row['stacked_share_of_update_step']:.1%} -> "
            f"{row['group_sampler_share_of_update_step']:.1%}",
            flush=True,
        )
    return {"frames_per_seed": frames, "rows": rows}


class _SeedLinear(torch.nn.Module):
    """``S`` linear layers of one shape as one: ``weight`` ``[S, out, in]``, ``bias``
    ``[S, out]``; inputs ``[S, *B, in]``, seed ``s``'s rows meeting seed ``s``'s weights."""

    def __init__(self, layer: torch.nn.Linear, S: int) -> None:
        super().__init__()
        self.weight = torch.nn.Parameter(layer.weight.detach().expand(S, -1, -1).clone())
        self.bias = torch.nn.Parameter(layer.bias.detach().expand(S, -1).clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        flat = x.reshape(self.weight.shape[0], -1, x.shape[-1])
        y = ensemble_affine(flat, self.weight.transpose(-1, -2), self.bias.unsqueeze(-2))
        return y.view(*x.shape[:-1], y.shape[-1])


def _seed_batched(module: torch.nn.Module, S: int) -> torch.nn.Module:
    """A copy of ``module`` with every ``nn.Linear`` a :class:`_SeedLinear` of ``S``."""
    module = copy.deepcopy(module)
    for owner in list(module.modules()):
        for name, child in list(owner.named_children()):
            if isinstance(child, torch.nn.Linear):
                setattr(owner, name, _SeedLinear(child, S))
    return module


def library_td3_case(S: int, device) -> tuple[Case, float]:
    """TorchRL's ``TD3Loss`` over seed-batched copies of S recipe learners' networks (see
    the module's docstring), and the largest difference between its actor loss and the
    learners' own on a batch."""
    cfg, agents = learners("td3", S, device)
    losses = [a.loss for a in agents]
    first = losses[0]
    loss = TD3Loss(
        _seed_batched(first.actor_network, S),
        _seed_batched(first.qvalue_network, S),
        num_qvalue_nets=first.num_qvalue_nets,
        bounds=(first.min_action, first.max_action),
        policy_noise=first.policy_noise,
        noise_clip=first.noise_clip,
        loss_function="l2",
        reduction="none",
    )
    loss.make_value_estimator(gamma=cfg.optim.gamma)
    with torch.no_grad():  # the learners' numbers, seed-stacked (critics: [K, S, ...])
        for name, dim in [("actor_network_params", 0), ("target_actor_network_params", 0),
                          ("qvalue_network_params", 1), ("target_qvalue_network_params", 1)]:  # fmt: skip
            mine = getattr(loss, name)
            for key, leaf in mine.items(True, True):
                if key[-1] in ("weight", "bias"):
                    leaf.copy_(torch.stack([getattr(x, name).get(key) for x in losses], dim))
    leaves = {n: [p for p in getattr(loss, f"{n}_params").values(True, True) if p.requires_grad]
              for n in ("actor_network", "qvalue_network")}  # fmt: skip
    actor_opt = torch.optim.Adam(leaves["actor_network"], lr=cfg.optim.lr_actor, fused=True)
    critic_opt = torch.optim.Adam(leaves["qvalue_network"], lr=cfg.optim.lr_critic, fused=True)
    updater = ForeachSoftUpdate(loss, tau=cfg.optim.tau)
    data = group_batches(cfg.replay_buffer.batch_size, S, device)
    with torch.no_grad():
        mine = loss.actor_loss(data[0])[0].mean(-1)
        theirs = torch.stack([x.actor_loss(data[0][s])[0] for s, x in enumerate(losses)])
    difference = float((mine - theirs).abs().max())

    def step(batch):
        def seed_sum(x):
            return x.mean(-1).sum()

        if cfg.optim.critic_first:
            critic_opt.zero_grad()
            seed_sum(loss.value_loss(batch)[0]).backward()
            critic_opt.step()
            actor_opt.zero_grad()
            seed_sum(loss.actor_loss(batch)[0]).backward()
            actor_opt.step()
        else:
            critic_opt.zero_grad()
            actor_opt.zero_grad()
            (seed_sum(loss.value_loss(batch)[0]) + seed_sum(loss.actor_loss(batch)[0])).backward()
            critic_opt.step()
            actor_opt.step()
        updater.step()

    return Case(f"td3 library loss x{S}", step, data), difference


def _paired(a: Case, b: Case, device, seconds: float) -> dict:
    """``a`` against ``b`` in paired rounds (the order alternating, so that the machine's
    drift cancels in each round's ratio): the rounds, each one's median milliseconds per
    update, and the median of the rounds' time ratios ``a / b`` with its quartiles. At
    least four rounds run, however slow the machine, so that the quartiles exist."""
    for case in (a, b):  # warm-up: optimiser moments, allocator
        for _ in range(3):
            case.step()
    times: tuple[list[float], list[float]] = ([], [])
    order = [(0, a), (1, b)]
    end = time.perf_counter() + 2 * seconds
    while time.perf_counter() < end or len(times[0]) < 4:
        for i, case in order:
            sync(device)
            start = time.perf_counter()
            for _ in range(3):
                case.step()
            sync(device)
            times[i].append((time.perf_counter() - start) / 3)
        order.reverse()
    ratios = [x / y for x, y in zip(*times, strict=True)]
    q1, median, q3 = statistics.quantiles(ratios, n=4)
    return {
        "rounds": len(ratios),
        "ms": [statistics.median(t) * 1e3 for t in times],
        "ratio": median,
        "quartiles": [q1, q3],
    }


def _ratio_text(paired: dict) -> str:
    q1, q3 = paired["quartiles"]
    return f"paired ratio {paired['ratio']:.3f} (quartiles {q1:.3f}-{q3:.3f}, {paired['rounds']} rounds)"


def library_losses(seeds, threads, device, seconds: float) -> dict:
    """The group's ``td3`` update against TorchRL's ``TD3Loss`` over seed-batched networks
    (see the module's docstring): the median of paired rounds' time ratios."""
    rows = []
    for n_threads, algorithm, S in _settings(["td3"], seeds, threads, device):
        group, _ = group_case(algorithm, S, device)
        library, difference = library_td3_case(S, device)
        paired = _paired(library, group, device, seconds)
        row = {
            "algorithm": algorithm,
            "threads": n_threads,
            "seeds": S,
            "rounds": paired["rounds"],
            "group_ms": paired["ms"][1],
            "library_loss_ms": paired["ms"][0],
            "library_over_group": paired["ratio"],
            "library_over_group_quartiles": paired["quartiles"],
            "max_abs_difference": difference,
        }
        rows.append(row)
        print(
            f"{algorithm:5s} threads={n_threads} S={S}: group {row['group_ms']:.1f} ms, "
            f"TD3Loss over seed-batched networks {row['library_loss_ms']:.1f} ms per update; "
            f"{_ratio_text(paired)}; actor losses differ by at most {difference:.1e}",
            flush=True,
        )
    return {"rows": rows}


def against(path: Path, algorithms, seeds, threads, device, seconds: float) -> dict:
    """This checkout's group against the group of the ``seed_group.py`` at ``path``: the
    median of paired rounds' time ratios (this / that), with its quartiles."""
    import torchrl_rave.recipe.agent as agent_module

    spec = importlib.util.spec_from_file_location("seed_group_baseline", path)
    baseline = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(baseline)
    rows = []
    for n_threads, algorithm, S in _settings(algorithms, seeds, threads, device):
        mine, _ = group_case(algorithm, S, device)
        current, agent_module.SeedGroup = agent_module.SeedGroup, baseline.SeedGroup
        try:  # make_seed_group builds the SeedGroup its module imported
            theirs, built = group_case(algorithm, S, device)
        finally:
            agent_module.SeedGroup = current
        assert type(built) is baseline.SeedGroup
        paired = _paired(mine, theirs, device, seconds)
        row = {
            "algorithm": algorithm,
            "threads": n_threads,
            "seeds": S,
            "rounds": paired["rounds"],
            "this_ms": paired["ms"][0],
            "baseline_ms": paired["ms"][1],
            "time_ratio": paired["ratio"],
            "time_ratio_quartiles": paired["quartiles"],
        }
        rows.append(row)
        print(
            f"{algorithm:5s} threads={n_threads} S={S}: this {row['this_ms']:.1f} ms, "
            f"baseline {row['baseline_ms']:.1f} ms per group update; {_ratio_text(paired)}",
            flush=True,
        )
    return {"baseline": str(path), "rows": rows}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--algorithms", nargs="+", default=["rave", "ddpg"])
    parser.add_argument("--seeds", nargs="+", type=count(), default=[1, 2, 4, 8])
    parser.add_argument("--threads", nargs="+", type=count(), default=[1, 2])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seconds", type=float, default=4.0, help="timed per case")
    parser.add_argument(
        "--streams-cost",
        action="store_true",
        help="instead: time the per-seed random streams against one shared stream "
        "(to benchmarks/seed_group_streams.json unless --out is given)",
    )
    parser.add_argument(
        "--sampling",
        action="store_true",
        help="instead: time the group's batch sampling (GroupSampler) against rb.sample() "
        "per seed and a stack (to benchmarks/seed_group_sampling.json unless --out is given)",
    )
    parser.add_argument(
        "--frames", type=count(), default=10_000,
        help="with --sampling: transitions in each seed's replay buffer",
    )  # fmt: skip
    parser.add_argument(
        "--repeats",
        type=count(),
        default=1,
        help="measure each S this many times; a row reports the repeat with the median "
        "ratio and lists every repeat's (separate learners' speed moves between runs)",
    )
    parser.add_argument(
        "--against",
        type=Path,
        default=None,
        metavar="FILE",
        help="instead: time this checkout's group against the group of another copy of "
        "seed_group.py, in paired rounds (to benchmarks/seed_group_against.json unless "
        "--out is given)",
    )
    parser.add_argument(
        "--library-losses",
        action="store_true",
        help="instead: time the group's td3 update against TorchRL's TD3Loss over "
        "seed-batched networks (to benchmarks/seed_group_library_<preset>.json unless --out "
        "is given)",
    )
    parser.add_argument(
        "--preset", default="cpu", help="the recipe preset the learners are built with "
        "(`mujoco`: the field's sizes; to benchmarks/seed_group_<preset>.json unless --out "
        "is given)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    OVERRIDES[:] = [f"preset={args.preset}"]
    unknown = [a for a in args.algorithms if a not in GROUP_ALGORITHMS]
    if unknown:
        parser.error(f"--algorithms {unknown}: a seed group trains {', '.join(GROUP_ALGORITHMS)}")
    if torch.device(args.device).type == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda but torch.cuda.is_available() is False")
    modes = (args.streams_cost, args.against, args.sampling, args.library_losses)
    if args.repeats > 1 and any(modes):
        parser.error("--repeats applies to the speed-up rows only")
    if sum(map(bool, modes)) > 1:
        parser.error("--streams-cost, --against, --sampling and --library-losses are "
                     "different measurements")  # fmt: skip
    if args.library_losses and args.algorithms != ["td3"]:
        parser.error(
            "--library-losses times td3 only (--algorithms td3): SACLoss takes one scalar "
            "temperature, and the DDPG family's losses plan their networks as tensor calls"
        )
    if args.against is not None and not args.against.is_file():
        parser.error(f"--against {args.against}: no such file")
    if args.out is None:
        name = (
            "seed_group_streams.json" if args.streams_cost
            else "seed_group_against.json" if args.against
            else "seed_group_sampling.json" if args.sampling
            else f"seed_group_library_{args.preset}.json" if args.library_losses
            else "seed_group.json" if args.preset == "cpu"
            else f"seed_group_{args.preset}.json"
        )  # fmt: skip
        args.out = ROOT / "benchmarks" / name
    device = torch.device(args.device)
    malloc_kept = keep_freed_memory()
    threads = args.threads if device.type == "cpu" else [torch.get_num_threads()]
    result = {
        **provenance("seed_group.py", argv),
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "malloc": "keep_freed_memory" if malloc_kept else "default",
        "preset": args.preset,
        **(
            streams_cost(args.algorithms, args.seeds, threads, device, args.seconds)
            if args.streams_cost
            else against(args.against, args.algorithms, args.seeds, threads, device, args.seconds)
            if args.against
            else sampling_cost(
                args.algorithms, args.seeds, threads, device, args.seconds, args.frames
            )
            if args.sampling
            else library_losses(args.seeds, threads, device, args.seconds)
            if args.library_losses
            else run(args.algorithms, args.seeds, threads, device, args.seconds, args.repeats)
        ),
    }
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
