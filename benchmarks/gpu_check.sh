#!/usr/bin/env bash
# The GPU check of Ev-Net training (docs/training.md#the-gpu-check): one epoch on simulated
# scenes on the CUDA GPU (mixed precision), samples/s, and the loss against a float32 CPU run on
# the same batches. Needs a machine with one CUDA GPU and a CUDA build of torch; a few minutes
# there, bounded by a 5-minute timeout. Without a GPU it says so and exits 3.
# Usage: benchmarks/gpu_check.sh [options of benchmarks/gpu_check.py]
#   PYTHON=/path/to/python benchmarks/gpu_check.sh   (default: .venv/bin/python, else python3)
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -z "${PYTHON:-}" ]; then
    if [ -x .venv/bin/python ]; then PYTHON=.venv/bin/python; else PYTHON=python3; fi
fi
export PYTHONPATH="src${PYTHONPATH:+:$PYTHONPATH}"
exec timeout 300 "$PYTHON" benchmarks/gpu_check.py "$@"
