"""The package stands on its own: a built wheel in a fresh venv, outside the repository,
builds, trains and loads an agent through the library's API and runs its console command;
and the package declares exactly what its modules import."""

from __future__ import annotations

import ast
import importlib.metadata
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from test_recipe import TINY  # budgets where every code path runs

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "torchrl_rave"
# imported only through envs.families' on-demand loader, never by the package's own import
ON_DEMAND = {"envs/learn_to_run.py", "envs/learn_to_move.py"}
# needed at run time without being imported by name (gymnasium's MuJoCo envs load it)
RUNTIME_ONLY = {"mujoco"}


SCRIPT = """
import json, sys, torch
import torchrl_rave
from torchrl_rave.recipe import default_config, load_policy, make_agent, make_env, train

overrides = json.loads(sys.argv[1])
cfg = default_config(*overrides, algorithm="rave", env_name="Hopper-v5")
env = make_env(cfg, "cpu")
agent = make_agent(cfg, env)
final = train(cfg, "run")
policy = load_policy("run")
env.set_seed(0)
with torch.no_grad():
    rollout = env.rollout(5, policy, break_when_any_done=False)
print(json.dumps({
    "package": torchrl_rave.__file__,
    "estimator": type(agent.loss.value_estimator).__name__,
    "frames": final["frames"],
    "actions": list(rollout["action"].shape),
    "finite": bool(torch.isfinite(rollout["action"]).all()),
}))
"""

COMMAND = """
import sys
from importlib.metadata import entry_points
(ep,) = {e.name: e for e in entry_points(group="console_scripts")
         if e.name == "torchrl-rave-train"}.values()
sys.argv = ["torchrl-rave-train", *sys.argv[1:]]
ep.load()()
"""


@pytest.fixture(scope="module")
def fresh_venv(tmp_path_factory):
    """A new venv whose own site-packages holds only the built wheel; the dependencies come
    from this test environment's site-packages (as a path, so its editable install of the
    repository is not activated)."""
    tmp = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         "-w", str(tmp / "dist"), str(ROOT)],
        check=True, capture_output=True,
    )  # fmt: skip
    (wheel,) = (tmp / "dist").glob("torchrl_rave-*.whl")
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    (site,) = venv.glob("lib/python*/site-packages")
    deps = [p for p in sys.path if p.endswith("site-packages")]
    (site / "dependencies.pth").write_text("\n".join(deps) + "\n")
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site),
         str(wheel)],
        check=True, capture_output=True,
    )  # fmt: skip
    work = tmp / "work"  # outside the repository: nothing of it can be imported from here
    work.mkdir()
    return venv / "bin" / "python", site, work, wheel


def run_in(fresh_venv, code: str, *args: str) -> subprocess.CompletedProcess:
    python, _, work, _ = fresh_venv
    env = {"PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1", "HOME": str(work)}
    return subprocess.run([str(python), "-c", code, *args], cwd=work, env=env,
                          capture_output=True, text=True, timeout=600)  # fmt: skip


def test_the_wheel_builds_trains_and_loads_an_agent_outside_the_repository(fresh_venv):
    _, site, work, _ = fresh_venv
    done = run_in(fresh_venv, SCRIPT, json.dumps([*TINY, "collector.total_frames=200"]))
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["package"].startswith(str(site)) and str(ROOT) not in out["package"]
    assert out["estimator"] == "RAVEValueEstimator"
    assert out["frames"] == 200 and out["actions"] == [5, 3] and out["finite"]
    assert (work / "run" / "checkpoints").is_dir()


def test_the_installed_command_runs_and_reports_config_problems(fresh_venv):
    _, _, work, _ = fresh_venv
    bad = run_in(fresh_venv, COMMAND, "collector.total_frames=abc", "optim.gamma=2")
    assert bad.returncode == 1 and "Traceback" not in bad.stderr
    assert bad.stderr.splitlines()[0] == "2 problems in the config:"
    ok = run_in(fresh_venv, COMMAND, "algorithm=ddpg", *TINY, "hydra.run.dir=cmd")
    assert ok.returncode == 0, ok.stderr[-3000:]
    assert (work / "cmd" / "ddpg" / "scalars" / "eval" / "return.csv").exists()


def test_the_wheel_ships_its_data_and_no_logs(fresh_venv):
    import zipfile

    names = zipfile.ZipFile(fresh_venv[3]).namelist()
    for model in ("gait9dof18musc", "gait14dof22musc_20170320", "gait14dof22musc_planar_20170320"):
        assert f"torchrl_rave/envs/assets/{model}.osim" in names
    assert "torchrl_rave/recipe/schema.py" in names
    assert not [n for n in names if n.endswith(".log")]


def test_the_wheel_carries_its_licences_version_and_types(fresh_venv):
    import zipfile

    import torchrl_rave

    wheel = zipfile.ZipFile(fresh_venv[3])
    (metadata,) = [n for n in wheel.namelist() if n.endswith(".dist-info/METADATA")]
    meta = wheel.read(metadata).decode()
    assert f"Version: {torchrl_rave.__version__}\n" in meta
    assert "License-Expression: MIT" in meta
    assert (
        "License-File: LICENSE" in meta and "License-File: torchrl_rave/envs/assets/NOTICE" in meta
    )
    assert "torchrl_rave/py.typed" in wheel.namelist()


def test_the_sdist_holds_the_package_and_no_tests(tmp_path):
    import tarfile

    subprocess.run(
        [sys.executable, "-c", f"from setuptools import build_meta; build_meta.build_sdist({str(tmp_path)!r})"],
        cwd=ROOT, check=True, capture_output=True,
    )  # fmt: skip
    (sdist,) = tmp_path.glob("torchrl_rave-*.tar.gz")
    with tarfile.open(sdist) as archive:
        names = [n.split("/", 1)[1] for n in archive.getnames() if "/" in n]
    assert "pyproject.toml" in names and "LICENSE" in names
    assert "torchrl_rave/recipe/schema.py" in names and "torchrl_rave/envs/assets/NOTICE" in names
    assert not [n for n in names if n.startswith(("tests/", "recipes/", "results/"))]


def _imports(path: Path) -> list[tuple[str, bool]]:
    """``(top-level module, imported at module level)`` of every absolute import."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body} | {
        id(n) for s in tree.body if isinstance(s, ast.If | ast.Try) for n in ast.walk(s)
    }
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        out += [(n.split(".")[0], id(node) in top) for n in names]
    return out


def _requirement_names(specs: list[str]) -> set[str]:
    return {re.split(r"[\[<>=!~ ;]", s, maxsplit=1)[0].lower() for s in specs}


def test_dependencies_are_what_the_package_imports():
    """The components (everything outside ``recipe/``) import only the core dependencies
    at module level; the recipe may import its extra too; optional families anything."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    required = _requirement_names(project["dependencies"])
    recipe = _requirement_names(project["optional-dependencies"]["recipe"])
    extras = set().union(
        *(_requirement_names(v) for v in project["optional-dependencies"].values())
    )
    distributions = importlib.metadata.packages_distributions()
    used, problems = set(), []
    for path in PACKAGE.rglob("*.py"):
        rel = str(path.relative_to(PACKAGE))
        for module, at_top in _imports(path):
            if module in sys.stdlib_module_names or module in ("torchrl_rave", "__future__"):
                continue
            names = {d.lower() for d in distributions.get(module, [module])}
            used |= names
            if at_top and rel not in ON_DEMAND:
                allowed = required | (recipe if rel.startswith("recipe/") else set())
            else:
                allowed = required | extras
            if not names & allowed:
                problems.append(f"{rel} imports {module} ({sorted(names)}), not declared")
    assert problems == []
    # and nothing is declared that no module imports
    assert sorted(required - used) == []
    assert sorted(recipe - used - RUNTIME_ONLY) == []


# A lean install: the recipe's extra is not there. The fresh venv's dependencies come from
# this test environment, so its modules are hidden from the interpreter instead.
LEAN = """
import sys
for name in ("hydra", "omegaconf", "tqdm", "scipy", "mujoco"):
    sys.modules[name] = None  # import raises ModuleNotFoundError, find_spec returns None
"""

COMPONENTS = """
import json, torch
import torchrl_rave
from torchrl_rave import EnsembleDDPGLoss, RAVEValueEstimator, WorldModelEnsemble
from torchrl.modules import MLP, Actor, ValueOperator
from tensordict import TensorDict

actor = Actor(MLP(in_features=3, out_features=1, num_cells=[8]))
critic = ValueOperator(MLP(in_features=4, out_features=1, num_cells=[8]),
                       in_keys=["observation", "action"])
loss = EnsembleDDPGLoss(actor, critic, delay_actor=True, delay_value=True, num_value_nets=2)
wm = WorldModelEnsemble(3, 1, num_models=2)
loss.make_value_estimator(RAVEValueEstimator.for_loss(loss, world_model=wm, gamma=0.99))
B = 5
data = TensorDict(observation=torch.randn(B, 3), action=torch.rand(B, 1),
                  next=TensorDict(observation=torch.randn(B, 3), reward=torch.randn(B, 1),
                                  done=torch.zeros(B, 1, dtype=torch.bool),
                                  terminated=torch.zeros(B, 1, dtype=torch.bool),
                                  batch_size=[B]), batch_size=[B])
wm.update_normalizers_from(data)
out = loss(data)
try:
    import torchrl_rave.recipe
    recipe = "imported"
except ImportError as err:
    recipe = str(err)
print(json.dumps({"finite": bool(torch.isfinite(out["loss_value"])), "recipe": recipe}))
"""


def test_a_lean_install_runs_the_components_and_names_the_recipes_extra(fresh_venv):
    """``pip install torchrl-rave`` without the ``recipe`` extra: the estimator, loss and
    world model work; ``torchrl_rave.recipe`` and ``torchrl-rave-train`` name the extra."""
    _, site, _, _ = fresh_venv
    lean = "import sys; exec(open(sys.argv.pop(1)).read()); "
    blocker = site.parent / "lean_install.py"
    blocker.write_text(LEAN)
    done = run_in(fresh_venv, lean + f"exec({COMPONENTS!r})", str(blocker))
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["finite"]
    assert "pip install 'torchrl-rave[recipe]'" in out["recipe"], out["recipe"]
    command = run_in(fresh_venv, lean + f"exec({COMMAND!r})", str(blocker), "--help")
    assert command.returncode == 1 and "Traceback" not in command.stderr
    assert command.stderr.strip().startswith("torchrl-rave-train: torchrl_rave.recipe needs")
    assert "pip install 'torchrl-rave[recipe]'" in command.stderr
