#!/usr/bin/env bash
# Sets up a fresh machine for CAVIAR: system packages, the Rust core, and a Python
# virtual environment (.venv) with the caviar package and its plugins, every Python package at
# its version in requirements.lock (scripts/lock.sh makes it from requirements.in).
# Idempotent: run it again after pulling.
#
# What can run side by side does: apt in the background; the Rust extension's release build
# (pip, editable) in the background while uv installs the lock, downloading in parallel. Each
# phase prints when it starts ([seconds since the start]); docs/getting-started.md says where
# the time goes.
set -euo pipefail
cd "$(dirname "$0")/.."

log() { printf '\n== %s [%s s]\n' "$*" "$SECONDS"; }

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
# background LOG COMMAND...: runs COMMAND in the background (its pid in $!), its output to LOG,
# which ends with when it ran and the processor time it took.
background() {
    local out=$1; shift
    (
        t0=$SECONDS rc=0
        "$@" || rc=$?
        times >"$out.times"  # not in $(...): that would be another process's
        { read -r _; read -r user system; } <"$out.times"
        echo "from $t0 s to $SECONDS s (processor time: user $user, system $system)"
        exit "$rc"
    ) >"$out" 2>&1 &
}
# finish PID LOG NAME: waits for a background job; its output when it failed.
finish() {
    if wait "$1"; then
        log "$3 done, $(tail -n 1 "$2")"
    else
        cat "$2" >&2
        echo "error: $3 failed (above)" >&2
        exit 1
    fi
}

if ! command -v cargo >/dev/null 2>&1; then
    echo "error: cargo not found; install Rust (https://rustup.rs) and run this again" >&2
    exit 1
fi

# System packages, in the background. Sionna RT runs on Dr.Jit; without a GPU it uses the
# LLVM backend, which needs libLLVM >= 16 (Debian bookworm's default LLVM 14 fails);
# caviar_plugins.radio finds it, DRJIT_LIBLLVM_PATH overrides. chromium: the browser view's tests
# (scripts/setup-view.sh, run after this, installs it when run alone).
apt_pkgs=()
ls /usr/lib/*-linux-gnu/libLLVM.so.19* >/dev/null 2>&1 || apt_pkgs+=(libllvm19)
command -v chromium >/dev/null 2>&1 || apt_pkgs+=(chromium)
apt_pid=
if [ ${#apt_pkgs[@]} -gt 0 ]; then
    if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
        log "system packages, in the background: ${apt_pkgs[*]} (apt-get)"
        apt_install() { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@"; }
        background "$work/apt.log" apt_install "${apt_pkgs[@]}"
        apt_pid=$!
    elif [[ " ${apt_pkgs[*]} " == *" libllvm19 "* ]]; then
        echo "warning: install libLLVM >= 16 (Debian: apt-get install libllvm19) for Sionna RT on CPU" >&2
    fi
fi

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    log "creating .venv with $($PYTHON --version)"
    "$PYTHON" -m venv .venv
fi
# The lock holds for the Python it was made for and later patch releases of it; any other
# Python resolves requirements.in afresh (same packages, perhaps other versions).
locked=$(sed -n '1s/^# python: \([0-9.]*\).*/\1/p' requirements.lock)
use_lock=$(.venv/bin/python -c 'import sys; l = tuple(map(int, sys.argv[1].split(".")))
print(int(sys.version_info[:2] == l[:2] and sys.version_info[:3] >= l))' "$locked")

# A package's entry in the lock: its pin and hashes.
pinned() {
    for p in "$@"; do
        awk -v p="$p==" 'index($0, p) == 1 {on = 1} on {print; if ($0 !~ /\\$/) exit}' requirements.lock
    done
}
log "pip, uv and maturin (pip, at their versions in requirements.lock)"
.venv/bin/pip install --quiet --no-deps --require-hashes -r <(pinned pip uv maturin)
uv_install() { .venv/bin/uv pip install --python .venv/bin/python --quiet "$@"; }

if [ "$use_lock" = 1 ]; then
    # caviar in editable mode, its Rust extension caviar._core built in release mode by maturin:
    # pip, beside uv (uv holds the environment while it works); the lock has its dependencies.
    log "the Rust core, in the background: caviar (editable; caviar._core built by maturin, release)"
    # (maturin's build backend runs the `maturin` on PATH.)
    background "$work/rust.log" env PATH="$PWD/.venv/bin:$PATH" \
        .venv/bin/pip install --quiet --no-deps --no-build-isolation -e .
    rust_pid=$!
    log "Python packages: requirements.lock (uv, $(grep -c '^[a-z0-9]' requirements.lock) packages)"
    background "$work/uv.log" uv_install --no-deps --require-hashes -r requirements.lock
    finish $! "$work/uv.log" "Python packages"
    finish "$rust_pid" "$work/rust.log" "the Rust core"
    log "the plugins (editable)"
    uv_install --no-deps --no-build-isolation -e ./plugins
else
    echo "warning: requirements.lock is for Python $locked; .venv has $(.venv/bin/python --version):" \
         "resolving requirements.in instead" >&2
    log "Python packages: requirements.in (uv), caviar's Rust extension built in release mode"
    uv_install -r requirements.in
    uv_install --no-deps "deepmimo>=4,<5"
fi
# uv puts a package's C headers under its normalized name; cppyy (the ns3 extra) looks for
# CPyCppyy's where pip puts them, and warns without them.
inc=.venv/include/site/python$(.venv/bin/python -c 'import sys; print("%d.%d" % sys.version_info[:2])')
if [ -d "$inc/cpycppyy" ] && [ ! -e "$inc/CPyCppyy" ]; then
    ln -s cpycppyy "$inc/CPyCppyy"
fi

if [ -n "$apt_pid" ]; then
    finish "$apt_pid" "$work/apt.log" "system packages"
fi
# The browser view: its bundle ships built; chromium (apt) and playwright for its tests.
bash scripts/setup-view.sh

# Lint for the Rust side (scripts/test.sh runs cargo clippy -D warnings).
if ! cargo clippy --version >/dev/null 2>&1 && command -v rustup >/dev/null 2>&1; then
    log "clippy"
    rustup component add clippy
fi

log "ready: $(.venv/bin/caviar-core --version)"
