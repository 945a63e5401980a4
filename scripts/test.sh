#!/usr/bin/env bash
# Runs every check: lint and types (clippy, ruff, mypy), then the tests of the Rust core
# (cargo test) and of the Python side (pytest, including the view in headless chromium).
set -euo pipefail
cd "$(dirname "$0")/.."

log() { printf '\n== %s\n' "$*"; }

log "cargo clippy (warnings are errors)"
cargo clippy --workspace --all-targets --locked -- -D warnings
log "ruff"
.venv/bin/ruff check python plugins tests benches blueprints examples
log "mypy"
.venv/bin/mypy
log "cargo test"
cargo test --workspace --locked
log "pytest"
.venv/bin/python -m pytest -q "$@"
