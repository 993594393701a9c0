#!/usr/bin/env bash
# The packages that gpu_check.sh needs beside a GPU machine's own torch, as wheels in .whl/
# (git ignores it), for a machine that cannot reach a package index. Run here, where PyPI
# is reachable, before carrying .whl to that machine. The wheels are for CPython 3.12 on
# x86-64 Linux (PYTHON_VERSION=3.11 for another), at the versions this project's venv
# holds, so that the GPU machine runs what the tests here ran.
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PY:-.venv/bin/python}
PYTHON_VERSION=${PYTHON_VERSION:-3.12}
# torch is the machine's own; numpy, cloudpickle, packaging, tqdm and matplotlib are
# assumed there too (they are on the lent NVIDIA machines)
mapfile -t pins < <("$PY" - <<'PYEOF'
from importlib.metadata import PackageNotFoundError, version

names = ["torchrl", "tensordict", "hoptorch", "pyvers", "orjson", "importlib_metadata",
         "gymnasium", "Farama-Notifications", "mujoco", "mujoco-core", "glfw", "PyOpenGL",
         "hydra-core", "omegaconf", "antlr4-python3-runtime"]
for name in names:
    try:
        print(f"{name}=={version(name)}")
    except PackageNotFoundError:  # e.g. mujoco-core, split from mujoco in 4.0
        pass
PYEOF
)
binary=() source=()
for pin in "${pins[@]}"; do
  # hydra's parser runtime is published only as a source archive: its wheel is built here
  if [[ $pin == antlr4-python3-runtime==* ]]; then source+=("$pin"); else binary+=("$pin"); fi
done
rm -rf .whl && mkdir -p .whl
platforms=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64; do
  platforms+=(--platform "$p")
done
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version "$PYTHON_VERSION" \
  --implementation cp "${platforms[@]}" -d .whl "${binary[@]}"
"$PY" -m pip wheel -q --no-deps -w .whl "${source[@]}"
printf '%s\n' "${pins[@]}"
du -sh .whl
