"""How fast is one training update? RAVE, STEVE and our DDPG against plain PyTorch and
TorchRL's stock DDPGLoss, as ratios measured in one process.

    python benchmarks/update_throughput.py                 # CPU-friendly sizes, < 5 min
    python benchmarks/update_throughput.py --device cuda   # on a GPU
    python benchmarks/update_throughput.py --help

Measured, in this order:

1. dense float32 matmul peak (GFLOP/s) of this device;
2. full updates at the recipe's default sizes (``recipes/config.yaml``, Hopper-v5 shapes):
   a plain-PyTorch DDPG, TorchRL's stock ``DDPGLoss``, the recipe's ``ddpg``, ``steve``
   and ``rave`` (world-model step + K critics + actor + soft target update, exactly the
   recipe's ``WorldModelTrainer.update`` / ``agent_update``) and the same RAVE update in
   plain PyTorch (``plain_rave.py``); the matmul kernels of our ``ddpg`` and ``rave``
   updates alone, recorded and replayed back to back (a floor under any implementation
   of them, :func:`record_matmuls`); and the value target alone;
   malloc is set up as the recipe sets it (``keep_freed_memory``; ``--default-malloc``
   leaves it alone);
3. the paper's row: seconds for 500 batches of 512 at the paper's sizes (``preset=paper``),
   RAVE vs STEVE vs DDPG (the median of ``--paper-batches`` interleaved rounds, extrapolated);
4. a scaling table: one RAVE update as N, K, H_max and the batch size grow;
5. with ``--compile [MODE]``: the recipe's ``ddpg`` and ``rave`` updates under
   ``compile.enabled=true`` (and ``compile.mode=MODE``, e.g. ``reduce-overhead`` for CUDA
   graphs) and the plain-PyTorch DDPG under ``torch.compile``, beside their eager twins;
   the paper's row then also times ``ddpg``, ``steve`` and ``rave`` compiled (compile
   time is printed, not timed).

FLOPs per update are counted with ``torch.utils.flop_counter`` (matmuls forward and
backward), so "fraction of peak" is counted FLOPs x updates/s over the matmul peak.
Timings interleave the cases over several rounds and report the median, so slow drift of
the machine hits every case alike. Results go to stdout and a JSON file.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import platform
import statistics
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from plain_rave import PlainRAVE
from provenance import provenance
from tensordict import TensorDict
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import FlopCounterMode
from torchrl.data import Bounded
from torchrl.modules import MLP, Actor, ValueOperator
from torchrl.objectives import DDPGLoss, SoftUpdate, ValueEstimators

from torchrl_rave.recipe.agent import make_agent
from torchrl_rave.recipe.config import check_config, override_keys, preset_of, world_model_sizes
from torchrl_rave.recipe.memory import keep_freed_memory
from torchrl_rave.recipe.schema import with_algorithm_preset
from torchrl_rave.recipe.update import make_agent_step

ROOT = Path(__file__).resolve().parents[1]

# Hopper-v5's shapes; the networks' sizes come from the recipe's config.
OBS_DIM, ACT_DIM = 11, 3


def batches(batch_size: int, device: torch.device, count: int = 8) -> list[TensorDict]:
    """A few fixed random batches (the replay buffer is not what is measured)."""
    g = torch.Generator().manual_seed(0)

    def one():
        return TensorDict(
            {
                "observation": torch.randn(batch_size, OBS_DIM, generator=g),
                "action": torch.rand(batch_size, ACT_DIM, generator=g) * 2 - 1,
                ("next", "observation"): torch.randn(batch_size, OBS_DIM, generator=g),
                ("next", "reward"): torch.randn(batch_size, 1, generator=g),
                ("next", "done"): torch.zeros(batch_size, 1, dtype=torch.bool),
                ("next", "terminated"): torch.zeros(batch_size, 1, dtype=torch.bool),
            },
            [batch_size],
        ).to(device)

    return [one() for _ in range(count)]


class _GlobalOnly:
    """Stands in for FlopCounterMode's module tracker, which cannot hash TensorDictParams
    (TorchRL losses hold their parameters in them): every FLOP is counted as 'Global'."""

    parents = ("Global",)

    def __enter__(self):
        return self

    def __exit__(self, *args):
        return False


class FlopCounter(FlopCounterMode):
    """``torch.utils.flop_counter`` totals (matmuls forward and backward), no per-module split."""

    def __init__(self) -> None:
        super().__init__(display=False)
        self.mod_tracker = _GlobalOnly()


class Case:
    """One measured workload: ``step()`` does one update on the next batch."""

    def __init__(self, name: str, step: Callable[[TensorDict], object], data: list[TensorDict]):
        self.name, self._step, self.data = name, step, data
        self.i = 0
        self.samples: list[float] = []
        self.flops = 0

    def step(self) -> None:
        self._step(self.data[self.i % len(self.data)])
        self.i += 1

    def count_flops(self) -> None:
        with FlopCounter() as counter:
            self.step()
        self.flops = counter.get_total_flops()

    @property
    def seconds(self) -> float:
        return statistics.median(self.samples)


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure(cases: list[Case], device: torch.device, seconds: float, rounds: int = 5) -> None:
    """Median seconds per update of each case over ``rounds`` interleaved rounds."""
    for case in cases:  # warm-up (allocations, lazy planning, cuDNN/BLAS selection)
        for _ in range(3):
            case.step()
        sync(device)
        t = time.perf_counter()
        case.step()
        sync(device)
        case._n = max(2, int(seconds / rounds / max(time.perf_counter() - t, 1e-6)))
    for _ in range(rounds):
        for case in cases:
            sync(device)
            t = time.perf_counter()
            for _ in range(case._n):
                case.step()
            sync(device)
            case.samples.append((time.perf_counter() - t) / case._n)


def matmul_peak(device: torch.device, sizes=None, seconds: float = 3.0) -> float:
    """Dense float32 matmul throughput in GFLOP/s: the best timed block over a few sizes
    (float32 as the workloads run it: TF32 only where torch's matmul precision allows)."""
    if sizes is None:
        sizes = (2048, 4096, 8192) if device.type == "cuda" else (1024, 2048)
    best = 0.0
    for size in sizes:
        a = torch.randn(size, size, device=device)
        b = torch.randn(size, size, device=device)
        for _ in range(2):
            a @ b
        sync(device)
        deadline = time.perf_counter() + seconds / len(sizes)
        while time.perf_counter() < deadline:
            t = time.perf_counter()
            for _ in range(3):
                a @ b
            sync(device)
            best = max(best, 3 * 2 * size**3 / (time.perf_counter() - t) / 1e9)
    return best


_GEMMS = ("mm", "addmm", "bmm", "baddbmm")


class _RecordMatmuls(TorchDispatchMode):
    """Records each matmul kernel call: ``(op, operand layouts, keyword args, FLOPs)``;
    counts every ATen call in ``total``."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[tuple] = []
        self.total = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        self.total += 1
        if func.overloadpacket.__name__ in _GEMMS and not kwargs.get("out"):
            layouts = [
                (tuple(a.shape), a.stride(), a.dtype) if isinstance(a, torch.Tensor) else a
                for a in args
            ]
            a, b = args[-2], args[-1]  # the two factors (addmm / baddbmm: bias first)
            flops = 2 * a.numel() * b.shape[-1]
            self.calls.append((func, layouts, kwargs, flops))
        return func(*args, **kwargs)


def _operand(layout, device=None):
    """A random tensor with a recorded ``(shape, stride, dtype)`` (a view of a flat
    buffer just long enough for it: transposed and broadcast layouts included)."""
    if not isinstance(layout, tuple):
        return layout
    shape, stride, dtype = layout
    size = 1 + sum((n - 1) * st for n, st in zip(shape, stride, strict=True))
    return torch.randn(size, dtype=dtype, device=device).as_strided(shape, stride)


class RecordedMatmuls:
    """One step's matmul kernels, recorded by :func:`record_matmuls`: ``replay()`` calls
    exactly them again, back to back, on random operands of the recorded layouts (it
    takes and ignores a batch, so that it can be a :class:`Case`'s step). ``kernels`` and
    ``other_calls`` count one step's matmul kernels and its other ATen calls."""

    def __init__(self, calls: list[tuple], other_calls: int, device=None) -> None:
        self.kernels, self.other_calls = len(calls), other_calls
        self.flops = sum(c[3] for c in calls)
        self._replay = [
            (func, [_operand(x, device) for x in layouts], kw) for func, layouts, kw, _ in calls
        ]

    def replay(self, batch=None) -> None:
        for func, args, kw in self._replay:
            func(*args, **kw)


def record_matmuls(run: Callable[[], object], steps: int = 1, device=None) -> RecordedMatmuls:
    """Runs ``run()`` (``steps`` steps of a workload) and keeps one step's matmul kernels
    (``mm``, ``addmm``, ``bmm``, ``baddbmm``; forward and backward, with each operand's
    shape and stride) and its number of other ATen calls. Replayed back to back they are
    a floor under the step's time: no implementation that does these products with these
    kernels is faster, and the replay's operands even stay warm in cache."""
    with _RecordMatmuls() as rec:
        run()
    per_step = len(rec.calls) // steps
    return RecordedMatmuls(rec.calls[:per_step], (rec.total - len(rec.calls)) // steps, device)


# ------------------------------------------------------------------- the workloads
def recipe_config(overrides: list[str]):
    """The recipe's config for ``overrides``, as a run composes it (a preset's values for
    the algorithm included)."""
    with initialize_config_dir(config_dir=str(ROOT / "recipes"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    return with_algorithm_preset(cfg, preset_of(overrides), override_keys(overrides))


class _Spec:
    """The bits of an env the recipe's builders read (no simulator needed)."""

    def __init__(self, device):
        from torchrl.data import Composite, Unbounded

        self.observation_spec = Composite(
            observation=Unbounded((OBS_DIM,), device=device), device=device
        )
        self.action_spec = Bounded(-1.0, 1.0, (ACT_DIM,), device=device)


def recipe_agent(algorithm: str, overrides: list[str], device, seed: int = 0):
    """The recipe's agent for ``algorithm`` (seeded with ``seed``; a world model's
    normalisers have seen random data): ``(agent, config, algorithm spec)``."""
    cfg = recipe_config([f"algorithm={algorithm}", *overrides])
    algo = check_config(cfg)
    torch.manual_seed(seed)
    agent = make_agent(cfg, _Spec(device), device)
    if agent.world_model is not None:
        agent.world_model.update_normalizers(
            torch.randn(256, OBS_DIM, device=device),
            torch.rand(256, ACT_DIM, device=device) * 2 - 1,
            torch.randn(256, OBS_DIM, device=device),
            torch.randn(256, device=device),
        )
    return agent, cfg, algo


def recipe_update(algorithm: str, overrides: list[str], device, target_only=False):
    """The recipe's update for ``algorithm`` (its own builders and update functions):
    ``(step, config, loss)``."""
    agent, cfg, algo = recipe_agent(algorithm, overrides, device)
    loss = agent.loss

    if target_only:
        estimator = loss.value_estimator

        if algo.model_based:

            def step(batch):
                return estimator.value_estimate(batch)

        else:

            def step(batch):
                # TD(0) needs the next value first: what EnsembleDDPGLoss computes for it
                with torch.no_grad():
                    return loss.loss_value(batch)[1]["target_value"]

        return step, cfg, loss

    agent_step = make_agent_step(cfg, loss, agent.optimizers, agent.target_updater)
    wm_trainer = agent.world_model_trainer

    def step(batch):
        if wm_trainer is not None:
            wm_trainer.update(batch)
        agent_step(batch)

    return step, cfg, loss


def _mlp(in_f, out_f, cells, layers):
    return MLP(
        in_features=in_f,
        out_features=out_f,
        num_cells=[cells] * (layers - 1),
        activation_class=nn.ReLU,
    )


def plain_ddpg_update(cfg, device):
    """DDPG as one writes it in plain PyTorch: same networks, fused Adam, soft targets."""
    n = cfg.network
    actor = nn.Sequential(_mlp(OBS_DIM, ACT_DIM, n.actor_cells, n.num_layers), nn.Tanh()).to(device)
    critic = _mlp(OBS_DIM + ACT_DIM, 1, n.critic_cells, n.num_layers).to(device)
    actor_t, critic_t = copy.deepcopy(actor), copy.deepcopy(critic)
    opt_a = torch.optim.Adam(actor.parameters(), lr=3e-4, fused=True)
    opt_c = torch.optim.Adam(critic.parameters(), lr=3e-4, fused=True)
    pairs = [
        (list(t.parameters()), list(m.parameters()))
        for t, m in ((actor_t, actor), (critic_t, critic))
    ]
    gamma, tau = cfg.optim.gamma, cfg.optim.tau

    def step(batch):
        s, a = batch["observation"], batch["action"]
        s2, r = batch["next", "observation"], batch["next", "reward"]
        not_done = 1.0 - batch["next", "terminated"].float()
        with torch.no_grad():
            y = r + gamma * not_done * critic_t(torch.cat([s2, actor_t(s2)], -1))
        critic_loss = (critic(torch.cat([s, a], -1)) - y).pow(2).mean()
        opt_c.zero_grad()
        critic_loss.backward()
        opt_c.step()
        actor_loss = -critic(torch.cat([s, actor(s)], -1)).mean()
        opt_a.zero_grad()
        actor_loss.backward()
        opt_a.step()
        with torch.no_grad():
            for target, online in pairs:
                torch._foreach_lerp_(target, online, tau)

    return step


def plain_rave_update(device, target_only=False, overrides=()):
    """RAVE in plain PyTorch (``plain_rave.PlainRAVE``), from the starting parameters of
    the recipe's agent (with config ``overrides``); with ``target_only``, its value target
    alone."""
    rave = PlainRAVE(*recipe_agent("rave", list(overrides), device)[:2])
    if target_only:
        return lambda batch: rave.target(*rave.read(batch))
    return rave.update


def stock_ddpg_update(cfg, device):
    """TorchRL's DDPGLoss with its TD(0) estimator and SoftUpdate, as its docs build it."""
    n = cfg.network
    spec = Bounded(-1.0, 1.0, (ACT_DIM,), device=device)
    actor = Actor(
        nn.Sequential(_mlp(OBS_DIM, ACT_DIM, n.actor_cells, n.num_layers), nn.Tanh()), spec=spec
    )
    critic = ValueOperator(
        _mlp(OBS_DIM + ACT_DIM, 1, n.critic_cells, n.num_layers),
        in_keys=["observation", "action"],
    )
    loss = DDPGLoss(actor, critic, delay_actor=True, delay_value=True).to(device)
    loss.make_value_estimator(ValueEstimators.TD0, gamma=cfg.optim.gamma)
    updater = SoftUpdate(loss, tau=cfg.optim.tau)
    opt_a = torch.optim.Adam(loss.actor_network_params.values(True, True), lr=3e-4, fused=True)
    opt_c = torch.optim.Adam(loss.value_network_params.values(True, True), lr=3e-4, fused=True)

    def step(batch):
        out = loss(batch)
        opt_a.zero_grad()
        opt_c.zero_grad()
        (out["loss_actor"] + out["loss_value"]).backward()
        opt_a.step()
        opt_c.step()
        updater.step()

    return step


# ----------------------------------------------------------------------- sections
def compile_overrides(mode: str) -> list[str]:
    """The recipe's overrides for ``--compile MODE`` (``default``: torch.compile's own)."""
    return ["compile.enabled=true"] + ([f"compile.mode={mode}"] if mode != "default" else [])


def section_default(device, seconds, peak, compiled: str | None = None) -> dict:
    """All workloads at the recipe's default (CPU) sizes; with ``compiled`` (a compile
    mode), also the recipe's updates under ``compile.enabled=true`` and plain DDPG under
    ``torch.compile``."""
    cfg = recipe_config([])
    data = batches(cfg.replay_buffer.batch_size, device)
    cases = [
        Case("plain PyTorch DDPG", plain_ddpg_update(cfg, device), data),
        Case("TorchRL DDPGLoss", stock_ddpg_update(cfg, device), data),
    ]
    for algo in ("ddpg", "steve", "rave"):
        cases.append(Case(f"ours: {algo}", recipe_update(algo, [], device)[0], data))
    cases.append(Case("plain PyTorch RAVE", plain_rave_update(device), data))
    for algo in ("ddpg", "rave"):  # the floor: exactly these updates' matmul kernels
        step = recipe_update(algo, [], device)[0]
        step(data[0])  # optimiser states exist, as in the timed updates
        floor = record_matmuls(lambda step=step: step(data[1]), device=device)
        cases.append(Case(f"matmuls alone: {algo}", floor.replay, data))
    for algo in ("ddpg", "steve", "rave"):
        step = recipe_update(algo, [], device, target_only=True)[0]
        cases.append(Case(f"target only: {algo}", step, data))
    cases.append(Case("target only: plain RAVE", plain_rave_update(device, True), data))
    for case in cases:
        case.count_flops()
    if compiled:
        eager = {case.name: case for case in cases}
        mode = None if compiled == "default" else compiled
        plain = torch.compile(plain_ddpg_update(cfg, device), mode=mode)
        twins = [Case("plain DDPG compiled", plain, data)]
        twins[0].flops = eager["plain PyTorch DDPG"].flops
        for algo in ("ddpg", "rave"):
            step = recipe_update(algo, compile_overrides(compiled), device)[0]
            twins.append(Case(f"ours compiled: {algo}", step, data))
            twins[-1].flops = eager[f"ours: {algo}"].flops  # the same arithmetic
        started = time.perf_counter()
        for case in twins:  # the compile itself, outside the timings
            for _ in range(2):
                case.step()
        print(f"compiled the {len(twins)} --compile cases in {time.perf_counter() - started:.0f} s")
        cases += twins
    measure(cases, device, seconds)
    rows = {}
    for case in cases:
        rows[case.name] = {
            "ms_per_update": 1e3 * case.seconds,
            "updates_per_s": 1.0 / case.seconds,
            "gflop_per_update": case.flops / 1e9,
            "gflop_per_s": case.flops / case.seconds / 1e9,
            "fraction_of_peak": case.flops / case.seconds / 1e9 / peak,
        }
    t = {name: row["ms_per_update"] for name, row in rows.items()}
    ratios = {
        "rave / steve (full update)": t["ours: rave"] / t["ours: steve"],
        "rave / steve (target only)": t["target only: rave"] / t["target only: steve"],
        "ours ddpg / plain PyTorch DDPG": t["ours: ddpg"] / t["plain PyTorch DDPG"],
        "TorchRL DDPGLoss / plain PyTorch DDPG": t["TorchRL DDPGLoss"] / t["plain PyTorch DDPG"],
        "rave / ours ddpg": t["ours: rave"] / t["ours: ddpg"],
        "ours rave / plain PyTorch RAVE": t["ours: rave"] / t["plain PyTorch RAVE"],
        "ours rave / plain RAVE (target only)": t["target only: rave"]
        / t["target only: plain RAVE"],
        "plain RAVE / plain DDPG": t["plain PyTorch RAVE"] / t["plain PyTorch DDPG"],
        "ours rave / its matmuls alone": t["ours: rave"] / t["matmuls alone: rave"],
        "ours ddpg / its matmuls alone": t["ours: ddpg"] / t["matmuls alone: ddpg"],
    }
    if compiled:
        ratios.update(
            {
                "compiled / eager: ours rave": t["ours compiled: rave"] / t["ours: rave"],
                "compiled / eager: ours ddpg": t["ours compiled: ddpg"] / t["ours: ddpg"],
                "compiled / eager: plain DDPG": t["plain DDPG compiled"] / t["plain PyTorch DDPG"],
                "ours ddpg compiled / plain PyTorch DDPG": t["ours compiled: ddpg"]
                / t["plain PyTorch DDPG"],
                "ours ddpg compiled / plain DDPG compiled": t["ours compiled: ddpg"]
                / t["plain DDPG compiled"],
            }
        )
    wm = world_model_sizes(cfg)
    sizes = {
        "batch": cfg.replay_buffer.batch_size,
        "N": cfg.world_model.num_models,
        "K (steve, rave)": 4,
        "H_max": cfg.estimator.horizon,
        "actor/critic": f"{cfg.network.num_layers} x {cfg.network.critic_cells}",
        "transition": f"{wm['transition_layers']} x {wm['transition_cells']}",
        "reward/termination": f"{wm['reward_layers']} x {wm['reward_cells']}",
    }
    return {"sizes": sizes, "rows": rows, "ratios": ratios}


def section_paper(device, batches_timed: int, peak: float, compiled: str | None = None) -> dict:
    """Seconds for 500 batches of 512 at the paper's sizes, extrapolated from the median of
    ``batches_timed`` interleaved rounds; with ``compiled`` (a compile mode), the recipe's
    updates compiled as well."""
    overrides = ["preset=paper"]
    cfg = recipe_config(overrides)
    data = batches(cfg.replay_buffer.batch_size, device, count=4)
    out = {}
    workloads = {
        "plain PyTorch DDPG": plain_ddpg_update(cfg, device),
        "TorchRL DDPGLoss": stock_ddpg_update(cfg, device),
    }
    for algo in ("ddpg", "steve", "rave"):
        workloads[algo] = recipe_update(algo, overrides, device)[0]
    workloads["plain PyTorch RAVE"] = plain_rave_update(device, overrides=overrides)
    if compiled:
        for algo in ("ddpg", "steve", "rave"):
            step = recipe_update(algo, overrides + compile_overrides(compiled), device)[0]
            workloads[f"{algo} compiled"] = step
    flops, cases = {}, {}
    for algo, step in workloads.items():
        case = cases[algo] = Case(algo, step, data)
        if algo.endswith(" compiled"):  # the same arithmetic as its eager twin
            for _ in range(3):  # compiles, then records the CUDA graphs
                case.step()
            case.flops = flops[algo.removesuffix(" compiled")]
        else:
            case.count_flops()  # doubles as the warm-up
            flops[algo] = case.flops
    # interleaved rounds, one batch of each case per round at least (and 1 s over all rounds
    # for the DDPG rows, which take milliseconds), so that the machine's drift hits every row
    per_round: dict[str, list[float]] = {algo: [] for algo in cases}
    done = dict.fromkeys(cases, 0)
    for _ in range(batches_timed):
        for algo, case in cases.items():
            sync(device)
            t, n = time.perf_counter(), 0
            while n < 1 or time.perf_counter() - t < 1.0 / batches_timed:
                case.step()
                n += 1
                if n % 10 == 0:
                    sync(device)
            sync(device)
            per_round[algo].append((time.perf_counter() - t) / n)
            done[algo] += n
    for algo, case in cases.items():
        per_batch = statistics.median(per_round[algo])
        out[algo] = {
            "batches_timed": done[algo],
            "s_per_batch": per_batch,
            "s_per_500_batches": 500 * per_batch,
            "gflop_per_update": case.flops / 1e9,
            "fraction_of_peak": case.flops / per_batch / 1e9 / peak,
        }
    out["rave / steve"] = out["rave"]["s_per_batch"] / out["steve"]["s_per_batch"]
    if compiled:
        out["rave / steve (compiled)"] = (
            out["rave compiled"]["s_per_batch"] / out["steve compiled"]["s_per_batch"]
        )
    out["rave / plain PyTorch RAVE"] = (
        out["rave"]["s_per_batch"] / out["plain PyTorch RAVE"]["s_per_batch"]
    )
    out["rave / steve (FLOPs)"] = out["rave"]["gflop_per_update"] / out["steve"]["gflop_per_update"]
    out["batches_timed"] = batches_timed
    return out


PAPER_ROWS = (
    "rave",
    "steve",
    "ddpg",
    "plain PyTorch RAVE",
    "plain PyTorch DDPG",
    "TorchRL DDPGLoss",
)


SCALING_BASE = {"N": 4, "K": 4, "H": 3, "batch": 128}
# K starts at 2: RAVE refuses one critic (its inverse-variance mix would be TD(0))
SCALING_GRID = {
    "N": [1, 2, 4, 8],
    "K": [2, 3, 4, 8],
    "H": [0, 1, 3, 6],
    "batch": [64, 128, 256, 512],
}


def scaling_overrides(point: dict) -> list[str]:
    """The recipe's config overrides for one scaling point ``{"N", "K", "H", "batch"}``."""
    return [
        f"world_model.num_models={point['N']}",
        f"network.num_critics={point['K']}",
        f"estimator.horizon={point['H']}",
        f"replay_buffer.batch_size={point['batch']}",
    ]


def section_scaling(device, seconds) -> list[dict]:
    """One RAVE update (full) as one of N, K, H_max, batch grows from the default."""
    base, grid = SCALING_BASE, SCALING_GRID
    cases, meta = [], []
    for knob, values in grid.items():
        for v in values:
            p = {**base, knob: v}
            step = recipe_update("rave", scaling_overrides(p), device)[0]
            cases.append(Case(f"{knob}={v}", step, batches(p["batch"], device, count=4)))
            meta.append((knob, v, p))
    for case in cases:
        case.count_flops()
    measure(cases, device, seconds, rounds=3)
    rows = []
    for case, (knob, v, _) in zip(cases, meta, strict=True):
        base_case = cases[[m[2] == {**base} and m[0] == knob for m in meta].index(True)]
        rows.append(
            {
                "knob": knob,
                "value": v,
                "ms_per_update": 1e3 * case.seconds,
                "gflop_per_update": case.flops / 1e9,
                "time_vs_default": case.seconds / base_case.seconds,
                "flops_vs_default": case.flops / base_case.flops,
            }
        )
    return rows


# --------------------------------------------------------------------------- report
def print_report(result: dict) -> None:
    print(f"\ndevice: {result['device']}  threads: {result['threads']}  malloc: {result['malloc']}")
    print(
        f"dense float32 matmul peak: {result['matmul_peak_gflops']:.1f} GFLOP/s "
        "(best of the measurements at the start and the end)\n"
    )
    d = result["default"]
    print("default sizes: " + ", ".join(f"{k} {v}" for k, v in d["sizes"].items()))
    print(
        f"{'workload':<24}{'ms/update':>10}{'updates/s':>11}{'GFLOP/upd':>11}{'GFLOP/s':>9}"
        f"{'of peak':>9}"
    )
    for name, r in d["rows"].items():
        print(
            f"{name:<24}{r['ms_per_update']:>10.2f}{r['updates_per_s']:>11.1f}"
            f"{r['gflop_per_update']:>11.3f}{r['gflop_per_s']:>9.1f}"
            f"{100 * r['fraction_of_peak']:>8.1f}%"
        )
    print("\nratios (time per update):")
    for name, v in d["ratios"].items():
        print(f"  {name:<40}{v:6.2f}")
    if "paper" in result:
        p = result["paper"]
        print(
            f"\npaper sizes, 500 batches of 512 (the median of {p['batches_timed']} interleaved rounds,"
            f" extrapolated; DDPG rows use the paper's 4 x 128 actor and critic):"
        )
        for algo in PAPER_ROWS + tuple(f"{a} compiled" for a in ("rave", "steve", "ddpg")):
            if algo not in p:
                continue
            r = p[algo]
            print(
                f"  {algo:<20}{r['s_per_500_batches']:9.1f} s   {r['gflop_per_update']:7.2f} GFLOP"
                f"/update   {100 * r['fraction_of_peak']:5.1f}% of peak"
            )
        print(
            f"  ours ddpg / plain PyTorch DDPG {p['ddpg']['s_per_batch'] / p['plain PyTorch DDPG']['s_per_batch']:.2f}"
        )
        print(f"  ours rave / plain PyTorch RAVE {p['rave / plain PyTorch RAVE']:.2f}")
        print(f"  rave / steve FLOPs per update {p['rave / steve (FLOPs)']:.2f}")
        print(
            f"  rave / steve {p['rave / steve']:.2f}  (paper, on its GPU: 13.20 s / 10.62 s = 1.24)"
        )
    if "scaling" in result:
        print("\nRAVE update as one knob grows (default N=4, K=4, H_max=3, batch=128):")
        print(f"{'knob':<12}{'ms/update':>10}{'GFLOP':>9}{'time x':>8}{'FLOPs x':>9}")
        for r in result["scaling"]:
            print(
                f"{r['knob'] + '=' + str(r['value']):<12}{r['ms_per_update']:>10.2f}"
                f"{r['gflop_per_update']:>9.3f}{r['time_vs_default']:>8.2f}"
                f"{r['flops_vs_default']:>9.2f}"
            )


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", help="cpu or cuda (default cpu)")
    parser.add_argument(
        "--seconds", type=float, default=6.0, help="timed seconds per workload (default 6)"
    )
    parser.add_argument(
        "--paper-batches",
        type=int,
        default=3,
        help="interleaved rounds at the paper's sizes, one batch of each case per round at least "
        "(and 1 s per case over all rounds); the median is extrapolated to 500 (default 3; 0 skips)",
    )
    parser.add_argument("--no-scaling", action="store_true", help="skip the scaling table")
    parser.add_argument(
        "--compile",
        nargs="?",
        const="default",
        default=None,
        metavar="MODE",
        help="also time the recipe's compile.enabled=true updates and a compiled plain DDPG; "
        "MODE is compile.mode (e.g. reduce-overhead; default: torch.compile's own)",
    )
    parser.add_argument(
        "--threads", type=int, default=None, help="torch threads (default: torch's own)"
    )
    parser.add_argument(
        "--default-malloc",
        action="store_true",
        help="leave glibc's malloc thresholds alone (default: keep_freed_memory(), as the "
        "recipe runs; see malloc_reuse.py)",
    )
    parser.add_argument(
        "--json",
        default=str(ROOT / "benchmarks" / "update_throughput.json"),
        help="where to write the results",
    )
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    malloc_kept = False if args.default_malloc else keep_freed_memory()
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda but torch.cuda.is_available() is False")
    started = time.perf_counter()
    peak = matmul_peak(device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else platform.processor()
    result = {
        **provenance("update_throughput.py", argv),
        "device": f"{device.type}: {name or platform.machine()}, {os.cpu_count()} cores",
        "threads": torch.get_num_threads(),
        "malloc": "keep_freed_memory()" if malloc_kept else "the C library's defaults",
        "torch": torch.__version__,
        "matmul_peak_gflops": peak,
        "default": section_default(device, args.seconds, peak, compiled=args.compile),
    }
    if args.paper_batches > 0:
        result["paper"] = section_paper(device, args.paper_batches, peak, compiled=args.compile)
    if not args.no_scaling:
        result["scaling"] = section_scaling(device, args.seconds / 3)
    # the machine's clock can drift over a run: measure the peak again and keep the larger
    result["matmul_peak_gflops_end"] = matmul_peak(device)
    if result["matmul_peak_gflops_end"] > peak:
        scale = peak / result["matmul_peak_gflops_end"]
        peak = result["matmul_peak_gflops_end"]
        result["matmul_peak_gflops"] = peak
        for row in result["default"]["rows"].values():
            row["fraction_of_peak"] *= scale
        for algo in result.get("paper", {}):
            if isinstance(result["paper"][algo], dict):
                result["paper"][algo]["fraction_of_peak"] *= scale
    result["wall_s"] = time.perf_counter() - started
    print_report(result)
    print(f"\nwall time {result['wall_s']:.0f} s; results in {args.json}")
    Path(args.json).write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()


class CountOps(TorchDispatchMode):
    """Counts the ATen calls made under it, by operator (``counts``)."""

    def __init__(self) -> None:
        super().__init__()
        self.counts: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.counts[str(func.overloadpacket)] += 1
        return func(*args, **(kwargs or {}))
