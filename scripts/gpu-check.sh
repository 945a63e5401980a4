#!/usr/bin/env bash
# One command that checks a GPU machine (issue #39): every blueprint for a few steps, then the
# timing items; one table, and docs/results/gpu.json with the device named
# (scripts/gpu_check.py says what it runs). Run it first and last whenever a session is lent a
# GPU. The interpreter: $CAVIAR_PYTHON, else this checkout's .venv, else python3 (the GPU
# machine's, with the packages of docs/tutorials/gpu-machine.md on its path).
set -euo pipefail
cd "$(dirname "$0")/.."
py="${CAVIAR_PYTHON:-}"
if [ -z "$py" ]; then
  if [ -x .venv/bin/python ]; then py=.venv/bin/python; else py=python3; fi
fi
export MPLBACKEND=Agg
exec "$py" scripts/gpu_check.py "$@"
