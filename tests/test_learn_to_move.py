"""The NeurIPS 2019 Learn-to-Move task (``LearnToMove-v0``, ``LearnToMove2D-v0``; the
``osim`` extra): its target-velocity field by hand, the observation layout, seeding, a
footstep's reward by hand, a real fall and the task bonus."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

L = pytest.importorskip("torchrl_rave.envs.learn_to_move", reason="needs the osim extra")
DT = 0.01


@pytest.fixture(scope="module")
def env3d():
    return L.LearnToMoveEnv("3D", difficulty=0)


def test_the_field_at_map_points_and_between_them_by_hand():
    field = L.TargetVelocityField(difficulty=1)
    field.reset(np.random.default_rng(7))
    r, phase = field.sink[0], field.phase
    assert 5 <= r <= 7 and field.sink[1] == 0  # difficulty 1: straight ahead
    # at the walker (a map point) the sink is `span` = r away: the wave at 2 pi, pointing +x
    assert np.allclose(field.velocity([0.0, 0.0]), [1.3 + 0.5 * math.sin(phase), 0.0])
    # 10 m to the left the sink is sqrt(r^2 + 100) > r + 1 away: full speed, towards it
    d = math.hypot(r, 10.0)
    assert np.allclose(field.velocity([0.0, 10.0]), [1.8 * r / d, -1.8 * 10.0 / d])
    # within 1 m of the sink: linear in the distance, 0 at the sink itself
    x = round(r * 2) / 2  # the map point nearest the sink on its axis
    d = abs(x - r)
    slow = d * (1.3 + 0.5 * math.sin(phase + 2 * math.pi / r))
    assert np.allclose(field.velocity([x, 0.0]), [math.copysign(slow, r - x), 0.0])
    # between map points: the mean of the four corners at the centre of a cell
    corners = [field.velocity([a, b]) for a in (1.0, 1.5) for b in (2.0, 2.5)]
    assert np.allclose(field.velocity([1.25, 2.25]), np.mean(corners, 0))
    # off the 40 x 40 m map: its nearest edge value
    assert np.allclose(field.velocity([0.0, 35.0]), field.velocity([0.0, 20.0]))


def test_the_local_field_is_the_global_one_in_the_body_frame():
    field = L.TargetVelocityField(difficulty=1)
    field.reset(np.random.default_rng(7))
    r, s = field.sink[0], 1.3 + 0.5 * math.sin(field.phase)
    local = field.local_field([0.0, 0.0, math.pi / 2])  # facing global +y
    assert local.shape == (2, 11, 11)
    # at the walker the target points along global +x: to the walker's right
    assert np.allclose(local[:, 5, 5], [0.0, -s])
    # 5 m ahead (global (0, 5)): full speed towards (r, 0), seen from the body frame
    d = math.hypot(r, 5.0)
    assert np.allclose(local[:, 10, 5], [1.8 * -5.0 / d, -1.8 * r / d])
    # 5 m to the left, forward offset 0, leftward offset +5: global (-5, 0), behind the sink
    assert np.allclose(local[:, 5, 10], L.rotate(*field.velocity([-5.0, 0.0]), -math.pi / 2))
    # difficulty 0: 1.4 m/s forward everywhere, whatever the yaw
    constant = L.TargetVelocityField(difficulty=0)
    constant.reset(np.random.default_rng(0))
    local = constant.local_field([3.0, 1.0, 0.0])
    assert np.allclose(local[0], 1.4) and np.allclose(local[1], 0.0)


def test_a_target_is_reached_after_its_hold_time_and_the_next_sink_follows():
    field = L.TargetVelocityField(difficulty=3)
    field.reset(np.random.default_rng(1))
    first, hold = field.sink.copy(), field.hold_seconds
    assert 2 <= hold <= 4
    steps = math.floor(hold / DT)
    assert not any(field.update([*first, 0.0]) for _ in range(steps))
    assert field.update([*first, 0.0])  # held for longer than the hold time
    assert field.targets_reached == 1 and 5 <= np.linalg.norm(field.sink - first) <= 7
    # walking away resets the hold: nothing is reached until it has been held again
    field.update([*(field.sink + 1.0), 0.0])
    assert field.targets_reached == 1
    with pytest.raises(ValueError, match="difficulty"):
        L.TargetVelocityField(difficulty=4)


def test_spaces_and_observation_layout(env3d):
    obs, info = env3d.reset(seed=0)
    assert env3d.action_space.shape == (22,) and (env3d.action_space.low == 0).all()
    assert obs.shape == (339,) == env3d.observation_space.shape
    assert {"target_field": slice(0, 242), "body": slice(242, 339)} == L.OBSERVATION_LAYOUT
    assert L.ACTION_MUSCLES[:3] == ("abd_r", "add_r", "iliopsoas_r") and len(L.ACTION_MUSCLES) == 22
    field, body = obs[:242].reshape(2, 11, 11), obs[242:]
    assert np.allclose(field[0], 1.4) and np.allclose(field[1], 0)  # difficulty 0
    assert body[0] == pytest.approx(0.94) == info["pelvis_height"]  # the standing start
    assert (body[1:9] == 0).all()  # level, at rest
    weight = env3d.body_weight
    assert weight == pytest.approx(75.1646 * 9.80665)
    for leg in (9, 53):  # per leg: its ground force, upward, is what the foot presses down
        assert body[leg + 2] == pytest.approx(
            -env3d.foot_force("r" if leg == 9 else "l")[1] / weight
        )
        assert (body[leg + 3 : leg + 11] == 0).all()  # joint angles and rates at the start
        fibres = body[leg + 11 : leg + 44].reshape(11, 3)
        assert (fibres[:, 1] > 0.3).all() and (fibres[:, 1] < 2).all()  # lengths / optimal
    # a step under excitation moves the muscles: forces over their maximum isometric force
    obs, *_ = env3d.step(np.full(22, 0.5))
    assert np.isfinite(obs).all() and (obs[242 + 20 : 242 + 53 : 3] > 0).all()


def test_same_seed_same_start_and_field_and_the_planar_model_stays_planar():
    a, b = (gym.make("LearnToMove2D-v0", difficulty=2) for _ in range(2))
    first = a.reset(seed=3)[0]
    assert np.array_equal(first, b.reset(seed=3)[0])
    assert np.array_equal(a.unwrapped.field.sink, b.unwrapped.field.sink)
    assert not np.array_equal(a.reset(seed=4)[0][:242], first[:242])  # another sink
    full = gym.make("LearnToMove-v0", difficulty=2)
    full.reset(seed=4)
    actions = np.random.default_rng(0).uniform(0, 1, (20, 22))
    for action in actions:
        planar, *_ = a.step(action)
        spatial, *_ = full.step(action)
    # roll, leftward velocity, roll and yaw rates: none in 2D, some in 3D
    out_of_plane = [2, 4, 7, 8]
    assert np.abs(planar[242:][out_of_plane]).max() < 1e-9
    assert np.abs(spatial[242:][out_of_plane]).min() > 1e-6


def test_a_footstep_is_paid_by_hand_from_the_recorded_steps(env3d):
    """The walker dropped from 6 cm: both feet leave the ground, and the landing is a
    footstep. Its three terms are recomputed from the recorded steps."""
    env3d.reset(seed=0)
    env3d.set_coordinates({"pelvis_ty": 1.0})
    activations, velocities, contacts = [], [], []
    rng = np.random.default_rng(0)
    for _ in range(30):
        _, reward, terminated, _, info = env3d.step(rng.uniform(0, 0.2, 22))
        activations.append(env3d.activations())
        velocities.append(env3d.pelvis_velocity())
        contacts.append([env3d.foot_force(s)[1] < -0.05 * env3d.body_weight for s in "rl"])
        terms = info["reward_terms"]
        assert set(terms) == set(L.REWARD_TERMS)
        assert reward == pytest.approx(sum(terms.values())) and not terminated
        if info["footsteps"]:
            break
    assert info["footsteps"] == 1, "no footstep within 30 steps of the drop"
    n = len(activations)
    # a footstep: a foot in contact now that was not in the step before (at reset: standing)
    assert any(contacts[-1]) and (n == 1 or not all(contacts[-2]))
    assert terms["alive"] == 0.1
    assert terms["footstep"] == pytest.approx(10 * n * DT)
    deviation = sum((v - np.array([1.4, 0.0])) * DT for v in velocities)
    assert terms["velocity"] == pytest.approx(-np.linalg.norm(deviation))  # weight 1, round 1
    assert terms["effort"] == pytest.approx(-sum(float(a @ a) for a in activations) * DT)
    assert info["footsteps"] == 1
    # the next footstep counts from here: a new sum
    env3d.set_effort_weight(0.0)
    for _ in range(60):
        _, _, _, _, info = env3d.step(np.zeros(22))
        if info["footsteps"] == 2:
            assert info["reward_terms"]["footstep"] > 0
            assert info["reward_terms"]["effort"] == 0  # weight 0 from now on
            break
    with pytest.raises(ValueError, match="effort_weight"):
        env3d.set_effort_weight(-1.0)


def test_termination_on_a_real_fall(env3d):
    env3d.reset(seed=0)
    heights = []
    for _ in range(300):  # no excitation: the walker folds up
        _, _, terminated, truncated, info = env3d.step(np.zeros(22))
        heights.append(info["pelvis_height"])
        if terminated:
            break
    assert terminated and not truncated
    assert heights[-1] < 0.6 <= min(heights[:-1])  # the first step below 0.6 m ends it
    with pytest.raises(ValueError, match="22 muscle excitations"):
        env3d.step(np.zeros(18))
    with pytest.raises(ValueError, match="non-finite"):
        env3d.step(np.full(22, np.nan))


def test_round_two_pays_the_task_bonus_at_a_reached_target():
    """A placed state: the walker stands at the first sink, whose hold time is cut to one
    step; the next step reaches it and pays 500 (difficulty 3)."""
    env = L.LearnToMoveEnv("3D", difficulty=3)
    env.reset(seed=5)
    assert env.time_limit == 2500 and env.round == 2
    sink = env.field.sink.copy()
    env.set_coordinates({"pelvis_tx": sink[0], "pelvis_tz": -sink[1]})
    assert np.allclose(env.pose()[:2], sink)
    env.field.hold_seconds = 0.5 * DT
    _, reward, _, _, info = env.step(np.zeros(22))
    assert info["reward_terms"]["target"] == 500.0 and info["targets_reached"] == 1
    assert reward == pytest.approx(sum(info["reward_terms"].values()))
    assert np.linalg.norm(env.field.sink - sink) >= 5  # the second sink is in place
    # round 1 has no task bonus
    easy = L.LearnToMoveEnv("3D", difficulty=2)
    easy.reset(seed=5)
    easy.set_coordinates({"pelvis_tx": easy.field.sink[0], "pelvis_tz": -easy.field.sink[1]})
    easy.field.hold_seconds = 0.5 * DT
    _, _, _, _, info = easy.step(np.zeros(22))
    assert info["targets_reached"] == 1 and info["reward_terms"]["target"] == 0


def test_bad_arguments_name_the_problem():
    with pytest.raises(ValueError, match="model must be"):
        L.LearnToMoveEnv("4D")
    with pytest.raises(ValueError, match="difficulty"):
        L.LearnToMoveEnv("2D", difficulty=5)
    with pytest.raises(ValueError, match="time_limit"):
        L.LearnToMoveEnv("2D", time_limit=0)
    with pytest.raises(ValueError, match="speed_range"):
        L.TargetVelocityField(1, speed_range=(2.0, 1.0))


def test_torchrl_env_through_the_recipe_factory():
    import torch
    from test_recipe import make_cfg

    from torchrl_rave.recipe.agent import make_env

    cfg = make_cfg("env.name=LearnToMove2D-v0", "env.kwargs={difficulty:1}")
    env = make_env(cfg, torch.device("cpu"))
    env.set_seed(0)
    rollout = env.rollout(3, break_when_any_done=False)
    assert rollout["next", "observation"].shape == (3, 339)
    assert rollout["next", "observation"].dtype == torch.float32
    assert (rollout["next", "reward"] >= 0.1 - 1e-6).all()  # alive, no footstep yet


@pytest.mark.parametrize("algorithm", ["rave", "sac", "ppo"])
def test_the_recipe_trains_on_learn_to_move(algorithm, tmp_path):
    """A model-based learner, one of TorchRL's losses and the on-policy one (every
    algorithm trains on ``LearnToRun-v0``, the same kind of env)."""
    import rave_mujoco
    from test_recipe import TINY, make_cfg

    cfg = make_cfg(
        *TINY, f"algorithm={algorithm}", "env.name=LearnToMove2D-v0", "collector.total_frames=200",
        "env.kwargs={difficulty:0,time_limit:50}",  # short episodes
        "eval.interval=200", "eval.episodes=1", "world_model.pretrain_frames=100",
        "ppo.rollout_frames=100", "ppo.minibatch_size=50", "ppo.epochs=1",
    )  # fmt: skip
    results = rave_mujoco.train(cfg, str(tmp_path))
    assert results["frames"] == 200 and results["updates"] > 0
    assert results["eval/return"] >= 0.1 and results["eval/falling_rate"] in (0.0, 1.0)


def test_the_time_limit_pays_round_one_and_asks_round_two_for_footsteps():
    easy = L.LearnToMoveEnv("2D", difficulty=0, time_limit=5)
    easy.reset(seed=0)
    for step in range(1, 6):
        _, reward, terminated, truncated, info = easy.step(np.zeros(22))
        assert truncated == (step == 5) and not terminated
    assert info["success"] and info["footsteps"] == 0  # standing: no footstep
    # the unfinished step's time (5 steps since the start) and the success bonus
    assert info["reward_terms"]["footstep"] == pytest.approx(10 * 5 * DT)
    assert info["reward_terms"]["success"] == 10.0
    assert reward == pytest.approx(0.1 + 0.5 + 10.0)  # no velocity or effort term then
    hard = L.LearnToMoveEnv("2D", difficulty=3, time_limit=5)
    hard.reset(seed=0)
    for _ in range(5):
        _, reward, _, truncated, info = hard.step(np.zeros(22))
    # round 2 succeeds only after more than 5 footsteps: nothing beyond the alive bonus
    assert truncated and not info["success"] and reward == pytest.approx(0.1)


def test_distillation_noises_the_range_the_task_can_produce_at_the_stage_speed(tmp_path):
    """On the planar task at difficulty 0 the target field is one constant: in the pairs
    its range is about 0, so noise over that range is none and the "distillation" plain
    behaviour cloning (refused, named). The env's own target part is noised over every
    value the task can produce at the stage the run reached (2.5 m/s here, the
    curriculum's first stage), and the pairs are collected at that speed."""
    import rave_mujoco
    from test_recipe import TINY, make_cfg

    from torchrl_rave.recipe.distill import distill_run

    assert L.LearnToMoveEnv("2D", difficulty=0, constant_speed=2.5).target_range == (-2.5, 2.5)
    assert L.LearnToMoveEnv("2D", difficulty=1).target_range == (-1.8, 1.8)
    run = tmp_path / "run"
    cfg = make_cfg(
        *TINY, "algorithm=ddpg", "env.name=LearnToMove2D-v0", "collector.total_frames=100",
        "env.kwargs={difficulty:0,time_limit:20}", "eval.interval=100", "eval.episodes=1",
        "curriculum.kwarg=constant_speed", "curriculum.stages=[2.5,1.4]",
        "curriculum.thresholds=[1e9]",
    )  # fmt: skip
    rave_mujoco.train(cfg, str(run))
    result = distill_run(run, tmp_path / "out", frames=40, steps=5)
    assert result["collected_with"] == {"difficulty": 0, "time_limit": 20, "constant_speed": 2.5}
    assert result["noise"] == [-2.5, 2.5] and result["target"] == [0, 242]
    from torchrl_rave.recipe.checkpoint import saved_config

    assert saved_config(tmp_path / "out").env.kwargs.constant_speed == 2.5  # recorded
    with pytest.raises(ValueError, match="take one value in the 40 pairs"):
        distill_run(run, tmp_path / "degenerate", slice(0, 242), frames=40, steps=5)


def test_grader_scoring_pays_footsteps_a_step_late_and_round_one_its_bonus_alone():
    """``scoring="grader"`` by hand from the recorded contacts: osim-rl scores a step
    before it updates the contacts, so a footstep that lands in step t is paid in step
    t + 1, with 10 x the time since the last paid one; osim-rl 3.0.6's fresh env starts
    with no contact (the standing start is a footstep), and its time limit pays 10 alone."""
    env = L.LearnToMoveEnv("2D", difficulty=0, time_limit=60, scoring="grader",
                           integrator_accuracy=1e-3)  # fmt: skip
    assert L.LearnToMoveEnv("2D", scoring="grader").integrator_accuracy == 5e-5
    env.reset(seed=0)
    assert [e.getValue() for e in env._excitations] == [1.0] * 22  # a fresh osim-rl env's
    rng = np.random.default_rng(0)
    contact, late, since, paid = {"r": False, "l": False}, False, 0.0, []
    for t in range(60):
        _, _, terminated, truncated, info = env.step(rng.uniform(0, 0.3, 22))
        since += DT
        expected = 10 * since if late else 0.0
        if late:
            since = 0.0
        now = {s: env.foot_force(s)[1] < -0.05 * env.body_weight for s in ("r", "l")}
        late = any(now[s] and not contact[s] for s in now)
        contact = now
        terms = info["reward_terms"]
        assert terms["footstep"] == pytest.approx(expected, abs=1e-12), t
        paid.append(expected > 0)
        if terminated:
            break
    assert paid[1]  # the standing start, detected in the first step, paid in the second
    assert truncated and terms["success"] == 10.0  # no unfinished step's term beside it
    with pytest.raises(ValueError, match="scoring must be one of"):
        L.LearnToMoveEnv("2D", scoring="osim")
