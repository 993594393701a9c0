"""The application layer's modules import one way too: no import circle among
``torchrl_rave/recipe/`` modules, and no import of one of them placed inside a function
(where it would hide a circle from this test and from the reader)."""

from __future__ import annotations

import ast
from pathlib import Path

RECIPE = Path(__file__).resolve().parents[1] / "torchrl_rave" / "recipe"
PACKAGE = "torchrl_rave.recipe"


def recipe_imports(path: Path, modules: set[str]) -> list[tuple[str, int, bool]]:
    """``(module, line, local)`` for every import of a ``torchrl_rave.recipe`` module in
    ``path``; ``local``: inside a function. ``from torchrl_rave.recipe import x`` imports
    the module ``x`` where there is one, else the package (``__init__``)."""
    out = []

    def visit(node: ast.AST, local: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = local or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            names = []
            if isinstance(child, ast.Import):
                names = [a.name for a in child.names]
            elif isinstance(child, ast.ImportFrom) and child.module and child.level == 0:
                if child.module == PACKAGE:
                    names = [f"{PACKAGE}.{a.name}" for a in child.names]
                else:
                    names = [child.module]
            for name in names:
                if name == PACKAGE or name.startswith(PACKAGE + "."):
                    module = name[len(PACKAGE) + 1 :].split(".")[0] or "__init__"
                    out.append((module if module in modules else "__init__", child.lineno, local))
            visit(child, inner)

    visit(ast.parse(path.read_text()), False)
    return out


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every circle of ``graph`` found by a depth-first walk (each as the path that closes
    it); empty for a graph without one."""
    found, state = [], {}

    def walk(node: str, path: list[str]) -> None:
        state[node] = "open"
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                found.append(path[path.index(nxt) :] + [nxt])
            elif nxt not in state:
                walk(nxt, [*path, nxt])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            walk(node, [node])
    return found


def graph_and_local_imports() -> tuple[dict[str, set[str]], list[str]]:
    modules = {p.stem for p in RECIPE.glob("*.py")}
    graph, local = {}, []
    for path in sorted(RECIPE.glob("*.py")):
        graph[path.stem] = set()
        for module, line, inside in recipe_imports(path, modules):
            if inside:
                local.append(f"{path.name}:{line} imports {PACKAGE}.{module} inside a function")
            elif module != path.stem:
                graph[path.stem].add(module)
    return graph, local


def test_no_import_circle_among_the_recipe_modules():
    graph, _ = graph_and_local_imports()
    assert circles(graph) == []


def test_no_recipe_module_is_imported_inside_a_function():
    _, local = graph_and_local_imports()
    assert local == []


def test_the_checks_see_a_circle_and_a_function_local_import(tmp_path):
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c", "a"]]
    assert circles({"a": {"b"}, "b": {"c"}, "d": {"a", "c"}}) == []
    path = tmp_path / "m.py"
    path.write_text(
        "from torchrl_rave.recipe.config import ConfigError\n"
        "def f():\n    from torchrl_rave.recipe import loop\n"
    )
    assert recipe_imports(path, {"config", "loop"}) == [("config", 1, False), ("loop", 3, True)]
