"""Optional environment families: the gymnasium ids a module registers when imported.

The Roboschool tasks of the paper live on as the PyBullet ports of
``pybullet-envs-gymnasium`` (the ``bullet`` extra); the osim-rl tasks are
:mod:`torchrl_rave.envs.learn_to_run` (2017) and :mod:`torchrl_rave.envs.learn_to_move` (2019), on the ``opensim`` package (the ``osim`` extra).
Their ids are registered only once that module is imported; :func:`import_env_family`
does that for an id of a family, in the learner and in every collector worker that
builds the env.
"""

from __future__ import annotations

import importlib

__all__ = ["BULLET_IDS", "OSIM_IDS", "import_env_family"]

# The paper's Roboschool tasks, as PyBullet ports (pybullet-envs-gymnasium 0.6.0)
BULLET_IDS = (
    "HopperBulletEnv-v0",
    "Walker2DBulletEnv-v0",
    "HalfCheetahBulletEnv-v0",
    "AntBulletEnv-v0",
    "HumanoidBulletEnv-v0",
    "HumanoidFlagrunBulletEnv-v0",
    "HumanoidFlagrunHarderBulletEnv-v0",
)
# the 2017 Learning-to-Run task (NIPS 2017 challenge) and the 2019 Learn-to-Move task
# (NeurIPS 2019), 3D and planar, on OpenSim 4.6
OSIM_IDS = ("LearnToRun-v0", "LearnToMove-v0", "LearnToMove2D-v0")
# id suffix -> (module that registers the family, package it needs, extra that installs it)
_FAMILIES = {
    "BulletEnv-v0": ("pybullet_envs_gymnasium", "pybullet-envs-gymnasium", "bullet"),
    "LearnToRun-v0": ("torchrl_rave.envs.learn_to_run", "opensim", "osim"),
    "LearnToMove-v0": ("torchrl_rave.envs.learn_to_move", "opensim", "osim"),
    "LearnToMove2D-v0": ("torchrl_rave.envs.learn_to_move", "opensim", "osim"),
}


def import_env_family(env_id: str) -> None:
    """Imports the module that registers ``env_id`` when it belongs to an optional family
    (ids ending in ``BulletEnv-v0``; ``LearnToRun-v0``, ``LearnToMove-v0`` and
    ``LearnToMove2D-v0``); a missing package is named
    with the extra to install.

    Examples:
        >>> import_env_family("Hopper-v5")  # MuJoCo ids need nothing
    """
    for suffix, (module, package, extra) in _FAMILIES.items():
        if env_id.endswith(suffix):
            try:
                importlib.import_module(module)
            except ImportError as err:
                raise ImportError(
                    f"{env_id!r} needs the {package!r} package, which is not installed "
                    f"({err}): pip install 'torchrl-rave[{extra}]'"
                ) from err
