#!/usr/bin/env bash
# The GPU benchmarks in one go, each step under its own time limit, results into OUT (default
# benchmarks/results/gpu_run): work-precision on XLA's default settings and with while loops kept
# on the device (CUDA graphs with conditional nodes: XLA's command buffers for WHILE and
# CONDITIONAL), then batch size, chunk size and the closed form's bandwidth, then the fast tests.
#
#   bash benchmarks/gpu_run.sh [OUT]
set -u
OUT=${1:-${OUT:-benchmarks/results/gpu_run}}
mkdir -p "$OUT"
LOG="$OUT/gpu_run.log"
export PYTHONPATH=".:${PYTHONPATH:-}" PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
GRAPHS="--xla_gpu_enable_command_buffer=+WHILE,+CONDITIONAL"
WP_ONLY=fast,balanced,precise,exact,dopri8,vmap
{
  date -u
  nvidia-smi -L 2>&1 | head -2
  python3 -c "import jax, diffrax, equinox, optax, numpy; print('jax', jax.__version__, 'diffrax', \
diffrax.__version__, 'equinox', equinox.__version__, 'optax', optax.__version__, 'numpy', \
numpy.__version__, jax.devices())"
  echo "== work_precision, XLA defaults"
  timeout 150 python3 benchmarks/work_precision.py --n 10000 --no-readme --no-plot --only "$WP_ONLY" \
    --out-prefix "$OUT/work_precision.gpu_h200"
  echo "== work_precision, XLA_FLAGS=$GRAPHS"
  XLA_FLAGS="$GRAPHS" timeout 150 python3 benchmarks/work_precision.py --n 10000 --no-readme --no-plot \
    --only "$WP_ONLY" --out-prefix "$OUT/work_precision.gpu_h200_graphs"
  echo "== accelerator, XLA defaults"
  timeout 170 python3 benchmarks/accelerator.py --sizes 10000,1000000 --chunks "" \
    --out "$OUT/accelerator.gpu_h200.json"
  echo "== fast tests"
  RIGIDJAX_TEST_XLA_DEFAULTS=1 timeout 45 python3 -m pytest -q -o addopts="-ra" -p no:cacheprovider \
    -n 8 -m "not slow" tests/test_simulate.py tests/test_torque_free.py
  date -u
} 2>&1 | tee "$LOG"
