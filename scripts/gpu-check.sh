#!/usr/bin/env bash
# The prepared GPU check of issue 22 (scripts/gpu_check.py: gsplat vs the CPU splatter, training
# throughput of the residual network and of the paper preset, a short paper-preset run). Run from
# the repository root on a CUDA machine with the project installed; `--dry-run` checks it on a CPU.
# Results: OUT/gpu_check.json (default OUT: ${OUT:-/tmp}/gpu_check); copy the numbers to docs/train.md.
set -euo pipefail
out="${OUT:-/tmp}/gpu_check"
python="${PYTHON:-python3}"
PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" exec "$python" scripts/gpu_check.py --out "$out" "$@"
