"""The recipe's command line: ``torchrl-rave-train`` (installed with the package) and
``python recipes/rave_mujoco.py`` both run one hydra job of
:func:`~torchrl_rave.recipe.loop.train`.

``torchrl-rave-train env.name=Hopper-v5 algorithm=steve`` composes the shipped schema and
presets (:mod:`~torchrl_rave.recipe.schema`); the repository's script composes its
``recipes/config.yaml``, which selects the same. Config problems, unknown keys among them,
are printed together, without a traceback, before anything is built.
"""

from __future__ import annotations

import sys

import hydra
from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from torchrl_rave.recipe.checkpoint import config_for_resume
from torchrl_rave.recipe.config import ConfigError, check_command_line, override_keys
from torchrl_rave.recipe.loop import train
from torchrl_rave.recipe.schema import defaults, help_text, with_algorithm_preset

__all__ = ["exit_on_bad_command_line", "main", "run_job"]

# the installed command's primary config: what recipes/config.yaml selects
ConfigStore.instance().store(
    name="torchrl_rave_train", node={"defaults": ["rave_recipe", {"preset": "cpu"}, "_self_"]}
)


def exit_on_bad_command_line(argv: list[str], command: str = "torchrl-rave-train") -> None:
    """Exits with every problem of the command line's overrides in one message (hydra
    itself would stop at the first unknown key, with a traceback hint). ``--help`` (or
    ``-h``) prints every key with its default, rule and help line, and exits."""
    if "--help" in argv or "-h" in argv:
        print(help_text(command), end="")
        raise SystemExit(0)
    overrides = [a for a in argv if not a.startswith("-")]  # hydra's flags (-m, --cfg, ...)
    try:
        check_command_line(overrides)
    except ConfigError as err:
        raise SystemExit(f"{err}") from None


def run_job(cfg: DictConfig) -> float:
    """One hydra job: train (or, with ``resume=``, continue) into hydra's run directory;
    returns the final evaluation return (NaN when a stop came before the first evaluation:
    a clean stop, exit code 0). A config problem, or a ``resume=`` path with no run to
    continue, or a run directory that holds a run already, exits with its message only."""
    run_dir = HydraConfig.get().runtime.output_dir
    try:
        overrides = list(HydraConfig.get().overrides.task)
        if "resume" in override_keys(overrides) and not cfg.resume:
            raise ConfigError([
                f"resume={cfg.resume!r}: resume= takes the run directory to continue "
                "(resume=outputs/<date>/<time>); leave it out to start a new run"
            ])  # fmt: skip
        if cfg.resume:
            try:
                cfg = config_for_resume(cfg.resume, overrides, defaults())
            except FileNotFoundError as err:  # no run there: the message names the path
                raise SystemExit(f"resume={cfg.resume}: {err}") from None
        else:  # the preset's values for the algorithm, under the command line's
            preset = HydraConfig.get().runtime.choices.get("preset", "cpu")
            cfg = with_algorithm_preset(cfg, preset, override_keys(overrides))
        return train(cfg, run_dir).get("eval/return", float("nan"))
    except (ConfigError, FileExistsError) as err:  # the message says it all
        raise SystemExit(f"{err}") from None


@hydra.main(config_path=None, config_name="torchrl_rave_train", version_base="1.3")
def _main(cfg: DictConfig) -> float:
    return run_job(cfg)


def main() -> None:
    """The ``torchrl-rave-train`` console command."""
    exit_on_bad_command_line(sys.argv[1:])
    _main()
