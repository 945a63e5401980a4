"""``caviar-core calibrate 38.901``: the phase-1 (large-scale) calibration of TR 38.901 §7.8.1
(R1-165974; Table 7.8-1 settings, no fast fading), run through the ``radio-network``
plugin's own cells, measurements and SINR, as every blueprint runs.

    caviar-core calibrate 38.901 --scenario UMa --carrier 6e9 --drops 20

Each engine step is one drop: the network drops 10 UEs in each of the 57 sectors of the
19-site wrapped-around hexagonal layout, every UE attaches to its strongest cell (no
handover margin) and reports, on ``network.ue``, its coupling loss, its geometry SINR
(with noise) and its wideband SIR (without). The command writes
``<out>/<scenario>-<carrier>GHz.json`` (the three CDFs at the percentiles 0..100, the drops
and the settings; coupling loss as a positive loss) and a ``.png`` that draws each CDF
over the band of the 3GPP companies' curves where the shipped file has them
(``--reference``, :data:`~caviar_plugins.tools.calibration.config.COMPANIES` by default).

    caviar-core calibrate ray-traced --scene blueprints/osm-city/scene/scene.xml --drops 20

sets the ray-traced channel beside the stochastic one: the UMi-like layout of 7 sites at
ISD 200 m placed in a city scene (``--center``, or the centre nearest the scene's middle
with every site in the open), run once with ``channel = "ray-traced"`` and once with
``38.901-umi``, outdoor UEs only; it writes both channels' CDFs, their difference at the
percentiles 5, 50 and 95, and a map of where the ray-traced UEs lose
(``<out>/raytraced-vs-38.901-umi{.json,.png,-map.png}``).
"""

from __future__ import annotations

import argparse
import pathlib
import sys

from caviar_plugins.tools.calibration.config import COMPANIES, CalibrationError
from caviar_plugins.tools.calibration.runs import calibrate, side_by_side


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="caviar-core calibrate", description=__doc__.split("\n\n")[0])
    parser.add_argument("model", choices=["38.901", "ray-traced"],
                        help="38.901: TR 38.901 phase 1; ray-traced: the ray-traced channel in --scene "
                             "beside 38.901 UMi on one 7-site layout")
    parser.add_argument("--scenario", default="UMa", help="UMa or UMi (Table 7.8-1)")
    parser.add_argument("--carrier", type=float, default=6e9, help="6e9, 30e9 or 70e9 (Hz)")
    parser.add_argument("--drops", type=int, default=20, help="drops of 570 UEs (default 20)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("docs/results/calibration"))
    parser.add_argument("--reference", type=pathlib.Path,
                        default=COMPANIES,
                        help="the 3GPP companies' CDFs (JSON) to draw and compare with")
    parser.add_argument("--scene", default="blueprints/osm-city/scene/scene.xml",
                        help="ray-traced: the scene (a Mitsuba XML file, e.g. scene build's)")
    parser.add_argument("--center", default="auto",
                        help="ray-traced: X,Y of the centre site in the scene frame (m), or auto: the centre "
                             "nearest the scene's middle with every site in the open")
    parser.add_argument("--samples", type=int, default=100_000, help="ray-traced: rays per site and drop")
    parser.add_argument("--max-depth", type=int, default=2, help="ray-traced: reflections per path")
    args = parser.parse_args(argv)
    if args.model == "ray-traced":
        return _main_side_by_side(args)
    try:
        result = calibrate(args.scenario, args.carrier, args.drops, args.out, args.seed, args.reference)
    except CalibrationError as e:
        print(f"caviar-core calibrate: {e}", file=sys.stderr)
        return 2
    stem = f"{result['settings']['scenario']}-{args.carrier / 1e9:g}GHz"
    print(f"{result['samples']} UEs in {result['drops']} drops, {result['wall_s']} s: "
          f"{args.out / (stem + '.json')}, {args.out / (stem + '.png')}")
    for metric, rows in result.get("reference", {}).items():
        if isinstance(rows, dict):
            print(f"  {metric}: " + ", ".join(
                f"{p} {r['ours']:.1f} ({'in' if r['within_range'] else 'OUT of'} [{r['min']:.1f}, {r['max']:.1f}])"
                for p, r in rows.items()))
    return 0


def _main_side_by_side(args: argparse.Namespace) -> int:
    try:
        center = None
        if args.center != "auto":
            try:
                x, y = (float(v) for v in args.center.split(","))
            except ValueError:
                raise CalibrationError(f"--center: expected X,Y in metres or auto, got {args.center!r}") from None
            center = (x, y)
        result = side_by_side(args.scene, args.drops, args.out, center, args.seed, args.samples, args.max_depth)
    except CalibrationError as e:
        print(f"caviar-core calibrate: {e}", file=sys.stderr)
        return 2
    print(f"layout centred at {result['settings']['layout']['center_m']}: "
          f"{args.out / 'raytraced-vs-38.901-umi.json'}, {args.out / 'raytraced-vs-38.901-umi.png'}")
    for channel, r in result["channels"].items():
        print(f"  {channel}: {r['samples']} UEs ({r['uncovered']} reached by no cell), {r['wall_s']} s")
    for metric, d in result["difference_db"].items():
        print(f"  ray-traced − 38.901 {metric}: " + ", ".join(f"{p} {v:+.1f} dB" for p, v in d.items()))
    return 0
