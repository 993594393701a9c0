#!/usr/bin/env bash
# The packages that gpu_check.sh needs beside a GPU machine's own torch, as wheels in .whl/
# (git ignores it), for a machine that cannot reach a package index. Run here, where PyPI
# is reachable, before carrying .whl to that machine. The wheels are for CPython 3.12 on
# x86-64 Linux (PYTHON_VERSION=3.11 for another), the versions this project's venv holds.
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PY:-.venv/bin/python}
PYTHON_VERSION=${PYTHON_VERSION:-3.12}
rm -rf .whl && mkdir -p .whl
platforms=()
for p in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64; do
  platforms+=(--platform "$p")
done
# torch is the machine's own; numpy, cloudpickle, packaging, tqdm and matplotlib are
# assumed there too (they are on the lent NVIDIA machines)
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version "$PYTHON_VERSION" \
  --implementation cp "${platforms[@]}" -d .whl \
  torchrl==0.14.1 tensordict==0.14.3 hoptorch==0.1.4 pyvers==0.2.3 orjson==3.13.0 \
  importlib_metadata==10.2.0 gymnasium==1.4.0 Farama-Notifications==0.0.6 \
  mujoco==4.0.1 mujoco-core==4.0.1 glfw==2.11.0 PyOpenGL==3.1.10 \
  hydra-core==1.3.8 omegaconf==2.3.1
# hydra's parser runtime is published only as a source archive: build its pure-Python wheel
"$PY" -m pip wheel -q --no-deps -w .whl antlr4-python3-runtime==4.9.3
du -sh .whl
