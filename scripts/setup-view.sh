#!/usr/bin/env bash
# Sets up `caviar-core view` (the browser view of a run) and its tests. Idempotent.
#
# The page's bundle (python/caviar/view/static/: view.js, three.js and the page minified by
# esbuild from web/, with index.html, style.css and THIRD-PARTY.txt) is committed built, beside
# its sources. Why: so that setting up (and CI) needs no node, no npm and no npm registry, and
# spends no time on `npm ci` (the bundle changes only when web/ does). The cost is 540 kB of
# generated JavaScript in git, which could drift from web/: BUILT-FROM.sha256 beside it records
# the hashes of web/'s sources and of the bundle at its last build, and tests/test_docs.py
# fails when either changed since. After editing web/, rebuild and commit both:
#     bash scripts/setup-view.sh --build --no-browser
# (`npm run build` in web/ alone leaves the record stale.) This script:
#   * rebuilds the bundle from web/ (npm ci + npm run build) and writes BUILT-FROM.sha256 when
#     the bundle is missing or with --build (needs node >= 18 and npm; packages from the npm
#     registry);
#   * for the browser tests: Debian's chromium (apt, when root) and playwright (pip, into
#     the virtual environment; playwright's own browser download is not used).
# Usage: scripts/setup-view.sh [--build] [--no-browser]
set -euo pipefail
cd "$(dirname "$0")/.."

log() { printf '\n== %s\n' "$*"; }
BUILD=0
BROWSER=1
for a in "$@"; do
    case "$a" in
        --build) BUILD=1 ;;
        --no-browser) BROWSER=0 ;;
        *) echo "usage: $0 [--build] [--no-browser]" >&2; exit 2 ;;
    esac
done
PY=${PYTHON:-.venv/bin/python}  # the project's virtual environment (scripts/setup.sh makes it)

if [ "$BUILD" = 1 ] || [ ! -f python/caviar/view/static/view.js ]; then
    if ! command -v npm >/dev/null 2>&1; then
        echo "error: npm not found; install Node.js >= 18 (Debian: apt-get install nodejs npm) to build the view" >&2
        exit 1
    fi
    log "view front-end: npm ci && npm run build (web/ -> python/caviar/view/static/)"
    (cd web && npm ci --no-audit --no-fund && npm run build)
    STATIC=python/caviar/view/static
    # sha256sum's own format: `sha256sum -c --quiet $STATIC/BUILT-FROM.sha256` checks it too.
    files=$( { printf '%s\n' web/build.mjs web/package.json web/package-lock.json
               { find web/src -type f; find "$STATIC" -maxdepth 1 -type f ! -name BUILT-FROM.sha256; } \
                   | LC_ALL=C sort; } )
    # shellcheck disable=SC2086  # one path a line, none with spaces
    sha256sum $files > "$STATIC/BUILT-FROM.sha256"
fi

if [ "$BROWSER" = 1 ]; then
    if ! command -v chromium >/dev/null 2>&1; then
        if command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
            log "chromium (Debian) for the view's browser tests"
            apt-get update -qq
            DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
        else
            echo "warning: no chromium; the view's browser tests will be skipped (Debian: apt-get install chromium)" >&2
        fi
    fi
    if [ ! -x "$PY" ]; then
        echo "warning: $PY not found: run scripts/setup.sh first (or set PYTHON) to install playwright" >&2
    elif ! "$PY" -c "import playwright" >/dev/null 2>&1; then
        log "playwright (Python) for the view's browser tests"
        "$PY" -m pip install --quiet playwright
    fi
fi
log "view ready: caviar-core view RUN_DIR"
