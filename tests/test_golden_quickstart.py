"""The quickstart records the same messages, byte for byte, as the reference recording.

``tests/data/quickstart-messages.jsonl.gz`` was recorded by the code before the layout
change of issue 12 (commit 147b824). A refactoring that changes what is recorded (a topic,
a payload byte, an order, a time stamp) fails here and names the first differing message.
Regenerate the reference only for an intended change of the quickstart's messages:

    python tests/test_golden_quickstart.py --write
"""

from __future__ import annotations

import base64
import gzip
import json
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "tests" / "data" / "quickstart-messages.jsonl.gz"
COLUMNS = ("step", "time", "seq", "source", "topic", "kind", "text", "meta", "data")


def _cli() -> str:
    return str(pathlib.Path(sys.executable).with_name("caviar-core"))


def record_quickstart(out_dir: pathlib.Path) -> list[str]:
    """Runs the quickstart blueprint into ``out_dir``; its messages as canonical lines."""
    import pyarrow.parquet as pq

    run_dir = out_dir / "quickstart"
    p = subprocess.run([_cli(), "run", str(ROOT / "blueprints" / "quickstart" / "config.toml"), "--quiet",
                        "--out", str(run_dir)], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    single = run_dir / "messages.parquet"
    parts = [single] if single.exists() else sorted((run_dir / "messages").glob("*.parquet"))
    rows = []
    for part in parts:
        rows.extend(pq.read_table(part).to_pylist())
    rows.sort(key=lambda r: (r["step"], r["seq"]))
    lines = []
    for r in rows:
        rec = {c: r[c] for c in COLUMNS}
        rec["time"] = float(rec["time"]).hex()  # every bit of the time stamp
        if rec["data"] is not None:
            rec["data"] = base64.b64encode(rec["data"]).decode()
        lines.append(json.dumps(rec, sort_keys=True))
    return lines


def test_quickstart_records_the_reference_messages(tmp_path):
    expected = gzip.decompress(GOLDEN.read_bytes()).decode().splitlines()
    got = record_quickstart(tmp_path)
    for i, (e, g) in enumerate(zip(expected, got, strict=False)):
        assert g == e, f"message {i} differs from the reference:\n  expected {e}\n  got      {g}"
    assert len(got) == len(expected), f"{len(got)} messages recorded, the reference has {len(expected)}"


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        lines = record_quickstart(pathlib.Path(d))
    GOLDEN.write_bytes(gzip.compress(("\n".join(lines) + "\n").encode(), mtime=0))
    print(f"{GOLDEN}: {len(lines)} messages")
