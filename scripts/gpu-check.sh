#!/usr/bin/env bash
# One command that checks a GPU machine (issue #39): every blueprint for a few steps, then the
# timing items; one table, and docs/results/gpu.json with the device named
# (scripts/gpu_check.py says what it runs). Run it first and last whenever a session is lent a
# GPU. The interpreter: $CAVIAR_PYTHON, else this checkout's .venv, else python3 (the GPU
# machine's) with gpu-env.tar.xz (scripts/gpu-pack.sh) unpacked onto its path.
set -euo pipefail
cd "$(dirname "$0")/.."
py="${CAVIAR_PYTHON:-}"
if [ -z "$py" ] && [ -x .venv/bin/python ]; then
  py=.venv/bin/python
elif [ -z "$py" ]; then
  # The lent GPU machine: its python3 and what scripts/gpu-pack.sh packed (carried as
  # gpu-env.tar.xz), unpacked once per machine.
  py=python3
  if [ -f gpu-env.tar.xz ]; then
    env_dir="${TMPDIR:-/tmp}/caviar-gpu-env-$(stat -c %Y gpu-env.tar.xz)"
    if [ ! -d "$env_dir/site" ]; then
      mkdir -p "$env_dir" && xz -dc gpu-env.tar.xz | tar -C "$env_dir" -xf -
    fi
    export PYTHONPATH="$env_dir/site${PYTHONPATH:+:$PYTHONPATH}"
  fi
fi
export MPLBACKEND=Agg
exec "$py" scripts/gpu_check.py "$@"
