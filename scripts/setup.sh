#!/usr/bin/env bash
# Sets up a fresh machine for CAVIAR: system packages, the Rust core, and a Python
# virtual environment (.venv) with the caviar package and its plugins.
# Idempotent: run it again after pulling.
set -euo pipefail
cd "$(dirname "$0")/.."

log() { printf '\n== %s\n' "$*"; }

if ! command -v cargo >/dev/null 2>&1; then
    echo "error: cargo not found; install Rust (https://rustup.rs) and run this again" >&2
    exit 1
fi

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    log "creating .venv with $($PYTHON --version)"
    "$PYTHON" -m venv .venv
fi

log "Python packages"
.venv/bin/pip install --quiet --upgrade pip maturin
# Builds the Rust extension caviar._core (release) and installs caviar in editable mode.
.venv/bin/pip install --quiet -e ".[test]"
.venv/bin/pip install --quiet -e plugins

log "ready: $(.venv/bin/caviar-core --version)"
