#!/usr/bin/env bash
# Fuzzes the parsers for longer than the test command does (issue #28) and writes what
# ran to docs/results/reliability.json ("fuzz"): the Rust targets (tests/fuzz.rs: wire
# frames, topic matcher, config loader with --set, run-directory reader) for SECONDS
# each on fresh seeds, then the Python run reader (tests/test_fuzz_rundir.py) with
# EXAMPLES hypothesis examples per target.
#
#   bash scripts/fuzz.sh            # 120 s per Rust target, 2000 Python examples
#   bash scripts/fuzz.sh 600 10000
set -euo pipefail
cd "$(dirname "$0")/.."
seconds=${1:-120}
examples=${2:-2000}
report=$(mktemp)
trap 'rm -f "$report"' EXIT
CAVIAR_FUZZ_SECONDS=$seconds CAVIAR_FUZZ_REPORT=$report \
    cargo test --release --locked --test fuzz -- --nocapture --test-threads 1
CAVIAR_FUZZ_EXAMPLES=$examples CAVIAR_FUZZ_REPORT=$report \
    .venv/bin/python -m pytest -q tests/test_fuzz_rundir.py
.venv/bin/python - "$report" "$seconds" "$examples" <<'PY'
import json, os, pathlib, platform, sys
report, seconds, examples = pathlib.Path(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
rows = [json.loads(line) for line in report.read_text().splitlines() if line.strip()]
out = pathlib.Path("docs/results/reliability.json")
data = json.loads(out.read_text()) if out.exists() else {}
data["fuzz"] = {
    "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
    "rust_seconds_per_target": seconds, "python_examples_per_target": examples,
    "cases": sum(r["cases"] for r in rows), "failures": sum(r.get("failures", 0) for r in rows),
    "targets": rows,
}
out.write_text(json.dumps(data, indent=1) + "\n")
print(json.dumps({k: v for k, v in data["fuzz"].items() if k != "targets"}))
PY
