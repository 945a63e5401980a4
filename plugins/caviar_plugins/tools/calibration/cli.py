"""``caviar-core calibrate 38.901``: the phase-1 (large-scale) calibration of TR 38.901 §7.8.1
(R1-165974; Table 7.8-1 settings, no fast fading), run through the ``radio-network``
plugin's own cells, measurements and SINR, as every blueprint runs.

    caviar-core calibrate 38.901 --scenario UMa --carrier 6e9 --drops 20

Each engine step is one drop: the network drops 10 UEs in each of the 57 sectors of the
19-site wrapped-around hexagonal layout, every UE attaches to its strongest cell (no
handover margin) and reports, in the step's ``network.ues`` table, its coupling loss, its
geometry SINR (with noise) and its wideband SIR (without). The command writes
``<out>/<scenario>-<carrier>GHz.json`` (the three CDFs at the percentiles 0..100, the drops
and the settings; coupling loss as a positive loss) and a ``.png`` that draws each CDF
over the band of the 3GPP companies' curves (``--reference``,
:data:`~caviar_plugins.tools.calibration.config.COMPANIES` by default: all six cases of
R1-165974); a case the file lacks is said so in the output and the JSON. The 38.901
channel runs with ``--spec-version`` 16.1 by default, the O2I model of the companies' 2016
curves (:data:`~caviar_plugins.network.tr38901.SPEC_VERSIONS`).

    caviar-core calibrate ray-traced --scene blueprints/osm-city/scene/scene.xml --drops 20

sets the ray-traced channel beside the stochastic one: the UMi-like layout of 7 sites at
ISD 200 m placed in a city scene (``--center``, or the centre nearest the scene's middle
with every site in the open), run once with ``channel = "ray-traced"`` and once with
``38.901-umi``, outdoor UEs only; it writes both channels' CDFs, their difference at the
percentiles 5, 50 and 95, and a map of where the ray-traced UEs lose
(``<out>/raytraced-vs-38.901-umi{.json,.png,-map.png}``).

Every flag is checked before any work starts; a bad one ends the command with one line
naming it, exit status 2.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

from caviar_plugins.tools import flags
from caviar_plugins.tools.calibration.config import COMPANIES, SPEC_VERSION, CalibrationError, settings
from caviar_plugins.tools.calibration.runs import calibrate, side_by_side
from caviar_plugins.tools.flags import Parser as _Parser
from caviar_plugins.tools.flags import Usage as _Usage

PROG = "caviar-core calibrate"
MAX_SEED = 2**32 - 1  # (the run's seed is mixed into Sionna's and torch's, which take 64 bits)
SPEC_VERSIONS = ("16.1", "19.2")  # (caviar_plugins.network.tr38901.SPEC_VERSIONS: Sionna's releases)


def parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("model", choices=["38.901", "ray-traced"],
                   help="38.901: TR 38.901 phase 1; ray-traced: the ray-traced channel in --scene "
                        "beside 38.901 UMi on one 7-site layout")
    p.add_argument("--scenario", default="UMa", help="UMa or UMi (Table 7.8-1)")
    p.add_argument("--carrier", type=float, default=6e9, help="6e9, 30e9 or 70e9 (Hz)")
    p.add_argument("--drops", type=int, default=20, help="drops of 570 UEs (default 20)")
    p.add_argument("--seed", type=int, default=1, help="the run's seed, 0 to 2^32 − 1 (default 1)")
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("docs/results/calibration"),
                   help="the folder the results go to (created)")
    p.add_argument("--reference", type=pathlib.Path, default=COMPANIES,
                   help="the 3GPP companies' CDFs (JSON) to draw and compare with (default: the six cases of "
                        "R1-165974 shipped with the package)")
    p.add_argument("--spec-version", choices=SPEC_VERSIONS, default=SPEC_VERSION,
                   help=f"the release of TR 38.901's tables (default {SPEC_VERSION}: the O2I model the companies' "
                        "2016 curves were made with; 19.2 is the latest)")
    p.add_argument("--scene", default="blueprints/osm-city/scene/scene.xml",
                   help="ray-traced: the scene (a Mitsuba XML file, e.g. scene build's)")
    p.add_argument("--center", default="auto",
                   help="ray-traced: X,Y of the centre site in the scene frame (m), or auto: the centre "
                        "nearest the scene's middle with every site in the open")
    p.add_argument("--samples", type=int, default=100_000, help="ray-traced: rays per site and drop")
    p.add_argument("--max-depth", type=int, default=2, help="ray-traced: reflections per path")
    return p


def checked(args: argparse.Namespace) -> dict | None:
    """Every flag checked before any work starts (:class:`~caviar_plugins.tools.flags.FlagError`
    or :class:`CalibrationError`, naming the flag); the reference file's contents (38.901)."""
    flags.integer(args.drops, "--drops", minimum=1, maximum=10_000)
    flags.integer(args.seed, "--seed", minimum=0, maximum=MAX_SEED)
    flags.output_dir(args.out, "--out")
    if args.model == "ray-traced":
        flags.existing_file(pathlib.Path(args.scene), "--scene", "a Mitsuba scene file (scene build's scene.xml)")
        if args.center != "auto":
            flags.numbers(args.center, "--center", 2, "X,Y in metres, or auto")
        flags.integer(args.samples, "--samples", minimum=1, maximum=10**8)
        flags.integer(args.max_depth, "--max-depth", minimum=0, maximum=10)
        return None
    settings(args.scenario, args.carrier, args.spec_version)
    data = flags.json_file(args.reference, "--reference", "the companies' CDFs as JSON")
    if not isinstance(data, dict) or not isinstance(data.get("scenarios"), dict):
        raise flags.FlagError("--reference", f"{args.reference} has no \"scenarios\" table (expected the companies' "
                                             f"CDFs in the format of {COMPANIES.name})")
    return data


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = parser().parse_args(argv)
        checked(args)
    except _Usage as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except SystemExit as e:  # --help
        return int(e.code or 0)
    except (flags.FlagError, CalibrationError) as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    if args.model == "ray-traced":
        return _main_side_by_side(args)
    try:
        result = calibrate(args.scenario, args.carrier, args.drops, args.out, args.seed, args.reference,
                           spec_version=args.spec_version)
    except CalibrationError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    stem = f"{result['settings']['scenario']}-{args.carrier / 1e9:g}GHz"
    print(f"{result['samples']} UEs in {result['drops']} drops, {result['wall_s']} s: "
          f"{args.out / (stem + '.json')}, {args.out / (stem + '.png')}")
    ref = result["reference"]
    if "missing" in ref:
        print(f"  no reference: {ref['missing']}")
    for metric in ("coupling_loss_db", "geometry_sinr_db", "wideband_sir_db"):
        rows = ref.get(metric)
        if isinstance(rows, dict):
            print(f"  {metric}: " + ", ".join(
                f"{p} {r['ours']:.1f} ({'in' if r['within_range'] else 'OUT of'} [{r['min']:.1f}, {r['max']:.1f}]"
                + (f", {r['from_median_db']:+.1f} dB from the median" if p == "p50" else "") + ")"
                for p, r in rows.items()))
    return 0


def _main_side_by_side(args: argparse.Namespace) -> int:
    center: tuple[float, float] | None = None
    if args.center != "auto":
        x, y = flags.numbers(args.center, "--center", 2, "X,Y in metres, or auto")
        center = (x, y)
    try:
        result = side_by_side(args.scene, args.drops, args.out, center, args.seed, args.samples, args.max_depth)
    except CalibrationError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    print(f"layout centred at {result['settings']['layout']['center_m']}: "
          f"{args.out / 'raytraced-vs-38.901-umi.json'}, {args.out / 'raytraced-vs-38.901-umi.png'}")
    for channel, r in result["channels"].items():
        print(f"  {channel}: {r['samples']} UEs ({r['uncovered']} reached by no cell), {r['wall_s']} s")
    for metric, d in result["difference_db"].items():
        print(f"  ray-traced − 38.901 {metric}: " + ", ".join(f"{p} {v:+.1f} dB" for p, v in d.items()))
    return 0
