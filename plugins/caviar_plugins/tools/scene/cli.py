"""``caviar-core scene ...`` (entry point group ``caviar.commands``, name ``scene``)
and ``python -m caviar_plugins.tools.scene ...``.

    scene build INPUT.osm|INPUT.osm.pbf --out DIR [--bbox S,W,N,E | --center LAT,LON --radius M]
                [--decimate R] [--default-height M] [--roads] [--sumo]

Exit status: 0 built; 2 bad input (missing or unreadable file, empty bbox, no buildings,
bad option), one line on stderr naming the file and the reason (every flag is checked before
any work starts, the message names it); 1 an unexpected error (one line; ``--debug`` shows
the traceback).
"""

from __future__ import annotations

import argparse
import pathlib
import sys

from caviar_plugins.tools import flags
from caviar_plugins.tools.flags import Parser as _Parser
from caviar_plugins.tools.flags import Usage as _Usage

PROG = "caviar-core scene"


def parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description="3D scenes for ray tracing (Sionna RT) and road networks (SUMO) "
                "from OpenStreetMap.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    b = sub.add_parser("build", help="build a scene (and a SUMO network) from an OSM extract",
                       description="Builds DIR/scene.xml (Mitsuba 3, ITU radio materials), meshes/*.ply, scene.json "
                       "and, with --sumo, net.net.xml from an OpenStreetMap extract, offline.")
    b.add_argument("input", type=pathlib.Path, help="OSM XML (.osm) or PBF (.osm.pbf) file")
    b.add_argument("--out", type=pathlib.Path, required=True, help="output directory (created)")
    where = b.add_mutually_exclusive_group()
    where.add_argument("--bbox", metavar="S,W,N,E", help="only buildings lying wholly inside this box (degrees)")
    where.add_argument("--center", metavar="LAT,LON", help="with --radius: the square of half-side M around it")
    b.add_argument("--radius", type=float, metavar="M", help="half-side of the --center square, metres")
    b.add_argument("--decimate", type=float, default=1.0, metavar="R",
                   help="keep the fraction R of the building faces, 0 < R <= 1 (default 1: no decimation; "
                   "Blender's Decimate ratio 0.75 is R = 0.75)")
    b.add_argument("--default-height", type=float, default=10.0, metavar="M",
                   help="height of buildings without height or building:levels tags (default 10 m)")
    b.add_argument("--roads", action="store_true", help="add road surfaces (highway ways buffered to their width)")
    b.add_argument("--sumo", action="store_true", help="also write net.net.xml (netconvert) in the same frame")
    b.add_argument("--per-building", action="store_true",
                   help="one shape per building instead of one per material (slower ray tracing; comparisons)")
    b.add_argument("--no-brick", action="store_true", help="map brick to concrete (ITU brick is defined to 40 GHz)")
    b.add_argument("--quiet", action="store_true", help="no progress lines")
    b.add_argument("--debug", action="store_true", help="tracebacks for unexpected errors")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = parser().parse_args(argv)
    except _Usage as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except SystemExit as e:  # --help
        return int(e.code or 0)
    if args.command == "build":
        try:
            checked(args)
        except flags.FlagError as e:
            print(f"{PROG} build: error: {e}", file=sys.stderr)
            return 2
        return _build(args)
    return 2


def checked(args) -> None:
    """``scene build``'s input and flags, before any work starts (:class:`~caviar_plugins.tools.flags.FlagError`
    naming the flag; the bounding box's own checks follow in :func:`_build`)."""
    flags.existing_file(args.input, "INPUT", "an OpenStreetMap extract, .osm or .osm.pbf")
    flags.output_dir(args.out, "--out")
    if args.center is not None:
        lat, lon = flags.numbers(args.center, "--center", 2, "LAT,LON in degrees")
        if not (-90 <= lat <= 90 and -180 <= lon <= 180):
            raise flags.FlagError("--center", f"expected LAT in [-90, 90] and LON in [-180, 180] degrees, got "
                                              f"{args.center!r}")
    if args.radius is not None:
        flags.number(args.radius, "--radius", positive=True)
    if not (args.decimate > 0 and args.decimate <= 1):
        raise flags.FlagError("--decimate", f"expected a fraction of faces to keep in (0, 1], got {args.decimate}")
    flags.number(args.default_height, "--default-height", positive=True)


def _build(args) -> int:
    from caviar_plugins.osm import BuildError

    try:
        from caviar_plugins.osm.build import Settings, build
        from caviar_plugins.osm.frame import BBox

        bbox = None
        if args.bbox:
            bbox = BBox.parse(args.bbox)
        elif args.center or args.radius is not None:
            if not (args.center and args.radius is not None):
                raise ValueError("--center and --radius go together")
            try:
                lat, lon = (float(v) for v in args.center.split(","))
            except ValueError:
                raise ValueError(f"--center: expected LAT,LON in degrees, got {args.center!r}") from None
            bbox = BBox.around(lat, lon, args.radius)
        settings = Settings(input=args.input, out=args.out, bbox=bbox, decimate=args.decimate,
                            default_height=args.default_height, roads=args.roads, sumo=args.sumo,
                            per_building=args.per_building, brick=not args.no_brick)
        build(settings, log=None if not args.quiet else (lambda msg: None))
    except ImportError as e:
        print(f"{PROG} build: error: {e.name or e}: not installed; install the 'osm' extra: "
              "pip install 'caviar-plugins[osm]'", file=sys.stderr)
        return 2
    except (BuildError, ValueError) as e:
        msg = " ".join(str(e).split())
        if str(args.input) not in msg:
            msg = f"{args.input}: {msg}"
        print(f"{PROG} build: error: {msg}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"{PROG} build: error: {args.input}: {e.filename or args.out}: {e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG} build: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # noqa: BLE001 - one line unless --debug
        if args.debug:
            raise
        print(f"{PROG} build: error: {args.input}: unexpected {type(e).__name__}: {' '.join(str(e).split())} "
              "(--debug shows the traceback)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
