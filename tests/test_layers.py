"""Imports run one way: the reusable layers never import the application layer, nor a
layer above their own (``trainers``/``transforms`` -> ``objectives`` -> ``modules`` ->
``envs``); every import is found, function-local ones included."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "torchrl_rave"
# a layer may import the layers listed after it (and private helpers such as _checks)
ORDER = ["recipe", "trainers", "transforms", "objectives", "modules", "envs"]
BELOW = {
    "recipe": set(ORDER[1:]),
    "trainers": {"objectives", "modules", "envs"},
    "transforms": {"objectives", "modules", "envs"},
    "objectives": {"modules", "envs"},
    "modules": {"envs"},
    "envs": set(),
}


def imported_layers(path: Path) -> dict[str, int]:
    """``torchrl_rave`` subpackages imported anywhere in ``path`` -> first line."""
    out: dict[str, int] = {}
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for name in names:
            parts = name.split(".")
            if parts[0] == "torchrl_rave" and len(parts) > 1 and parts[1] in BELOW:
                out.setdefault(parts[1], node.lineno)
    return out


@pytest.mark.parametrize("layer", ORDER)
def test_each_layer_imports_only_downward(layer):
    bad = []
    for path in sorted((PACKAGE / layer).rglob("*.py")):
        for other, line in imported_layers(path).items():
            if other != layer and other not in BELOW[layer]:
                bad.append(f"{path.relative_to(PACKAGE)}:{line} imports torchrl_rave.{other}")
    assert bad == []


def test_the_checker_sees_function_local_imports(tmp_path):
    path = tmp_path / "m.py"
    path.write_text("def f():\n    from torchrl_rave.recipe.update import x\n")
    assert imported_layers(path) == {"recipe": 2}


def test_private_helpers_import_no_layer():
    for path in (p for p in PACKAGE.glob("_*.py") if p.name != "__init__.py"):
        assert imported_layers(path) == {}, path
