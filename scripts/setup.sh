#!/usr/bin/env bash
# Creates ./.venv and installs torchrl-rave into it with its test extras.
# torch goes in first: a torch already in .venv is left alone; otherwise torch==2.13.0,
# which these machines serve as a CPU wheel from local disk (an open range would pull a
# multi-GB CUDA build). Elsewhere, install the torch build you want into .venv first.
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || python3 -m venv .venv
PY=.venv/bin/python
"$PY" -m pip install -q --upgrade pip >/dev/null 2>&1 || true
"$PY" -c "import torch" 2>/dev/null || "$PY" -m pip install -q torch==2.13.0
"$PY" -m pip install -q -e ".[test]"
echo "torchrl-rave installed in $(pwd)/.venv"
