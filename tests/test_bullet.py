"""The paper's Roboschool-class tasks as PyBullet ids (the ``bullet`` extra)."""

from __future__ import annotations

import numpy as np
import pytest
import rave_mujoco
import torch
from test_recipe import TINY, make_cfg

from torchrl_rave.envs import BULLET_IDS, import_env_family
from torchrl_rave.recipe.agent import make_env

ALL_ALGORITHMS = ["ddpg", "mve", "steve", "rave", "rave_constant", "td3", "sac", "ppo"]


@pytest.mark.parametrize("env_id", BULLET_IDS)
def test_each_bullet_id_builds_and_steps(env_id):
    env = make_env(make_cfg(f"env.name={env_id}"), torch.device("cpu"))
    try:
        env.set_seed(0)
        rollout = env.rollout(20, break_when_any_done=False)
    finally:
        env.close()
    assert rollout.batch_size == torch.Size([20])
    obs = rollout["next", "observation"]
    assert obs.dtype == torch.float32 and torch.isfinite(obs).all()
    low, high = env.action_spec.space.low, env.action_spec.space.high
    assert (rollout["action"] >= low).all() and (rollout["action"] <= high).all()
    # the random actions moved the body: not a frozen simulation
    assert not torch.equal(obs[0], obs[-1])


@pytest.mark.parametrize("algorithm", ALL_ALGORITHMS)
def test_every_algorithm_trains_on_a_bullet_task(algorithm, tmp_path):
    extra = ["ppo.rollout_frames=100", "ppo.minibatch_size=50", "ppo.epochs=1"]
    cfg = make_cfg(
        *TINY, f"algorithm={algorithm}", "env.name=HopperBulletEnv-v0", "collector.total_frames=300",
        "eval.interval=300", "eval.episodes=1", *extra,
    )  # fmt: skip
    results = rave_mujoco.train(cfg, str(tmp_path))
    assert results["frames"] == 300 and results["updates"] > 0
    assert np.isfinite(results["eval/return"])


def test_a_misspelt_id_lists_the_bullet_ids_too(tmp_path):
    with pytest.raises(ValueError, match="(?s)not a registered gymnasium id.*HopperBulletEnv-v0"):
        rave_mujoco.train(make_cfg(*TINY, "env.name=HoperBulletEnv-v1"), str(tmp_path))


def test_a_bullet_id_without_the_package_names_the_extra(hide_modules, tmp_path):
    hide_modules("pybullet_envs_gymnasium")
    with pytest.raises(ImportError, match=r"pip install 'torchrl-rave\[bullet\]'"):
        import_env_family("Walker2DBulletEnv-v0")
    cfg = make_cfg(*TINY, "env.name=Walker2DBulletEnv-v0")
    with pytest.raises(ValueError, match=r"env.name='Walker2DBulletEnv-v0'.*\[bullet\]"):
        rave_mujoco.train(cfg, str(tmp_path))
