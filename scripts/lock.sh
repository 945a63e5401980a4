#!/usr/bin/env bash
# Resolves requirements.in into requirements.lock: exact versions with their hashes, for one
# Python (the venv's, or LOCK_PYTHON_VERSION) on x86_64 Linux (manylinux_2_28 and newer).
# scripts/setup.sh installs that lock as it is. Run this after changing requirements.in or an
# extra in pyproject.toml / plugins/pyproject.toml; it keeps the versions already in the lock
# where they still fit. `bash scripts/lock.sh --upgrade` (or --upgrade-package NAME) moves them
# to the newest. Then run scripts/setup.sh and the tests, and commit both files.
set -euo pipefail
cd "$(dirname "$0")/.."

UV=${UV:-.venv/bin/uv}
if [ ! -x "$UV" ]; then
    echo "error: $UV not found: run scripts/setup.sh first (or set UV)" >&2
    exit 1
fi
PYVER=${LOCK_PYTHON_VERSION:-$(.venv/bin/python -c 'import platform; print(platform.python_version())')}
LOCK=requirements.lock
common=(--python-version "$PYVER" --python-platform x86_64-manylinux_2_28 --generate-hashes --quiet)

# deepmimo stays at its pin unless asked to move (any argument: --upgrade, --upgrade-package).
deepmimo_spec='deepmimo>=4,<5'
if [ $# = 0 ] && grep -q '^deepmimo==' "$LOCK" 2>/dev/null; then
    deepmimo_spec=$(grep -o '^deepmimo==[^ ]*' "$LOCK")
fi
# uv reads the pins already in the output file as preferences, so it resolves into the lock itself.
touch "$LOCK"
"$UV" pip compile requirements.in "${common[@]}" --output-file "$LOCK" \
    --no-emit-package caviar --no-emit-package caviar-plugins \
    --custom-compile-command "bash scripts/lock.sh" "$@"
body=$(cat "$LOCK")
deepmimo=$(echo "$deepmimo_spec" | "$UV" pip compile - "${common[@]}" --no-deps --no-header)
major_minor=${PYVER%.*}
{
    echo "# python: $PYVER (scripts/setup.sh installs this lock into a .venv of Python $PYVER or a later"
    echo "# $major_minor; any other Python resolves requirements.in afresh)"
    echo "$body"
    echo "# deepmimo, without its dependencies (requirements.in says why; setup installs the whole lock"
    echo "# with --no-deps)"
    echo "$deepmimo"
} > "$LOCK.tmp"
mv "$LOCK.tmp" "$LOCK"
echo "requirements.lock: $(grep -c '^[a-z0-9]' "$LOCK") packages for Python $PYVER"
