"""Console entry point of ``caviar-core`` / ``caviar``: the command line is the core's
(Rust); ``report`` (figures with matplotlib) and ``worker`` (a module over NATS) are the
Python side's."""

from __future__ import annotations

import sys


def main() -> None:
    argv = list(sys.argv)
    argv[0] = "caviar-core"
    if len(argv) > 1 and argv[1] == "report":
        from caviar.report import main as report

        sys.exit(report(argv[2:]))
    if len(argv) > 1 and argv[1] == "worker":
        from caviar.worker import main as worker

        sys.exit(worker(argv[2:]))
    from caviar import _core

    sys.exit(_core.main(argv))


if __name__ == "__main__":
    main()
