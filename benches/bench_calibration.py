"""The full TR 38.901 phase-1 calibration (issue #44): UMa at 6 GHz, 50 drops of 570 UEs
through the radio-network plugin, written to docs/results/calibration/UMa-6GHz.{json,png}
with its wall-clock time (about a minute on the 2-core machine). The test
(tests/test_calibration.py) runs 4 drops.

    .venv/bin/python benches/bench_calibration.py [--drops 50] [--scenario UMa] [--carrier 6e9]
"""

from __future__ import annotations

import sys

from caviar_plugins.tools.calibration import main

if __name__ == "__main__":
    argv = sys.argv[1:]
    if "--drops" not in argv:
        argv += ["--drops", "50"]
    sys.exit(main(["38.901", *argv]))
