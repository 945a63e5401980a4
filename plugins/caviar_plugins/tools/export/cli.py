"""``caviar-core export ...`` (entry point group ``caviar.commands``, name ``export``):
a recorded run in another tool's format.

    export deepmimo RUN_DIR OUT [--module NAME] [--quiet] [--debug]
    export raymobtime RUN_DIR OUT [--grid X,Y,Z] [--cell M] [--tx X,Y,Z] [--debug]

``deepmimo``: a DeepMIMO v4 scenario from the path data of a ray-traced run
(``sionna-link``'s ``publish_paths = true``; :mod:`caviar_plugins.tools.export.deepmimo_export`).
``raymobtime``: a ``beam-dataset`` run's records (position, beam-pair gains, LiDAR, camera)
in Raymobtime's files (:mod:`caviar_plugins.tools.export.raymobtime`).

Exit status: 0 written; 2 bad input (no run directory, a run without path data, an OUT
that exists, deepmimo missing, bad option), one line on stderr naming what is wrong (every
argument and flag is checked before any work starts, the message begins with its name);
1 an unexpected error (one line; ``--debug`` shows the traceback).
"""

from __future__ import annotations

import argparse
import pathlib
import sys
from typing import Callable

from caviar.rundir import RunDir
from caviar_plugins.tools import flags
from caviar_plugins.tools.flags import Parser as _Parser
from caviar_plugins.tools.flags import Usage as _Usage

PROG = "caviar-core export"


def parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description="A recorded run in another tool's format.")
    sub = p.add_subparsers(dest="format", required=True, parser_class=_Parser)
    d = sub.add_parser("deepmimo", help="a DeepMIMO v4 scenario from a ray-traced run's path data",
                       description="Writes OUT, a DeepMIMO v4 scenario (params.json, objects.json, vertices.npz, "
                       "per-link .npz files; one subfolder per step when there are several) from the paths that "
                       "sionna-link published with publish_paths = true, converted by DeepMIMO's Sionna RT "
                       "converter. Load it with deepmimo.config.set('scenarios_folder', PARENT_OF_OUT) and "
                       "deepmimo.load(NAME_OF_OUT, max_paths=25).")
    d.add_argument("run_dir", type=pathlib.Path, help="the run directory (caviar-core run's output)")
    d.add_argument("out", type=pathlib.Path, help="the scenario folder to create (a new, lower-case name)")
    d.add_argument("--module", help="the module whose paths to export, when several published some")
    d.add_argument("--quiet", action="store_true", help="no progress lines")
    d.add_argument("--debug", action="store_true", help="tracebacks for unexpected errors")
    r = sub.add_parser("raymobtime", help="a beam-dataset run's records in Raymobtime's files",
                       description="Writes OUT: CoordVehiclesRxPerScene.csv, beams_output.npz "
                       "(output_classification), lidar_input.npz (input_classification, occupancy grids around "
                       "the UE from its LiDAR sweeps), img_input.npz (inputs, the camera images) and meta.json, "
                       "from the records a beam-dataset module wrote (with lidar and camera modules in the run "
                       "for those modalities).")
    r.add_argument("run_dir", type=pathlib.Path, help="the run directory (caviar-core run's output)")
    r.add_argument("out", type=pathlib.Path, help="the folder to create")
    r.add_argument("--grid", default="40,40,20", help="LiDAR grid cells X,Y,Z (default 40,40,20)")
    r.add_argument("--cell", type=float, default=1.0, help="LiDAR grid cell size in metres (default 1)")
    r.add_argument("--tx", help="the base station X,Y,Z (default: the run's link module's tx_position)")
    r.add_argument("--debug", action="store_true", help="tracebacks for unexpected errors")
    return p


def _exported(args, bad_input: type[Exception], work: Callable[[], object]) -> int:
    """Runs ``work`` (one export): 0 done; 2 ``bad_input``, named in one line; 1 anything else,
    one line unless ``--debug``."""
    try:
        work()
    except bad_input as e:
        print(f"{PROG} {args.format}: error: {e}", file=sys.stderr)
        return 2
    except Exception as e:  # noqa: BLE001 - one line unless --debug
        if args.debug:
            raise
        print(f"{PROG} {args.format}: error: {type(e).__name__}: {e} (--debug for the traceback)", file=sys.stderr)
        return 1
    return 0


MAX_GRID_CELLS = 10**8
"""The most LiDAR grid cells (X·Y·Z) an export makes per record (--grid)."""


def checked(args) -> None:
    """Every argument and flag, before any work starts (:class:`~caviar_plugins.tools.flags.FlagError`
    naming it)."""
    flags.existing_dir(args.run_dir, "RUN_DIR", "the folder of a run of `caviar-core run`")
    if not RunDir(args.run_dir).exists():
        raise flags.FlagError("RUN_DIR", f"{args.run_dir} is not a run directory (no run status); give the folder "
                                         "of a run of `caviar-core run`")
    flags.new_output(args.out, "OUT")
    if args.format == "deepmimo":
        if args.module is not None and not args.module.strip():
            raise flags.FlagError("--module", "expected a module name, got an empty one")
        return
    grid = flags.numbers(args.grid, "--grid", 3, "X,Y,Z cells")
    if not all(g == int(g) and g >= 1 for g in grid) or grid[0] * grid[1] * grid[2] > MAX_GRID_CELLS:
        raise flags.FlagError("--grid", f"expected X,Y,Z: whole numbers of cells, at least 1 and at most "
                                        f"{MAX_GRID_CELLS:.0e} in all, got {args.grid!r}")
    flags.number(args.cell, "--cell", positive=True)
    if args.tx is not None:
        flags.numbers(args.tx, "--tx", 3, "X,Y,Z in metres")


def _raymobtime(args) -> None:
    from caviar_plugins.tools.export.raymobtime import export_raymobtime

    grid = tuple(int(v) for v in flags.numbers(args.grid, "--grid", 3, "X,Y,Z cells"))
    tx = list(flags.numbers(args.tx, "--tx", 3, "X,Y,Z in metres")) if args.tx else None
    meta = export_raymobtime(args.run_dir, args.out, grid=grid, cell_m=args.cell, tx=tx)  # type: ignore[arg-type]
    print(f"{args.out}: {meta['records']} records ({meta['lidar']['records']} with LiDAR, {meta['images']} with an "
          f"image)")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = parser().parse_args(argv)
    except _Usage as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except SystemExit as e:  # --help
        return int(e.code or 0)
    try:
        checked(args)
    except flags.FlagError as e:
        print(f"{PROG} {args.format}: error: {e}", file=sys.stderr)
        return 2
    if args.format == "raymobtime":
        from caviar_plugins.tools.export.raymobtime import ExportError as RaymobtimeError

        return _exported(args, RaymobtimeError, lambda: _raymobtime(args))
    from caviar_plugins.tools.export.deepmimo_export import ExportError, export_deepmimo

    return _exported(args, ExportError, lambda: export_deepmimo(
        args.run_dir, args.out, module=args.module, progress=None if args.quiet else print))


if __name__ == "__main__":
    sys.exit(main())
