"""Imported first by :mod:`torchrl_rave.recipe`: on a lean install (``pip install
torchrl-rave``, the components only) it names the extra the recipe needs, instead of
the first import that fails."""

from __future__ import annotations

import importlib.util

#: what the recipe imports beyond the components' dependencies (the ``recipe`` extra)
RECIPE_MODULES = ("hydra", "omegaconf", "tqdm", "scipy")

_missing = [m for m in RECIPE_MODULES if importlib.util.find_spec(m) is None]
if _missing:
    raise ImportError(
        f"torchrl_rave.recipe needs the recipe's dependencies ({', '.join(_missing)} not "
        "installed): pip install 'torchrl-rave[recipe]'",
        name=_missing[0],
    )
