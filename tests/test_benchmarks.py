"""benchmarks/update_throughput.py: its FLOP counts match the network rows of the estimator's
docstring (N M H transition, N^2 M H reward, K M (1 + N H) critic ...), and it runs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch
import update_throughput as bench
from torch import nn

from torchrl_rave.recipe.update import make_agent_step

ROOT = Path(__file__).resolve().parents[1]


def flops_per_row(module: nn.Module) -> int:
    """2 x in x out summed over one member's dense layers (Linear or EnsembleLinear)."""
    total = 0
    for name, p in module.named_parameters():
        if name.endswith("weight"):
            total += 2 * p.shape[-1] * p.shape[-2]
    return total


@pytest.mark.parametrize("N,K,H", [(4, 4, 3), (2, 3, 1), (3, 2, 2)])
def test_target_flops_equal_the_row_count(N, K, H):
    M = 16
    overrides = [
        f"world_model.num_models={N}",
        f"network.num_critics={K}",
        f"estimator.horizon={H}",
        f"replay_buffer.batch_size={M}",
    ]
    step, _, loss = bench.recipe_update("rave", overrides, torch.device("cpu"), target_only=True)
    estimator = loss.value_estimator
    wm = estimator.world_model
    case = bench.Case("rave target", step, bench.batches(M, torch.device("cpu"), count=1))
    case.count_flops()

    critic = flops_per_row(estimator.value_network)
    actor = flops_per_row(estimator.actor_network)
    expected = (
        (N * M * H + N * M) * flops_per_row(wm.transition)  # rollout + eq. 12 error
        + N * N * M * H * flops_per_row(wm.reward_model)
        + N * M * H * flops_per_row(wm.termination)
        + K * M * (1 + N * H) * critic
        + M * (1 + N * H) * actor
    )
    # the mean and log-variance heads are both evaluated: flops_per_row counts both
    assert case.flops == expected


def test_runs_and_writes_ratios(tmp_path):
    out = tmp_path / "b.json"
    result = bench.main(
        ["--seconds", "0.2", "--paper-batches", "0", "--no-scaling", "--json", str(out)]
    )
    saved = json.loads(out.read_text())
    assert saved["default"]["ratios"] == pytest.approx(result["default"]["ratios"])
    if sys.platform.startswith("linux"):  # glibc: measured as the recipe runs
        assert saved["malloc"] == "keep_freed_memory()"
    rows = saved["default"]["rows"]
    assert set(rows) >= {
        "plain PyTorch DDPG",
        "TorchRL DDPGLoss",
        "ours: rave",
        "target only: rave",
    }
    assert all(r["ms_per_update"] > 0 and r["gflop_per_update"] > 0 for r in rows.values())
    # the plain-PyTorch RAVE makes exactly our matmuls, in the update and in the target
    for ours, plain in (
        ("ours: rave", "plain PyTorch RAVE"),
        ("target only: rave", "target only: plain RAVE"),
    ):
        assert rows[plain]["gflop_per_update"] == rows[ours]["gflop_per_update"]
    # the floor rows replay exactly the updates' matmuls
    for algo in ("ddpg", "rave"):
        floor = rows[f"matmuls alone: {algo}"]
        assert floor["gflop_per_update"] == rows[f"ours: {algo}"]["gflop_per_update"]
    # the same networks: our DDPG and the plain one do about the same arithmetic
    assert rows["ours: ddpg"]["gflop_per_update"] == pytest.approx(
        rows["plain PyTorch DDPG"]["gflop_per_update"], rel=0.15
    )


def test_every_scaling_point_builds_a_rave_agent():
    """The scaling table's grid holds only configurations the recipe accepts (it once
    kept K = 1, which RAVE refuses, and the default command stopped there)."""
    for knob, values in bench.SCALING_GRID.items():
        assert bench.SCALING_BASE[knob] in values  # each knob's row has the default point
        for v in values:
            point = {**bench.SCALING_BASE, knob: v}
            agent, cfg, _ = bench.recipe_agent("rave", bench.scaling_overrides(point), "cpu")
            assert agent.world_model.num_models == point["N"]
            assert cfg.network.num_critics == point["K"]


def test_plain_rave_is_the_recipes_rave_update():
    """plain_rave.PlainRAVE, the plain-PyTorch baseline, computes the recipe's numbers: from
    the same start and random stream, the same target and the same three losses, and
    after 4 updates the same parameters, online and target (float rounding only)."""
    from plain_rave import PlainRAVE, tensors

    cpu = torch.device("cpu")
    agent, cfg, _ = bench.recipe_agent("rave", [], cpu)
    plain = PlainRAVE(agent, cfg)
    data = bench.batches(cfg.replay_buffer.batch_size, cpu, count=4)
    batch = data[0]
    torch.manual_seed(1)
    ours = agent.loss.value_estimator.value_estimate(batch.clone()).reshape(-1)
    torch.manual_seed(1)
    torch.testing.assert_close(plain.target(*plain.read(batch)), ours, rtol=1e-6, atol=1e-6)
    assert ours.std() > 0.1  # per-sample targets, not a constant

    torch.manual_seed(2)
    model = agent.world_model_trainer.loss(batch)
    torch.manual_seed(2)
    expected = model["loss_transition"] + model["loss_reward"] + model["loss_termination"]
    torch.testing.assert_close(plain.model_loss(*plain.read(batch)), expected)
    torch.manual_seed(3)
    out = agent.loss(batch.clone())
    torch.manual_seed(3)
    critic, actor = plain.agent_losses(*plain.read(batch))
    torch.testing.assert_close((critic, actor), (out["loss_value"], out["loss_actor"]))

    before = [p.detach().clone() for p in tensors(plain.critic)]
    step = make_agent_step(cfg, agent.loss, agent.optimizers, agent.target_updater)
    for i, batch in enumerate(data):
        torch.manual_seed(10 + i)
        agent.world_model_trainer.update(batch)
        step(batch)
        torch.manual_seed(10 + i)
        plain.update(batch)

    def flat(ts):
        return [t.detach().reshape(-1) for t in ts]

    def leaves(params):  # a parameter TensorDict's weights and biases, in layer order
        flat_td = params.flatten_keys()
        return flat([flat_td[k] for k in flat_td.keys() if "action_" not in k])  # noqa: SIM118

    def gaussian(g):  # in plain_rave's order: trunk, mean head, log-variance head, bounds
        heads = (*g.trunk.parameters(), *g.mean_head.parameters(), *g.logvar_head.parameters())
        return [*heads, g.max_logvar, g.min_logvar]

    wm, loss = agent.world_model, agent.loss
    pairs = {
        "world model": (
            plain.model,
            [*gaussian(wm.transition), *gaussian(wm.reward_model), *wm.termination.parameters()],
        ),
        "actor": (plain.actor, leaves(loss.actor_network_params)),
        "critics": (plain.critic, leaves(loss.value_network_params)),
        "target critics": (plain.critic_target, leaves(loss.target_value_network_params)),
        "target actor": (plain.actor_target, leaves(loss.target_actor_network_params)),
    }
    for name, (got, want) in pairs.items():
        torch.testing.assert_close(flat(tensors(got)), flat(want), rtol=1e-5, atol=1e-6, msg=name)
    moved = max((a - b).abs().max() for a, b in zip(tensors(plain.critic), before, strict=True))
    assert moved > 1e-4  # the updates did move the critics


def test_profile_names_the_target_critic_rows(capsys):
    """profile_update.py: the shape table holds the K = 4 critics on the target's
    M (1 + N H) = 128 x 13 = 1664 rows, the biggest item of a default RAVE update."""
    import profile_update

    threads = torch.get_num_threads()
    try:
        text = profile_update.main(["--steps", "2", "--rows", "40", "--target-only"])
    finally:
        torch.set_num_threads(threads)
    assert "rave value target, default sizes, 1 thread(s), keep_freed_memory():" in text
    assert "[4, 1664, 64]" in text and "aten::bmm" in text


def test_profile_matmuls_in_place_names_the_critic_rows_and_unwraps():
    """profile_update.py --matmuls: the K = 4 critics' hidden layer on the target's 1664
    rows is timed twice per target (two hidden layers), and the wrapped entry points are
    the originals again afterwards."""
    import profile_update

    originals = (torch.bmm, torch.baddbmm, torch.matmul, torch.nn.functional.linear)
    threads = torch.get_num_threads()
    try:
        text = profile_update.main(["--steps", "2", "--rows", "40", "--matmuls", "--target-only"])
    finally:
        torch.set_num_threads(threads)
    row = next(line for line in text.splitlines() if "(4, 1664, 64), (4, 64, 64)" in line)
    assert row.split()[1] == "2.0"  # calls per target
    assert (torch.bmm, torch.baddbmm, torch.matmul, torch.nn.functional.linear) == originals


def test_op_table_counts_each_aten_call_per_step():
    """profile_update.op_table on a hand-counted step: per step one mm, two adds (one in
    place) and a relu; over 3 steps the table says so, busiest operator first."""
    import profile_update

    a, b = torch.randn(3, 4), torch.randn(4, 2)

    def run():
        for _ in range(3):
            c = torch.mm(a, b)
            c = c + 1.0
            c.add_(c)
            torch.relu(c)

    text = profile_update.op_table(run, steps=3, rows=10)
    assert text.splitlines()[0] == "ATen calls: 4 per step"
    rows = {line.split()[1]: float(line.split()[0]) for line in text.splitlines()[3:]}
    assert rows == {"aten.mm": 1.0, "aten.add": 1.0, "aten.add_": 1.0, "aten.relu": 1.0}


def test_floor_records_forward_and_backward_matmuls_with_their_layouts():
    """profile_update.matmul_floor on a hand-counted step: a forward ``mm`` and
    ``baddbmm`` and the one backward ``mm`` (the weight's gradient, on the transposed
    input) per step, their FLOPs exactly, and the other ATen calls counted apart."""
    import profile_update

    x, w = torch.randn(8, 4), torch.randn(4, 3, requires_grad=True)
    bias, p, q = torch.randn(2, 1, 5), torch.randn(2, 6, 7), torch.randn(2, 7, 5)

    def run():
        for _ in range(3):
            (x @ w).sum().backward()
            torch.baddbmm(bias, p, q)

    with bench._RecordMatmuls() as rec:
        run()
    ops = [(c[0].overloadpacket.__name__, c[3]) for c in rec.calls[:3]]
    assert ops == [("mm", 2 * 8 * 4 * 3), ("mm", 2 * 4 * 8 * 3), ("baddbmm", 2 * 2 * 6 * 7 * 5)]
    # the backward product reads the input transposed: [4, 8] with strides (1, 4)
    assert rec.calls[1][1][0][:2] == ((4, 8), (1, 4))
    floor = profile_update.matmul_floor(run, steps=3, seconds=0.1)
    assert floor["calls"] == 3 and floor["ms"] > 0
    assert floor["gflop"] == (192 + 192 + 840) / 1e9


def test_record_matmuls_keeps_one_steps_kernels_and_counts_its_other_calls():
    """Over 4 steps of one ``mm`` and one ``relu``: one kernel and one other call per step,
    and the replay calls that kernel again (counted by a second recording)."""
    a, b = torch.randn(3, 4), torch.randn(4, 2)

    def run():
        for _ in range(4):
            torch.mm(a, b)
            torch.relu(a)

    rec = bench.record_matmuls(run, steps=4)
    assert (rec.kernels, rec.other_calls, rec.flops) == (1, 1, 2 * 3 * 4 * 2)
    again = bench.record_matmuls(rec.replay)
    assert (again.kernels, again.other_calls) == (1, 0)


@pytest.mark.parametrize(
    "layout",
    [((3, 4), (4, 1)), ((4, 3), (1, 4)), ((2, 5, 3), (0, 3, 1)), ((2, 3, 4), (24, 8, 1))],
)
def test_floor_operands_have_the_recorded_layout(layout):
    """Replayed operands keep a recorded shape and stride: contiguous, transposed,
    broadcast (stride 0) and a strided slice."""

    t = bench._operand((*layout, torch.float32))
    assert (tuple(t.shape), t.stride()) == layout


def test_floor_of_the_rave_update_counts_every_flop_of_the_flop_counter():
    """The floor's recorded matmuls of one default-size RAVE update carry exactly the
    FLOPs ``torch.utils.flop_counter`` counts for it (forward and backward)."""
    import profile_update

    step, cfg, _ = bench.recipe_update("rave", [], torch.device("cpu"))
    data = bench.batches(cfg.replay_buffer.batch_size, torch.device("cpu"), count=2)
    step(data[0])
    case = bench.Case("rave", step, data)
    case.count_flops()
    floor = profile_update.matmul_floor(lambda: step(data[1]), steps=1, seconds=0.1)
    assert floor["gflop"] * 1e9 == pytest.approx(case.flops, rel=0, abs=0.5)


def test_floor_report_sets_the_step_beside_its_matmuls_and_the_40_percent_budget():
    """profile_update.py --floor: the report's numbers agree with each other (the
    budget is the step's FLOPs at 40 % of the printed peak)."""
    import re

    import profile_update

    threads = torch.get_num_threads()
    try:
        text = profile_update.main(["--floor", "--steps", "2", "--target-only"])
    finally:
        torch.set_num_threads(threads)
    peak = float(re.search(r"matmul peak ([\d.]+) GFLOP/s", text).group(1))
    gflop = float(re.search(r"([\d.]+) GFLOP\n", text).group(1))
    budget = float(re.search(r"40 % of peak would be: +([\d.]+) ms", text).group(1))
    # The target's products, one per layer and call: the 4-layer transition model (3 trunk
    # layers, mean and log-variance heads) on the real step and H = 3 rollout steps,
    # 4 x 5; the 3-layer reward model once, 2 + 2; the termination model once, 3; the
    # K critics once, batched, 4; the 4-layer actor at H + 1 states, 4 x 4.
    assert f"{4 * 5 + 4 + 3 + 4 + 4 * 4} matmul kernels" in text
    assert budget == pytest.approx(gflop / (0.4 * peak) * 1e3, rel=0.005)  # 3 printed digits
    assert re.search(r"its matmuls alone: +[\d.]+ ms", text)


def test_optimizer_step_times_the_recipes_own_parameter_sets(tmp_path):
    """optimizer_step.py: one row per optimiser of a default-size RAVE agent, with the
    agent's own tensor counts, and a time for every variant."""
    import optimizer_step

    threads = torch.get_num_threads()
    try:
        result = optimizer_step.main(
            ["--steps", "2", "--rounds", "1", "--json", str(tmp_path / "o.json")]
        )
    finally:
        torch.set_num_threads(threads)
    rows = {r["parameters"]: r for r in result["rows"]}
    # world model, (weight, bias) per layer: transition 3 trunk layers, mean and log-variance
    # heads and 2 log-variance bounds = 12; reward 2 trunk layers, 2 heads, 2 bounds = 10;
    # termination 3 layers = 6. Critics and actor: 4 layers (the actor's bounds get no step).
    assert [rows[k]["tensors"] for k in ("world model", "critic", "actor", "one small tensor")] == [
        28,
        8,
        8,
        1,
    ]
    assert rows["critic"]["elements"] == 4 * (14 * 64 + 64 + 2 * (64 * 64 + 64) + 64 + 1)
    assert all(r[f"{v}_us"] > 0 for r in rows.values() for v in ("fused", "foreach", "loop"))


def test_seed_group_benchmark_calls_do_not_grow_with_the_group(tmp_path, capsys):
    """benchmarks/seed_group.py: a group of 2 makes no more ATen calls per update than a
    group of 1, while two separate updates make twice one's; its JSON says so, and with
    ``--repeats`` a row is the repeat with the median ratio."""
    import seed_group

    out = tmp_path / "s.json"
    seed_group.main(
        ["--algorithms", "ddpg", "--seeds", "1", "2", "--threads", "1", "--seconds", "0.1",
         "--repeats", "3", "--out", str(out)]
    )  # fmt: skip
    rows = {r["seeds"]: r for r in json.loads(out.read_text())["rows"]}
    assert rows[2]["group_aten_calls"] <= rows[1]["group_aten_calls"]
    assert rows[2]["separate_aten_calls"] == 2 * rows[1]["separate_aten_calls"]
    assert rows[2]["group_gflop"] == pytest.approx(2 * rows[1]["group_gflop"], rel=1e-6)
    for r in rows.values():
        assert r["speedup"] == pytest.approx(
            r["group_per_seed_updates_per_s"] / r["separate_per_seed_updates_per_s"]
        )
        assert len(r["speedup_repeats"]) == 3
        assert r["speedup"] == pytest.approx(sorted(r["speedup_repeats"])[1])
    # bad arguments are named before anything is built
    for bad, problem in ((["--repeats", "0"], "argument --repeats: must be an integer >= 1"),
                         (["--seeds", "0", "4"], "argument --seeds: must be an integer >= 1"),
                         (["--threads", "0"], "argument --threads: must be an integer >= 1"),
                         (["--algorithms", "ppo"], "--algorithms ['ppo']: a seed group trains")):  # fmt: skip
        with pytest.raises(SystemExit):
            seed_group.main([*bad, "--out", str(out)])
        assert problem in capsys.readouterr().err


def test_seed_group_streams_cost_compares_the_two_ways_of_drawing(tmp_path):
    """benchmarks/seed_group.py --streams-cost: the group with its per-seed streams and the
    same group on one shared stream, each timed, and their ratio."""
    import seed_group

    out = tmp_path / "streams.json"
    seed_group.main(
        ["--streams-cost", "--algorithms", "td3", "--seeds", "2", "--threads", "1",
         "--seconds", "0.1", "--out", str(out)]
    )  # fmt: skip
    (row,) = json.loads(out.read_text())["rows"]
    assert row["algorithm"] == "td3" and row["seeds"] == 2
    assert row["own_streams_ms"] > 0 and row["shared_stream_ms"] > 0
    assert row["ratio"] == pytest.approx(row["own_streams_ms"] / row["shared_stream_ms"])


def test_seed_group_library_losses_runs_torchrls_td3_loss_per_seed(tmp_path, capsys):
    """benchmarks/seed_group.py --library-losses: TorchRL's TD3Loss over seed-batched
    networks gives each seed the actor loss its own learner gives (to the bit), and is
    timed against the group in paired rounds, four at least however slow the machine
    (``--seconds 0``: a round past the time once failed to give quartiles); other learners
    are refused, saying why."""
    import seed_group

    out = tmp_path / "library.json"
    seed_group.main(
        ["--library-losses", "--algorithms", "td3", "--seeds", "2", "--threads", "1",
         "--seconds", "0", "--out", str(out)]
    )  # fmt: skip
    (row,) = json.loads(out.read_text())["rows"]
    assert row["seeds"] == 2 and row["rounds"] == 4
    assert row["max_abs_difference"] == 0.0
    assert row["group_ms"] > 0 and row["library_loss_ms"] > 0
    q1, q3 = row["library_over_group_quartiles"]
    assert q1 <= row["library_over_group"] <= q3
    with pytest.raises(SystemExit):
        seed_group.main(["--library-losses", "--algorithms", "sac", "--out", str(out)])
    assert "SACLoss takes one scalar temperature" in capsys.readouterr().err


def test_seed_group_against_times_the_group_of_another_file(tmp_path, capsys):
    """benchmarks/seed_group.py --against: the baseline group is built from the given copy
    of seed_group.py. A copy whose update sleeps 50 ms is the slower one in every round."""
    import seed_group

    import torchrl_rave.trainers.seed_group as module

    source = Path(module.__file__).read_text()
    marker = "        step_actor = step_actor or self.sac\n"
    assert marker in source
    slow = tmp_path / "slow_seed_group.py"
    slow.write_text(source.replace(marker, "        __import__('time').sleep(0.05)\n" + marker))
    out = tmp_path / "against.json"
    seed_group.main(
        ["--against", str(slow), "--algorithms", "ddpg", "--seeds", "2", "--threads", "1",
         "--seconds", "0.5", "--out", str(out)]
    )  # fmt: skip
    result = json.loads(out.read_text())
    (row,) = result["rows"]
    assert result["baseline"] == str(slow) and row["seeds"] == 2 and row["rounds"] >= 2
    assert row["baseline_ms"] >= 50 > row["this_ms"]  # per group update
    assert row["time_ratio_quartiles"][1] < 1
    with pytest.raises(SystemExit):
        seed_group.main(["--against", str(tmp_path / "none.py"), "--out", str(out)])
    assert "no such file" in capsys.readouterr().err


def test_vector_env_cost_times_one_batched_env_against_envs_in_turn(tmp_path):
    """benchmarks/collection_throughput.py --vector-env: S GymEnv stepped in turn and one
    GymWrapper over a SyncVectorEnv of S, each rate counting every env's steps."""
    import collection_throughput

    out = tmp_path / "vector.json"
    row = collection_throughput.main(
        ["--env", "InvertedPendulum-v5", "--vector-env", "2", "--steps", "30", "--repeats", "1",
         "--json", str(out)]
    )  # fmt: skip
    saved = json.loads(out.read_text())
    assert saved["num_envs"] == 2 and saved["steps"] == 30 and saved["env"] == "InvertedPendulum-v5"
    assert row["in_turn_steps_per_s"] > 0 and row["vector_steps_per_s"] > 0
    assert row["vector_over_in_turn"] == pytest.approx(
        row["vector_steps_per_s"] / row["in_turn_steps_per_s"]
    )
