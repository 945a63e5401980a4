"""Console entry point of ``caviar-core`` / ``caviar``: the command line is the core's."""

from __future__ import annotations

import sys


def main() -> None:
    from caviar import _core

    argv = list(sys.argv)
    argv[0] = "caviar-core"
    sys.exit(_core.main(argv))


if __name__ == "__main__":
    main()
