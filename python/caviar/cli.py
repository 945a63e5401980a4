"""Console entry point of ``caviar-core`` / ``caviar``: the command line is the core's
(Rust); ``report``, which draws figures with matplotlib, is the Python side's."""

from __future__ import annotations

import sys


def main() -> None:
    argv = list(sys.argv)
    argv[0] = "caviar-core"
    if len(argv) > 1 and argv[1] == "report":
        from caviar.report import main as report

        sys.exit(report(argv[2:]))
    from caviar import _core

    sys.exit(_core.main(argv))


if __name__ == "__main__":
    main()
