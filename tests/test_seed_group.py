"""A seed group's update against each seed's single-learner update, and its isolation."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from test_recipe import make_cfg
from torchrl.data import Bounded, Composite, Unbounded

import torchrl_rave.modules.world_model as world_model_module
from torchrl_rave.modules import ensemble
from torchrl_rave.recipe.agent import make_agent, make_seed_group
from torchrl_rave.recipe.config import GROUP_ALGORITHMS as ALGORITHMS
from torchrl_rave.recipe.update import make_agent_step
from torchrl_rave.trainers import seed_group

OBS, ACT, B = 5, 2, 16
SMALL = [
    "network.actor_cells=16",
    "network.critic_cells=16",
    "network.num_layers=3",
    "world_model.num_models=3",
    "world_model.transition_cells=16",
    "world_model.reward_cells=16",
    "world_model.termination_cells=16",
    "optim.tau=0.5",  # targets move visibly: a wrong soft update shows
]


class Spec:
    """The parts of an env that make_agent reads."""

    observation_spec = Composite(observation=Unbounded((OBS,)))
    action_spec = Bounded(-1.0, 1.0, (ACT,))


def learner(algorithm: str, seed: int, *overrides: str):
    cfg = make_cfg(f"algorithm={algorithm}", *SMALL, *overrides)
    torch.manual_seed(seed)
    agent = make_agent(cfg, Spec())
    if agent.world_model is not None:
        g = torch.Generator().manual_seed(100 + seed)
        agent.world_model.update_normalizers(
            torch.randn(64, OBS, generator=g) * (1 + seed),
            torch.rand(64, ACT, generator=g) * 2 - 1,
            torch.randn(64, OBS, generator=g),
            torch.randn(64, generator=g) + seed,
        )
    return cfg, agent


def make_group(agents, cfg, **kwargs):
    return make_seed_group(cfg, agents, **kwargs)


def batch(S: int, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    terminated = torch.rand(S, B, 1, generator=g) < 0.2
    return TensorDict(
        {
            "observation": torch.randn(S, B, OBS, generator=g),
            "action": torch.rand(S, B, ACT, generator=g) * 2 - 1,
            ("next", "observation"): torch.randn(S, B, OBS, generator=g),
            ("next", "reward"): torch.randn(S, B, 1, generator=g),
            ("next", "done"): terminated.clone(),
            ("next", "terminated"): terminated,
        },
        [S, B],
    )


class Recorder:
    """The group's random draws, kept so that each single learner can replay its slice."""

    def __init__(self) -> None:
        self.noise: list[torch.Tensor] = []
        self.indices: list[torch.Tensor] = []

    def draw(self, mean, logvar, sample):
        if not sample:
            return mean
        eps = torch.randn_like(mean)
        self.noise.append(eps)
        return mean + eps * (0.5 * logvar).exp()

    def policy_noise(self, action):
        eps = torch.randn_like(action)
        self.noise.append(eps)
        return eps

    def bootstrap(self, B_, S):
        idx = torch.randint(B_, (3, S, B_))
        self.indices.append(idx)
        return idx


def replay(monkeypatch, agent, recorder: Recorder, s: int) -> None:
    """Makes ``agent``'s world model draw seed ``s``'s slice of the group's draws."""
    noise = iter([eps[s] for eps in recorder.noise])

    def draw(mean, logvar, sample):
        if not sample:
            return mean
        return mean + next(noise).reshape(mean.shape) * (0.5 * logvar).exp()

    monkeypatch.setattr(world_model_module, "_draw", draw)
    if agent.world_model is None:  # TD3's target smoothing noise: its only draw
        monkeypatch.setattr(torch, "randn_like", lambda x: next(noise).reshape(x.shape))
    # SAC's tanh-Gaussian draws (torch's Normal.rsample)
    monkeypatch.setattr(torch.distributions.normal, "_standard_normal",
                        lambda shape, dtype, device: next(noise).reshape(shape))  # fmt: skip
    if agent.world_model_trainer is not None:
        idx = iter([i[:, s] for i in recorder.indices])
        monkeypatch.setattr(agent.world_model_trainer.loss, "bootstrap_indices",
                            lambda batch_size, device=None: next(idx))  # fmt: skip


def grads(leaves):
    return [None if p.grad is None else p.grad.clone() for p in leaves]


def close(a, b, what):
    torch.testing.assert_close(a, b, rtol=2e-5, atol=2e-6, msg=lambda m: f"{what}: {m}")


CRITIC_FIRST = ("optim.critic_first=true",)
POLICY_SCALE = ("network.default_policy_scale=0.2", "network.scale_lb=0.05")


@pytest.mark.parametrize(
    "algorithm, S, large, extra",
    [(a, S, False, ()) for a in ALGORITHMS for S in (1, 2, 3)]
    + [("rave", 2, True, ()), ("ddpg", 2, True, ())]
    + [(a, 2, False, CRITIC_FIRST) for a in ("ddpg", "rave", "td3", "sac", "rave_sac")]
    + [("sac", 2, False, POLICY_SCALE)],
)
def test_each_seed_is_its_single_update(algorithm, S, large, extra, monkeypatch):
    """Two steps (world model, then agent) of a group of S equal each seed's own steps on
    its own rows: losses, targets, diagnostics, gradients and parameters after Adam. With
    ``large``, every layer takes the path of outputs larger than the caches (bmm, then the
    bias added in place); with ``extra``, the group's and each single learner's config
    (``optim.critic_first``: the critics step before the actor's loss; the SAC policy's
    scale mapping)."""
    if large:
        monkeypatch.setattr(ensemble, "_LARGE", 0)
    critic_first = CRITIC_FIRST[0] in extra
    cfg, _ = learner(algorithm, 0, *extra)
    singles = [learner(algorithm, s, *extra)[1] for s in range(S)]
    grouped = [learner(algorithm, s, *extra)[1] for s in range(S)]
    rec = Recorder()
    group = make_group(grouped, cfg, draw=rec.draw, bootstrap_indices=rec.bootstrap,
                       policy_noise_draw=rec.policy_noise)  # fmt: skip
    # TD3 delays its actor: the second update steps the critics only
    step_actor = [True, algorithm != "td3"]
    data = [batch(S, seed=i) for i in range(2)]
    outs, wm_outs, group_grads = [], [], []
    for d in data:
        if group.world_model is not None:
            wm_outs.append(group.update_world_model(d))
        outs.append(group.update(d, step_actor[len(outs)]))
        group_grads.append(grads(group.actor_leaves + group.critic_leaves))
    monkeypatch.undo()
    for s, agent in enumerate(singles):
        replay(monkeypatch, agent, rec, s)
        loss = agent.loss
        step = make_agent_step(cfg, loss, agent.optimizers, agent.target_updater)
        for i, d in enumerate(data):
            if agent.world_model_trainer is not None:
                wm = agent.world_model_trainer.update(d[s])
                for key in ("loss_transition", "loss_reward", "loss_termination",
                            "transition_nll", "reward_mse", "termination_accuracy"):  # fmt: skip
                    close(wm[key], wm_outs[i][key][s], f"seed {s} step {i} {key}")
            out = step(d[s].clone(), step_actor[i])
            got = outs[i][s]
            sac = algorithm.endswith("sac")
            qvalue = algorithm == "td3" or sac
            names = {"loss_value": "loss_qvalue" if qvalue else "loss_value"}
            # without an actor step, the separate parts compute no actor loss
            keys = ["loss_value"] + ([] if critic_first and not step_actor[i] else ["loss_actor"])
            if critic_first and not step_actor[i]:  # nor does the group's critics-only step
                assert "loss_actor" not in got
            if sac:  # SACLoss reports its temperature and entropy instead
                keys += ["loss_alpha", "alpha"] + ([] if critic_first else ["entropy"])
            elif not critic_first:  # the separate parts return their losses only
                keys += ["target_value", "pred_value", "state_action_value_actor"]
            for key in keys:
                close(got[key], out[names.get(key, key)], f"seed {s} step {i} {key}")
            if group.expanding:
                diag = loss.value_estimator.diagnostics
                for key in diag.keys():  # noqa: SIM118 (a TensorDict)
                    close(got[key], diag[key], f"seed {s} step {i} {key}")
            # gradients: the group's leaves hold seed s at dim 0
            critics = loss.qvalue_network_params if qvalue else loss.value_network_params
            leaves = [*loss.actor_network_params.values(True, True),
                      *critics.values(True, True)]  # fmt: skip
            single = grads([p for p in leaves if p.requires_grad])  # not the action bounds
            for j, (g_single, g_group) in enumerate(zip(single, group_grads[i], strict=True)):
                close(g_group[s], g_single, f"grad {j}")
        # parameters after both steps (targets, world model and normalisers too): the
        # grouped learner's leaves are views of the group's tensors
        mine, theirs = grouped[s].state_components(), agent.state_components()
        for name in ("loss", "world_model"):
            if name not in theirs:
                continue
            a, b = theirs[name].state_dict(), mine[name].state_dict()
            for key in a:
                close(b[key], a[key], f"seed {s} {name} {key}")


@pytest.mark.parametrize("algorithm", ["ddpg", "rave"])
def test_no_seed_reads_another_seeds_data(algorithm):
    """Changing seed 1's rewards leaves seeds 0 and 2 bit-identical."""
    runs = []
    for scale in (1.0, 1000.0):
        cfg, _ = learner(algorithm, 0)
        agents = [learner(algorithm, s)[1] for s in range(3)]
        group = make_group(agents, cfg)
        torch.manual_seed(7)
        outs = []
        for i in range(3):
            d = batch(3, seed=i)
            d["next", "reward"][1] *= scale
            if group.world_model is not None:
                outs.append(group.update_world_model(d))
            outs.append(group.update(d))
        runs.append((outs, [p.detach().clone() for p in group.actor_leaves + group.critic_leaves]))
    (outs_a, params_a), (outs_b, params_b) = runs
    for a, b in zip(outs_a, outs_b, strict=True):
        for key in a.keys():  # noqa: SIM118 (a TensorDict)
            assert torch.equal(a[key][0], b[key][0]) and torch.equal(a[key][2], b[key][2]), key
            if key in ("loss_value", "loss_reward"):  # seed 1's own numbers did change
                assert not torch.equal(a[key][1], b[key][1]), key
    for a, b in zip(params_a, params_b, strict=True):
        for s in (0, 2):
            assert torch.equal(a[s], b[s])


def test_learners_read_the_group_weights():
    """After an update each learner's own policy acts with the group's new weights."""
    cfg, _ = learner("ddpg", 0)
    agents = [learner("ddpg", s)[1] for s in range(2)]
    group = make_group(agents, cfg)
    obs = torch.randn(2, 4, OBS)
    before = [agents[s].actor(TensorDict(observation=obs[s], batch_size=[4]))["action"]
              for s in range(2)]  # fmt: skip
    group.update(batch(2))
    with torch.no_grad():
        grouped = group._policy(group.actor, obs)
    for s in range(2):
        after = agents[s].actor(TensorDict(observation=obs[s], batch_size=[4]))["action"]
        assert not torch.equal(after, before[s])
        close(after, grouped[s], f"seed {s}")


def test_refuses_mixed_learners():
    cfg, a = learner("steve", 0)
    _, b = learner("rave", 1)
    with pytest.raises(ValueError, match="value estimator"):
        make_group([a, b], cfg)
    with pytest.raises(ValueError, match=r"batches of shape \[1, B\]"):
        make_group([learner("ddpg", 0)[1]], cfg).update(batch(2))


def test_seed_streams_keep_each_seed_apart():
    """Each seed's stream continues where it left off, whatever the others drew meanwhile;
    ``stack`` draws seed by seed under each stream."""
    streams = seed_group.SeedStreams(2)
    with pytest.raises(RuntimeError, match="never captured"):
        streams.use(0).__enter__()
    for i in range(2):
        torch.manual_seed(10 + i)
        streams.capture(i)
    with streams.use(0):
        first = torch.rand(4)
    with streams.use(1):
        other = torch.rand(1000)
    with streams.use(0):
        second = torch.rand(4)
    stacked = streams.stack(lambda i: torch.rand(3))
    torch.manual_seed(10)
    alone = torch.rand(11)
    torch.testing.assert_close(torch.cat([first, second, stacked[0]]), alone, rtol=0, atol=0)
    torch.manual_seed(11)
    alone = torch.rand(1003)
    torch.testing.assert_close(torch.cat([other, stacked[1]]), alone, rtol=0, atol=0)


@pytest.mark.parametrize("algorithm", ["rave", "td3", "sac"])
def test_a_seeds_draws_do_not_depend_on_its_group(algorithm):
    """With streams, seed 1 of a group of three draws what it draws in a group of its own:
    its world-model step and two updates give the same losses, targets and parameters."""
    cfg, _ = learner(algorithm, 0)
    results = []
    for members in ([0, 1, 2], [1]):
        agents = [learner(algorithm, s)[1] for s in members]
        streams = seed_group.SeedStreams(len(members))
        for i, s in enumerate(members):
            torch.manual_seed(1000 + s)
            streams.capture(i)
        group = make_group(agents, cfg, streams=streams)
        torch.manual_seed(5)  # the process stream: no draw of the update reads it
        at = members.index(1)
        outs = []
        for i in range(2):
            d = batch(3, seed=i)[[1] if len(members) == 1 else slice(None)]  # seed 1's rows
            if group.world_model is not None:
                outs.append(group.update_world_model(d)[at])
            outs.append(group.update(d)[at])
        results.append((outs, [p[at].detach().clone() for p in group.actor_leaves +
                               group.critic_leaves]))  # fmt: skip
    (outs_a, params_a), (outs_b, params_b) = results
    for a, b in zip(outs_a, outs_b, strict=True):
        for key in a.keys():  # noqa: SIM118 (a TensorDict)
            close(a[key], b[key], key)
    for a, b in zip(params_a, params_b, strict=True):
        close(a, b, "parameters")
    with pytest.raises(ValueError, match="streams hold 2 seeds"):
        make_group([learner(algorithm, 0)[1]], cfg, streams=seed_group.SeedStreams(2))


@pytest.mark.parametrize("output_major", [True, False])
def test_a_large_layers_owed_bias_is_the_bias_it_left_out(output_major, monkeypatch):
    """Without autograd, a large ReLU layer returns ``max(x w, -b)`` and owes ``b``; the
    next layer takes the owed bias into its own. Against a loop over the matrices of
    ``relu(x w + b)``, layer after layer, for K members of S seeds."""
    monkeypatch.setattr(ensemble, "_LARGE", 0)
    g = torch.Generator().manual_seed(0)
    S, K, R, widths = 2, 3, 7, [5, 6, 6, 2]
    layers, naive = [], []
    for j, (i, o) in enumerate(zip(widths[:-1], widths[1:], strict=True)):
        w = torch.randn(S, K, o, i, generator=g)
        b = torch.randn(S, K, o, generator=g)
        act = torch.nn.ReLU() if j < len(widths) - 2 else None
        if not output_major:  # EnsembleLinear's layout: [..., in, out], bias [..., 1, out]
            w, b = w.mT.contiguous(), b.unsqueeze(-2)
        layers.append(ensemble._Linear(w, b, act, output_major))
        naive.append((w if output_major else w.mT, b.reshape(S, K, o), act))
    x = torch.randn(S, R, widths[0], generator=g)
    want = torch.empty(S, K, R, widths[-1])
    for s in range(S):
        for k in range(K):
            h = x[s]
            for w, b, act in naive:
                h = h @ w[s, k].T + b[s, k]
                h = h if act is None else h.clamp_min(0)
            want[s, k] = h
    with torch.no_grad():
        y, owed = ensemble._run(layers[:2], x, settle=False)
        assert owed is not None and owed.shape == (S * K, 1, widths[2])
        torch.testing.assert_close(y + owed.view(S, K, 1, -1), ensemble._run(layers[:2], x))
        torch.testing.assert_close(ensemble._run(layers, x), want)
    # with autograd the layers add their bias as they go: nothing is owed
    x.requires_grad_(True)
    assert ensemble._run(layers[:2], x, settle=False)[1] is None
    torch.testing.assert_close(ensemble._run(layers, x), want)


def test_without_autograd_a_groups_gaussian_heads_are_one_layer(monkeypatch):
    """In a group of more than one, without autograd, the mean and log-variance heads run
    as one layer of twice the width; the outputs are the two heads' to float rounding."""
    cfg, _ = learner("rave", 0)
    group = make_group([learner("rave", s)[1] for s in range(2)], cfg)
    wm = group.world_model
    x = torch.randn(2, 3, 9, OBS + ACT)  # [S, N, rows, features]
    calls = []
    original = ensemble._Linear.apply

    def counting(layer, *args, **kwargs):
        calls.append(layer.weight.shape[-1])
        return original(layer, *args, **kwargs)

    monkeypatch.setattr(ensemble._Linear, "apply", counting)
    with torch.no_grad():
        fused = wm.transition(x, per_member=True)
    monkeypatch.undo()
    assert calls[-1] == 2 * OBS  # one layer for both heads, of twice the width
    separate = wm.transition(x, per_member=True)  # with autograd: the two heads
    for a, b in zip(fused, separate, strict=True):
        torch.testing.assert_close(a, b.detach())


def transitions(n: int, seed: int) -> TensorDict:
    """``n`` transitions with the entries a collector gives and a group does not read."""
    g = torch.Generator().manual_seed(seed)
    terminated = torch.rand(n, 1, generator=g) < 0.2
    return TensorDict(
        {
            "observation": torch.randn(n, OBS, generator=g),
            "action": torch.rand(n, ACT, generator=g) * 2 - 1,
            "episode_reward": torch.randn(n, 1, generator=g),
            ("next", "observation"): torch.randn(n, OBS, generator=g),
            ("next", "reward"): torch.randn(n, 1, generator=g),
            ("next", "done"): terminated.clone(),
            ("next", "terminated"): terminated,
            ("next", "truncated"): torch.zeros(n, 1, dtype=torch.bool),
        },
        [n],
    )


@pytest.mark.parametrize("path", ["direct", "fallback"])
def test_a_group_sample_is_each_seeds_own_sample(path):
    """``GroupSampler`` gives each seed the rows its own ``rb.sample()`` gives under its
    stream, bit for bit, and leaves every stream where ``rb.sample()`` leaves it; its batch
    holds the entries the group reads. The buffers differ in length, so a seed that drew
    from another's buffer would show. ``fallback``: buffers with a transform, which the
    group samples by ``rb.sample()`` itself."""
    from torchrl.envs.transforms import RenameTransform

    from torchrl_rave.recipe.agent import make_replay_buffer
    from torchrl_rave.recipe.group import GroupSampler

    cfg, _ = learner("rave", 0)
    group = make_group([learner("rave", s)[1] for s in range(3)], cfg,
                       streams=seed_group.SeedStreams(3))  # fmt: skip

    def start():  # fresh buffers, and each stream at its start
        rbs = []
        for i, n in enumerate((40, 90, 300)):
            rb = make_replay_buffer(cfg, "cpu")
            rb.extend(transitions(n, seed=20 + i))
            if path == "fallback":
                rb.append_transform(RenameTransform(["episode_reward"], ["ret"]))
            rbs.append(rb)
        for i in range(3):
            torch.manual_seed(50 + i)
            group.streams.capture(i)
        return rbs

    def probe():  # what each stream draws next
        out = []
        for i in range(3):
            with group.streams.use(i):
                out.append(torch.rand(4))
        return out

    rbs = start()
    sampler = GroupSampler(rbs, group)
    assert (sampler.keys is None) == (path == "fallback")
    got = [sampler() for _ in range(3)]
    next_draws = probe()
    rbs = start()
    keys = group.batch_keys(rbs[0].storage._storage.keys(True, True))
    assert keys == ["observation", "action", ("next", "observation"), ("next", "reward"),
                    ("next", "terminated")]  # fmt: skip
    for step in range(3):
        assert got[step].batch_size == torch.Size([3, cfg.replay_buffer.batch_size])
        if path == "direct":
            assert set(got[step].keys(True, True)) == set(keys)
        for i, rb in enumerate(rbs):
            with group.streams.use(i):
                want = rb.sample()
            for key in keys:
                assert torch.equal(got[step][i].get(key), want.get(key)), (step, i, key)
    for a, b in zip(next_draws, probe(), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("algorithm", ["ddpg", "td3", "rave"])
def test_critic_first_actor_learns_through_the_stepped_critics(algorithm):
    """``optim.critic_first``: the actor's gradient is its loss's gradient through the
    critics after their step, and not the one through the critics before it (what the
    default's single backward pass over the summed losses gives)."""
    # a large critic step, so that the two gradients differ visibly
    cfg, agent = learner(algorithm, 0, "optim.critic_first=true", "optim.lr_critic=0.1")
    loss, data = agent.loss, batch(1)[0]
    actor = [p for p in loss.actor_network_params.values(True, True) if p.requires_grad]
    before = [p.detach().clone() for p in actor]
    actor_loss = loss.actor_loss if algorithm == "td3" else loss.loss_actor

    def actor_grads():
        for p in actor:
            p.grad = None
        actor_loss(data.clone())[0].backward()
        return [p.grad.clone() for p in actor]

    through_old = actor_grads()
    make_agent_step(cfg, loss, agent.optimizers, agent.target_updater)(data.clone(), True)
    got = [p.grad.clone() for p in actor]
    with torch.no_grad():  # the actor as it was, the critics as the step left them
        for p, b in zip(actor, before, strict=True):
            p.copy_(b)
    through_new = actor_grads()
    for g, want in zip(got, through_new, strict=True):
        assert torch.equal(g, want)
    gap = max(float((g - o).abs().max()) for g, o in zip(got, through_old, strict=True))
    scale = max(float(o.abs().max()) for o in through_old)
    assert gap > 1e-2 * scale


@pytest.mark.parametrize("algorithm", ["sac", "rave_sac"])
def test_a_sac_groups_value_target_is_each_sacloss_target(algorithm, monkeypatch):
    """``SeedGroup.value_target`` of a SAC group (without an update) gives each seed the
    target its own ``SACLoss`` computes on its rows, from the same draws: the soft TD(0)
    target, and RAVE's soft value-expansion target."""
    cfg, _ = learner(algorithm, 0)
    singles = [learner(algorithm, s)[1] for s in range(2)]
    rec = Recorder()
    group = make_group([learner(algorithm, s)[1] for s in range(2)], cfg, draw=rec.draw,
                       bootstrap_indices=rec.bootstrap, policy_noise_draw=rec.policy_noise)  # fmt: skip
    d = batch(2, seed=3)
    target, diagnostics = group.value_target(d)
    assert target.shape == (2, B) and bool(diagnostics) == (algorithm == "rave_sac")
    monkeypatch.undo()
    for s, agent in enumerate(singles):
        replay(monkeypatch, agent, rec, s)
        with torch.no_grad():
            single = agent.loss._compute_target_v2(d[s].clone())
        close(target[s], single.squeeze(-1), f"seed {s} target")
        monkeypatch.undo()
