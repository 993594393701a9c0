"""The ``torchrl-rave-train`` console command's entry point: the recipe behind it needs the
``recipe`` extra, and without it the command says so (the message of
:mod:`torchrl_rave.recipe._requires`) instead of ending in a traceback."""

from __future__ import annotations


def main() -> None:
    try:
        from torchrl_rave.recipe.cli import main as recipe_main
    except ImportError as err:
        if "torchrl-rave[recipe]" not in str(err):
            raise
        raise SystemExit(f"torchrl-rave-train: {err}") from None
    recipe_main()
