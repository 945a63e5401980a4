#!/usr/bin/env bash
# Runs every check: format, lint and types (rustfmt, clippy, ruff, mypy), the documentation site (mkdocs, warnings
# are errors), then the tests of the Rust core
# (cargo test) and of the Python side (pytest on every core, including the view in headless chromium).
set -euo pipefail
cd "$(dirname "$0")/.."

log() { printf '\n== %s\n' "$*"; }

log "cargo fmt --check"
cargo fmt --all --check
log "cargo clippy (warnings are errors)"
cargo clippy --workspace --all-targets --locked -- -D warnings
log "ruff"
.venv/bin/ruff check python plugins tests benches blueprints examples
log "mypy"
.venv/bin/mypy
log "docs (mkdocs build --strict)"
# Warnings are errors (not --quiet: it hides them from --strict too); the site goes to a scratch folder.
NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict --site-dir "${TMPDIR:-/tmp}/caviar-site"
log "cargo test"
cargo test --workspace --locked
# One pytest worker per core (pytest-xdist), at most one per 4 GiB of memory (a worker imports torch and
# Sionna and runs whole simulations); PYTEST_WORKERS=1 runs the suite in one process.
cores=$(nproc)
mem_gib=$(awk '/MemTotal/ {print int($2 / 1048576)}' /proc/meminfo)
workers=${PYTEST_WORKERS:-$(( cores < mem_gib / 4 ? cores : mem_gib / 4 ))}
[ "$workers" -ge 1 ] || workers=1
log "pytest ($workers workers)"
if [ "$workers" = 1 ]; then
    .venv/bin/python -m pytest -q "$@"
else
    # Each worker's OpenMP (torch, numpy's BLAS) gets its share of the cores: with a pool of one
    # thread a core in every worker, OpenMP's threads wait for cores the other workers hold (the
    # 03-gymnasium notebook took 77 s beside one busy process instead of 13 s, and ran past its limit).
    OMP_NUM_THREADS=${OMP_NUM_THREADS:-$(( cores / workers > 1 ? cores / workers : 1 ))} \
        .venv/bin/python -m pytest -q -n "$workers" "$@"
fi
