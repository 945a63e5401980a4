#!/usr/bin/env bash
# Runs every test: the Rust core (cargo test) and the Python side (pytest).
set -euo pipefail
cd "$(dirname "$0")/.."

cargo test --workspace --locked
.venv/bin/python -m pytest -q "$@"
