#!/usr/bin/env bash
# The GPU figures of benchmarks/README.md and the CUDA tests (tests/test_cuda.py), in one
# call on a lent NVIDIA machine whose python3 holds a CUDA build of torch:
#
#   bash benchmarks/device/fetch_wheels.sh      # first, where PyPI is reachable: .whl/
#   bash benchmarks/device/gpu_check.sh         # there, with .whl carried beside the tree
#
# Writes to $OUT (default benchmarks/device/out): machine.txt (GPU, driver, versions),
# update_throughput_<device>.json and seed_group_<device>.json with their logs, and
# test_cuda.log. Each step has its own time limit (T_UPDATE, T_GROUP, T_TESTS seconds)
# so that the whole fits one 10-minute call; a step that runs out is cut and the next
# one runs. UPDATE_ARGS, GROUP_ARGS and TEST_ARGS replace each step's arguments;
# DEVICE=cpu runs the same steps on the CPU (a check of this script).
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-benchmarks/device/out}
DEVICE=${DEVICE:-cuda}
PY=${PY:-python3}
mkdir -p "$OUT"
WHEELS=${WHEELS:-.whl}  # WHEELS=none: use the packages python already has
if [ -d "$WHEELS" ]; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site "$WHEELS"/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
export PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1

{
  date -u
  nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv 2>&1
  "$PY" -c 'import platform, torch, torchrl, tensordict, gymnasium, mujoco
print("python", platform.python_version(), "torch", torch.__version__,
      "cuda", torch.version.cuda, "available", torch.cuda.is_available())
print("torchrl", torchrl.__version__, "tensordict", tensordict.__version__,
      "gymnasium", gymnasium.__version__, "mujoco", mujoco.__version__)
print("cpu", platform.processor() or platform.machine(), __import__("os").cpu_count(), "cores")'
  git log -1 --format='commit %H' 2>/dev/null
} > "$OUT/machine.txt" 2>&1
cat "$OUT/machine.txt"

step() {  # step NAME SECONDS COMMAND...: run with a time limit, log to $OUT/NAME.log
  local name=$1 limit=$2
  shift 2
  echo "== $name (at most $limit s): $*"
  timeout "$limit" "$@" 2>&1 | tee "$OUT/$name.log"
  echo "== $name: exit ${PIPESTATUS[0]}"
}

read -ra update_args <<< "${UPDATE_ARGS:---seconds 1 --paper-batches 3}"
read -ra group_args <<< "${GROUP_ARGS:---threads 1 --seconds 1}"
read -ra test_args <<< "${TEST_ARGS:--m gpu -n 0 -q -p no:cacheprovider tests/test_cuda.py}"
step update_throughput "${T_UPDATE:-240}" "$PY" benchmarks/update_throughput.py \
  --device "$DEVICE" "${update_args[@]}" --json "$OUT/update_throughput_$DEVICE.json"
step seed_group "${T_GROUP:-150}" "$PY" benchmarks/seed_group.py \
  --device "$DEVICE" "${group_args[@]}" --out "$OUT/seed_group_$DEVICE.json"
step test_cuda "${T_TESTS:-150}" "$PY" -m pytest "${test_args[@]}"
