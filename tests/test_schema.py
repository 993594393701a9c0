"""recipe.schema and recipe.config: the shipped schema is the recipe's config, and every
config problem is reported at once, without a traceback, before any work."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf
from test_recipe import make_cfg

from torchrl_rave.recipe.config import ConfigError, check_command_line, check_config
from torchrl_rave.recipe.schema import PRESETS, default_config, schema_fields

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "rave_mujoco.py"


class TestSchema:
    def test_config_yaml_only_selects_the_schema(self):
        for preset in PRESETS:
            composed = OmegaConf.to_container(make_cfg(f"preset={preset}"))
            assert composed == OmegaConf.to_container(default_config(preset=preset))

    def test_every_key_has_help_and_is_a_key_of_the_recipe(self):
        keys = dict(schema_fields())
        for key, f in keys.items():
            assert f.metadata.get("help"), key

        def leaves(node, prefix=""):
            for k, v in node.items():
                if isinstance(v, dict) and f"{prefix}{k}" not in keys:
                    yield from leaves(v, f"{prefix}{k}.")
                else:
                    yield f"{prefix}{k}"

        assert sorted(leaves(OmegaConf.to_container(make_cfg()))) == sorted(keys)
        assert len(keys) == 88  # 77, six reward.*, four curriculum.* and seeds

    def test_defaults_pass_their_own_checks(self):
        for preset in PRESETS:
            for algorithm in ("ddpg", "rave", "td3", "sac", "ppo"):
                check_config(default_config(preset=preset, algorithm=algorithm))

    def test_paper_preset_sizes_come_from_the_module_table(self):
        from torchrl_rave.modules.world_model import WORLD_MODEL_SIZES
        from torchrl_rave.recipe.config import world_model_sizes

        cfg = default_config(preset="paper")
        assert world_model_sizes(cfg) == WORLD_MODEL_SIZES["paper"]
        wider = default_config("world_model.transition_cells=32", preset="paper")
        assert world_model_sizes(wider) == {**WORLD_MODEL_SIZES["paper"], "transition_cells": 32}


class TestMujocoPreset:
    """``preset=mujoco``: the field's sizes, each learner with its own published settings."""

    def test_each_learner_gets_its_own_settings(self):
        common = {"network.actor_cells": 256, "network.critic_cells": 256,
                  "network.num_layers": 3, "replay_buffer.batch_size": 256,
                  "world_model.size": "mujoco"}  # fmt: skip
        own = {  # CleanRL's single-file scripts: SAC's critic and temperature rates, 5k
            # start; TD3 (alone) steps its critics first (docs/results/critic_first100k.md)
            "ddpg": {"optim.lr_critic": 3e-4, "optim.lr_alpha": 3e-4,
                     "collector.init_random_frames": 25_000, "optim.critic_first": False},
            "td3": {"optim.lr_critic": 3e-4, "collector.init_random_frames": 25_000,
                    "optim.critic_first": True},
            "rave": {"optim.lr_critic": 3e-4, "collector.init_random_frames": 25_000,
                     "optim.critic_first": False},
            "sac": {"optim.lr_critic": 1e-3, "optim.lr_alpha": 1e-3,
                    "collector.init_random_frames": 5_000, "optim.critic_first": False},
        }  # fmt: skip
        for algorithm, values in own.items():
            cfg = default_config(preset="mujoco", algorithm=algorithm)
            for key, value in {**common, **values}.items():
                assert OmegaConf.select(cfg, key) == value, (algorithm, key)
        assert default_config(preset="mujoco", algorithm="ppo").network.actor_cells == 64
        # the CPU preset keeps one backward pass for every learner
        assert default_config(algorithm="td3").optim.critic_first is False

    def test_the_command_line_wins_over_the_algorithms_own_values(self):
        cfg = default_config("algorithm=sac", "optim.lr_critic=5e-4", preset="mujoco")
        assert (cfg.optim.lr_critic, cfg.optim.lr_alpha) == (5e-4, 1e-3)

    def test_the_recipe_applies_them_under_its_command_line(self, tmp_path):
        """The hydra path: the run's saved config has SAC's own values where the command
        line gave none, and the command line's where it did."""
        done = subprocess.run(
            [sys.executable, str(RECIPE), "preset=mujoco", "algorithm=sac",
             "collector.total_frames=300", "replay_buffer.batch_size=64", "eval.episodes=1",
             "optim.lr_alpha=2e-3", "logger.progress_bar=false", "threads=1",
             f"hydra.run.dir={tmp_path}"],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr[-2000:]
        from torchrl_rave.recipe.checkpoint import RunCheckpoint

        saved = OmegaConf.create(RunCheckpoint(tmp_path).config())
        assert saved.optim.lr_critic == 1e-3 and saved.optim.lr_alpha == 2e-3
        assert saved.collector.init_random_frames == 5_000
        assert saved.replay_buffer.batch_size == 64 and saved.network.actor_cells == 256


class TestAllProblemsAtOnce:
    def test_types_ranges_cross_key_rules_and_unknown_keys_together(self):
        cfg = make_cfg("collector.frames_per_batch=20000", "optim.gamma=1.5",
                       "compile.enabled=maybe", "env.action_noise=-1")  # fmt: skip
        OmegaConf.set_struct(cfg, False)
        cfg.estimator.hoirzon = 3
        with pytest.raises(ConfigError) as caught:
            check_config(cfg)
        assert sorted(caught.value.problems) == sorted([
            "config key optim.gamma=1.5 is invalid: expected in [0, 1]",
            "config key compile.enabled='maybe' is invalid: expected true or false",
            "config key env.action_noise=-1 is invalid: expected a finite number >= 0",
            "config key estimator.hoirzon is not a key of the recipe; did you mean "
            "estimator.horizon? (--help lists every key)",
            "config key collector.frames_per_batch=20000 is invalid: expected <= "
            "collector.total_frames (15000)",
        ])  # fmt: skip
        assert str(caught.value).startswith("5 problems in the config:\n  ")

    def test_a_value_that_converts_is_converted(self):
        cfg = make_cfg("collector.total_frames='2000'", "optim.gamma=1")
        check_config(cfg)
        assert cfg.collector.total_frames == 2000 and isinstance(cfg.optim.gamma, float)

    @pytest.mark.parametrize(
        "override, problem",
        [
            ("optim.lr_actor=inf", "optim.lr_actor=inf is invalid: expected a finite number > 0"),
            ("env.reward_scale=inf", "env.reward_scale=inf is invalid"),
            ("exploration.sigma=inf", "exploration.sigma=inf is invalid"),
            ("world_model.lr=abc", "world_model.lr='abc' is invalid: expected a value of type float"),
            ("world_model.reward_layers=1", "world_model.reward_layers=1 is invalid: expected an integer >= 2"),
            ("network.default_policy_scale=0.005", "network.default_policy_scale=0.005 is invalid: expected > 0.01"),
            ("network.scale_lb=0", "network.scale_lb=0 is invalid: expected a finite number > 0"),
        ],
    )  # fmt: skip
    def test_values_that_cannot_work_are_named(self, override, problem):
        with pytest.raises(ConfigError, match=problem.replace("[", r"\[")):
            check_config(make_cfg(override))

    @pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="a CUDA device is here")
    def test_cuda_on_a_torch_without_it_is_named(self):
        with pytest.raises(
            ConfigError, match="collector.device='cuda': this torch has no usable CUDA"
        ):
            check_config(make_cfg("collector.device=cuda"))
        with pytest.raises(ConfigError, match="collector.device='gpu'"):
            check_config(make_cfg("collector.device=gpu"))

    def test_command_line_names_unknown_keys_beside_bad_values(self):
        with pytest.raises(ConfigError) as caught:
            check_command_line(["collector.total_frames=abc", "optim.gamma=1.5",
                                "estimator.hoirzon=3", "hydra.run.dir=x", "preset=paper"])  # fmt: skip
        assert len(caught.value.problems) == 3
        check_command_line(["env.name=Hopper-v5", "ray.worker_resources.actors=1"])  # fine

    def test_command_line_with_a_sweep(self):
        # a -m sweep's values are hydra's to expand; its key and every other override are
        # still checked (before: a ValidationError traceback about "Set[str]", and with -m
        # on the command line nothing was checked at all)
        from torchrl_rave.recipe.cli import exit_on_bad_command_line

        check_command_line(["algorithm=ddpg,td3", "env.seed=range(0,3)"])  # fine
        with pytest.raises(ConfigError, match="estimator.hoirzon is not a key"):
            check_command_line(["estimator.hoirzon=1,2"])
        with pytest.raises(SystemExit, match=r"optim.gamma=1.5 is invalid"):
            exit_on_bad_command_line(["-m", "algorithm=ddpg,td3", "optim.gamma=1.5"])

    def test_command_line_seed_group_with_env_seed_is_named(self):
        # the group seeds each run from seeds=; a given env.seed would be silently ignored
        with pytest.raises(ConfigError, match=r"seeds=\[0, 1\] and env.seed=3 are both given"):
            check_command_line(["seeds=[0,1]", "env.seed=3"])
        check_command_line(["seeds=[0,1]"])  # fine
        check_command_line(["seeds=null", "env.seed=3"])  # fine: one run

    def test_three_bad_keys_one_message_no_traceback_no_work(self, tmp_path):
        run = tmp_path / "run"
        done = subprocess.run(
            [sys.executable, str(RECIPE), "collector.total_frames=abc", "optim.gamma=1.5",
             "estimator.hoirzon=3", f"hydra.run.dir={run}"],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 1
        assert "Traceback" not in done.stderr + done.stdout
        assert done.stderr.strip().splitlines() == [
            "3 problems in the config:",
            "  config key estimator.hoirzon is not a key of the recipe; did you mean "
            "estimator.horizon? (--help lists every key)",
            "  config key collector.total_frames='abc' is invalid: expected a value of type int",
            "  config key optim.gamma=1.5 is invalid: expected in [0, 1]",
        ]
        assert not run.exists()  # nothing was built or written

    def test_help_lists_every_key_with_its_default_rule_and_help(self):
        """``--help`` listed the keys without the help strings the schema holds; an
        unknown key now names the nearest known one (``optim.batch_size``)."""
        from torchrl_rave.recipe.schema import schema_fields

        done = subprocess.run([sys.executable, str(RECIPE), "--help"], capture_output=True,
                              text=True, timeout=300)  # fmt: skip
        assert done.returncode == 0
        lines = done.stdout.splitlines()
        for name, f in schema_fields():
            (at,) = [i for i, line in enumerate(lines) if line.startswith(f"  {name}=")]
            assert lines[at + 1].split() == f.metadata["help"].replace("`", "").split()
        assert "  replay_buffer.batch_size=128   (an integer >= 1)" in lines
        with pytest.raises(ConfigError, match="optim.batch_size is not a key of the recipe; "
                           "did you mean replay_buffer.batch_size"):  # fmt: skip
            check_command_line(["optim.batch_size=256"])

    def test_a_resume_path_with_no_run_is_named(self, tmp_path):
        """A missing path, a directory with no checkpoint and a run's checkpoints/ folder
        are each named; on the command line in one line, without a traceback."""
        from torchrl_rave.recipe.checkpoint import config_for_resume

        run, missing, empty = tmp_path / "run", tmp_path / "missing", tmp_path / "empty"
        (run / "checkpoints" / "checkpoint-000000000200").mkdir(parents=True)
        empty.mkdir()
        cases = {
            missing: f"{missing} does not exist: expected a run directory",
            empty: f"no checkpoint under {empty / 'checkpoints'}",
            run / "checkpoints": f"{run / 'checkpoints'} is a run's checkpoints folder: pass "
            f"the run directory that holds it, {run}",
        }
        for path, problem in cases.items():
            with pytest.raises(FileNotFoundError) as caught:
                config_for_resume(path, [f"resume={path}"])
            assert str(caught.value) == problem
        done = subprocess.run(
            [sys.executable, str(RECIPE), f"resume={missing}", f"hydra.run.dir={tmp_path / 'h'}"],
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 1
        assert "Traceback" not in done.stderr + done.stdout
        assert done.stderr.strip().splitlines()[-1] == f"resume={missing}: {cases[missing]}"
