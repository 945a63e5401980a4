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

# Sionna RT runs on Dr.Jit; without a GPU it uses the LLVM backend, which needs
# libLLVM >= 16 (Debian bookworm's default LLVM 14 fails). caviar_plugins.radio
# finds it; DRJIT_LIBLLVM_PATH overrides.
if ! ls /usr/lib/*-linux-gnu/libLLVM.so.19* >/dev/null 2>&1; then
    if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
        log "system packages (libllvm19 for Dr.Jit)"
        apt-get update -qq
        DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null
    else
        echo "warning: install libLLVM >= 16 (Debian: apt-get install libllvm19) for Sionna RT on CPU" >&2
    fi
fi

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    log "creating .venv with $($PYTHON --version)"
    "$PYTHON" -m venv .venv
fi

log "Python packages"
.venv/bin/pip install --quiet --upgrade pip maturin
# Builds the Rust extension caviar._core (release) and installs caviar in editable mode.
.venv/bin/pip install --quiet -e ".[test,ml,docs]"
.venv/bin/pip install --quiet -e "plugins[radio,onnx,osm,traffic,network,live]"
# The `deepmimo` extra (caviar-core export deepmimo): deepmimo 4.x pins numpy<2.3, which would
# downgrade numpy under sionna and torch; it runs on theirs (tests/test_deepmimo.py), so it is
# installed without its dependencies, and those numpy aside here.
.venv/bin/pip install --quiet "tqdm>=4.59" requests "matplotlib>=3.8.2" "scipy>=1.6.2"
.venv/bin/pip install --quiet --no-deps "deepmimo>=4,<5"
# The `yolo` extra (training the person detector): Ultralytics needs torchvision, whose newest
# release would replace the torch Sionna SYS brought; held at that torch.
torch_pin=$(.venv/bin/python -c 'import torch; print(torch.__version__.split("+")[0])')
.venv/bin/pip install --quiet -e "plugins[yolo]" -c <(echo "torch==$torch_pin")
# The `ns3` extra (the ns3-network plugin): ns-3 3.44 with cppyy bindings, about 2.5 min.
.venv/bin/pip install --quiet -e "plugins[ns3]"

# The browser view: its bundle ships built; chromium (apt) and playwright for its tests.
bash scripts/setup-view.sh

# Lint for the Rust side (scripts/test.sh runs cargo clippy -D warnings).
if ! cargo clippy --version >/dev/null 2>&1 && command -v rustup >/dev/null 2>&1; then
    log "clippy"
    rustup component add clippy
fi

log "ready: $(.venv/bin/caviar-core --version)"
