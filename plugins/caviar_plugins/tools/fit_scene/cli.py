"""``caviar-core fit-scene``: learns a scene's radio materials from measurements by
differentiable ray tracing (:func:`caviar_plugins.twin.fit.fit_materials`).

    fit-scene SCENE MEASUREMENTS --out DIR [--learn P[,P]] [--materials M[,M]]
              [--group NAME=GLOB[,GLOB]]... [--holdout 0.2] [--iterations 100]
              [--method lm] [--learning-rate 0.1] [--noise-db 1] [--max-log-std 0.2]
              [--search-points 160] [--search-sweeps 3] [--restarts 8] [--rival-starts 8] [--inclusion-starts 3]
              [--samples 200000] [--max-depth 3]
              [--diffraction] [--diffuse] [--seed 0] [--threads 0] [--quiet]

SCENE is a shipped scene's name or a Mitsuba XML file; MEASUREMENTS a CSV or Parquet file
in the format of :mod:`caviar_plugins.twin.measurements`. Writes DIR/scene.xml (the same
scene with the learned materials, loadable by every module unchanged), DIR/fit.json (before
and after, fit and held-out RMSE, learned against starting values, what is not
identifiable, every iteration) and DIR/fit.png.

Exit status: 0 fitted; 2 bad input (a flag, the scene, the measurements), one line on stderr
naming the flag or the file, row and field, checked before any ray is traced; 1 an
unexpected error (one line; ``--debug`` shows the traceback).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time

from caviar_plugins.tools.flags import Parser as _Parser
from caviar_plugins.tools.flags import Usage as _Usage

PROG = "caviar-core fit-scene"


def parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description="Learns a scene's radio materials (permittivity, conductivity, scattering) "
                "from received-power measurements by gradient descent through Sionna RT.")
    p.add_argument("scene", help="a shipped scene's name or a Mitsuba XML scene file")
    p.add_argument("measurements", type=pathlib.Path, help="CSV or Parquet measurements (docs/tutorials/fit-scene.md)")
    p.add_argument("--out", type=pathlib.Path, required=True, help="output directory (created)")
    p.add_argument("--learn", default="relative_permittivity,conductivity",
                   help="properties to learn: relative_permittivity, conductivity, scattering_coefficient")
    p.add_argument("--materials", default="", help="materials to learn (default: every one the scene's objects use)")
    p.add_argument("--group", action="append", default=[], metavar="NAME=GLOB[,GLOB]",
                   help="objects (name globs) that get a material NAME of their own; repeatable")
    p.add_argument("--holdout", type=float, default=0.2, help="share of samples held out of the fit (default 0.2)")
    p.add_argument("--iterations", type=int, default=100, help="gradient steps at most (default 100)")
    p.add_argument("--method", default="lm", help="the descent: lm (Levenberg-Marquardt, default) or adam")
    p.add_argument("--learning-rate", type=float, default=0.1, help="with --method adam: Adam's step in the "
                   "properties' logs")
    p.add_argument("--noise-db", type=float, default=1.0, help="measurement noise, dB (identifiability bound)")
    p.add_argument("--max-log-std", type=float, default=0.2, help="learn a property only if its log is "
                   "determined within this (Cramér-Rao bound; default 0.2)")
    p.add_argument("--search-points", type=int, default=160, help="values per property in the coarse search")
    p.add_argument("--search-sweeps", type=int, default=3, help="rounds of a coarse search and a descent (0: no "
                   "search; default 3, fewer when a round finds nothing better)")
    p.add_argument("--restarts", type=int, default=8, help="rounds from random values after the search (default 8)")
    p.add_argument("--rival-starts", type=int, default=8, help="then descents from the other basins that fit about "
                   "as well, each with the other properties searched again (default 8)")
    p.add_argument("--inclusion-starts", type=int, default=3, help="the test of a property left out starts from the "
                   "fit's minimum and this many other minima the rounds ended at (default 3)")
    p.add_argument("--samples", type=int, default=200_000, help="rays per transmitter (default 2e5)")
    p.add_argument("--max-depth", type=int, default=3, help="interactions per path at most (default 3)")
    p.add_argument("--diffraction", action="store_true", help="trace diffraction too")
    p.add_argument("--diffuse", action="store_true", help="trace diffuse reflection (scattering) too")
    p.add_argument("--seed", type=int, default=0, help="draws the held-out samples and seeds the tracer")
    p.add_argument("--threads", type=int, default=0, help="Dr.Jit CPU threads (0: all cores)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--debug", action="store_true", help="tracebacks for unexpected errors")
    return p


def _names(text: str, flag: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if text.strip() and not names:
        raise _Usage(f"{flag}: expected comma-separated names, got {text!r}")
    return names


def _groups(items: list[str]) -> dict[str, tuple[str, ...]]:
    out = {}
    for item in items:
        name, eq, globs = item.partition("=")
        if not eq or not name.strip() or not globs.strip():
            raise _Usage(f"--group: expected NAME=GLOB[,GLOB], got {item!r}")
        if name.strip() in out:
            raise _Usage(f"--group: '{name.strip()}' given twice")
        out[name.strip()] = _names(globs, "--group")
    return out


def _check(args):
    """Every flag, the scene and the measurements, before any work: (FitSettings,
    TraceSettings, Measurements) or a _Usage naming the flag."""
    from caviar_plugins.rt.scene import scene_path
    from caviar_plugins.rt.settings import TraceSettings
    from caviar_plugins.tools import flags
    from caviar_plugins.twin.fit import FIT_RAYS, FitSettings
    from caviar_plugins.twin.measurements import MeasurementError, read_measurements

    try:
        for flag, v in (("--holdout", args.holdout), ("--learning-rate", args.learning_rate),
                        ("--noise-db", args.noise_db), ("--max-log-std", args.max_log_std)):
            flags.number(v, flag)
        for flag, v, lo, hi in (("--samples", args.samples, 1, 10**8), ("--max-depth", args.max_depth, 0, 10),
                                ("--iterations", args.iterations, 1, 10_000),
                                ("--search-points", args.search_points, 1, 1000),
                                ("--search-sweeps", args.search_sweeps, 0, 10),
                                ("--restarts", args.restarts, 0, 1000), ("--rival-starts", args.rival_starts, 0, 1000),
                                ("--inclusion-starts", args.inclusion_starts, 0, 1000),
                                ("--threads", args.threads, 0, 4096),
                                ("--seed", args.seed, 0, 2**31 - 1)):
            flags.integer(v, flag, lo, hi)
        flags.output_dir(args.out)
    except flags.FlagError as e:
        raise _Usage(str(e)) from None
    try:
        settings = FitSettings(learn=_names(args.learn, "--learn"), materials=_names(args.materials, "--materials"),
                               groups=_groups(args.group), holdout=args.holdout, iterations=args.iterations,
                               method=args.method, learning_rate=args.learning_rate, noise_db=args.noise_db,
                               max_log_std=args.max_log_std, seed=args.seed, search_points=args.search_points,
                               search_sweeps=args.search_sweeps, restarts=args.restarts,
                               rival_starts=args.rival_starts, inclusion_starts=args.inclusion_starts)
    except ValueError as e:
        key, _, rest = str(e).partition(":")
        raise _Usage(f"--{key.replace('_', '-')}:{rest}") from None
    rays = TraceSettings(**{**dataclasses.asdict(FIT_RAYS), "samples_per_src": args.samples,
                            "max_depth": args.max_depth, "diffraction": args.diffraction,
                            "diffuse_reflection": args.diffuse, "threads": args.threads})
    try:
        scene_path(args.scene)
    except FileNotFoundError as e:
        raise _Usage(f"SCENE: {e}") from None
    try:
        data = read_measurements(args.measurements)
    except MeasurementError as e:
        raise _Usage(f"MEASUREMENTS: {e}") from None
    args.out.mkdir(parents=True, exist_ok=True)
    return settings, rays, data


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = parser().parse_args(argv)
        settings, rays, data = _check(args)
    except _Usage as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
    except SystemExit as e:  # --help
        return int(e.code or 0)
    try:
        return _fit(args, settings, rays, data)
    except (ValueError, KeyError) as e:  # the scene and the settings disagree (a material, a group)
        print(f"{PROG}: error: {e.args[0] if e.args else e}", file=sys.stderr)
        return 2
    except Exception as e:  # noqa: BLE001 - one line unless --debug
        if args.debug:
            raise
        print(f"{PROG}: unexpected error: {type(e).__name__}: {e} (--debug shows the traceback)", file=sys.stderr)
        return 1


def _fit(args, settings, rays, data) -> int:
    from caviar_plugins.rt.materials import write_scene_xml
    from caviar_plugins.rt.scene import load_scene, scene_path
    from caviar_plugins.tools.fit_scene.report import plot_fit
    from caviar_plugins.twin.fit import fit_materials

    t0 = time.perf_counter()
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr, flush=True))
    say(f"{PROG}: {len(data)} samples at {data.frequency_hz / 1e9:g} GHz; tracing {args.scene}")
    scene = load_scene(args.scene, merge_shapes=not settings.groups)

    def progress(row):
        if row["phase"] == "descent" or row.get("sweep") is not None:
            values = ", ".join(f"{k}={v:.4g}" for k, v in row.items() if "." in k)
            step = f"iteration {row['iteration']}" if row["phase"] == "descent" else f"search {row['sweep']}"
            say(f"  {step}: fit {row['fit_rmse_db']:.3f} dB, held out {row['held_out_rmse_db']:.3f} dB; {values}")

    result = fit_materials(scene, data, settings, rays, run_seed=args.seed, progress=progress)
    report = result.as_json()
    report.update({"scene": str(args.scene), "measurements": str(args.measurements),
                   "frequency_hz": data.frequency_hz, "bandwidth_hz": data.bandwidth_hz,
                   "raytracing": dataclasses.asdict(rays), "wall_s": round(time.perf_counter() - t0, 1)})
    source = scene_path(args.scene)
    if source is not None:
        learned = {m for m, _ in result.learned}
        report["names_in_scene_xml"] = write_scene_xml(
            source, args.out / "scene.xml", {m: v for m, v in result.materials.items() if m in learned}, result.groups)
    (args.out / "fit.json").write_text(json.dumps(report, indent=1))
    plot_fit(result, data, args.out / "fit.png")
    rm = result.rmse_db
    say(f"{PROG}: held-out RMSE {rm['held_out']['before']:.2f} -> {rm['held_out']['after']:.2f} dB "
        f"(fit {rm['fit']['before']:.2f} -> {rm['fit']['after']:.2f}); {result.stopped}; wrote {args.out}")
    ds = result.delay_spread_ns
    if ds:
        which = "held_out" if ds["held_out"]["before"] is not None else "fit"
        say(f"{PROG}: RMS delay spread of {ds['samples']} profiles (median {ds['measured_median']:.1f} ns), "
            f"{which.replace('_', '-')} RMS error {ds[which]['before']} -> {ds[which]['after']} ns (not fitted on)")
    unseen = [f"{m}.{p}" for (m, p) in result.start if (m, p) not in result.identifiability.identifiable]
    if unseen:
        say(f"{PROG}: not identifiable from these measurements (kept at their start): {', '.join(unseen)}")
    return 0
