"""Host time around the solver (issue #53, part 3): what the project adds, outside Dr.Jit's
kernels, to Sionna's bare ``PathSolver`` call, in ``RadioScene.solve`` and in the comm
module's (``sionna-link``) whole step, on one scene.

    .venv/bin/python benches/bench_solve_host.py [--uavs 1 10] [--samples 1000000] [--reps 7]

Every item runs on the one scene of a ``sionna-link`` plugin (Central Park, the SAR route,
``uav_mesh`` on, ``shoot_cache = false``: Sionna's own loop, so that the bare call and the
project's solve trace the same rays), interleaved, the UAVs moved 0.5 m along the route
before each solve (a real solve every time), median of ``--reps`` after two warm-ups. Each
time is split with Dr.Jit's kernel history (as ``bench_freeze.py`` does) into kernels
(execution, code generation, backend compilation) and the rest, the host:

* ``bare``: ``PathSolver()(scene, ...)`` and a ``dr.eval`` of the paths' coefficients,
  delays and validity (what any use of them would wait for);
* ``bare_cfr``: the same and Sionna's ``paths.cfr(..., out_type="numpy")`` at the carrier
  (the narrowband H a user of Sionna would compute);
* ``solve_before``: the solve as it was before this change (the path tracer, then
  ``cfr``, ``np.array`` of validity and delays one by one, the line of sight, per receiver
  the beam gains): :func:`solve_before` below keeps it;
* ``solve``: ``RadioScene.solve(force=True)`` today;
* ``place_before`` and ``place``: moving the receivers and UAV bodies, as before
  (:func:`place_before`: Sionna's ``position`` setter per body, a geometry update each) and
  today (``RadioScene.place``: one update for all);
* ``step``: ``SionnaLink.step`` (positions in, messages out, publishing H and gains), and
  ``step_place`` (its ``RadioScene.place``: receivers and UAV bodies moved) and
  ``step_after_solve``: the step less its place and solve (host times of the same step).

"project adds" = the host time of ``solve`` less that of its own ``PathSolver`` call, in the
same call (median over the calls; the issue's target: <= 2 ms); ``..._vs_bare_call`` compares
with the separate ``bare`` calls instead (noisier: on a shared CPU the host time of a 1e5-sample
solve varies by 10 ms from call to call). The comm step after the solve:
``step_after_solve`` (target: <= 2 ms).

Then ``lookahead`` (:func:`bench_lookahead`): the comm module traced every step against
look-ahead with the UAV bodies, ``lookahead_steps = "auto"``; and ``freeze``
(:func:`freeze_trials`, unless ``--no-freeze``): ``dr.freeze`` on the carrier channel.

Writes docs/results/solve-host.json (the machine from ``bench_common.machine()``).

Measured on a 2-core AMD EPYC (LLVM, one Dr.Jit thread), 1e5 samples, 2026-11-28: the
project adds 0.50 ms of host time to Sionna's call for 1 UAV and 0.65 ms for 10 (0.58 and
0.79 before: ``cfr``'s kernels and a numpy read per array); the comm step after the solve
0.13 and 0.29 ms; moving 10 UAV bodies 128 -> 13 ms (one geometry rebuild instead of ten).
Look-ahead with the bodies along 40 steps: 4 solves instead of 40 (1 UAV, 9 steps ahead),
30 against 93 ms a step; 14 instead of 40 (10 UAVs, 2 ahead), 309 against 386 ms; the same
best pair at 92.5 % and 93.3 % of the steps, where another seed traced every step gives
90.0 % and 79.3 %. ``dr.freeze`` worked on the carrier channel: one kernel, recorded once per
receiver count and replayed whatever the path count, 0.08 ms of host time for 10 UAVs
against 0.15 ms unfrozen and 0.67 ms for the same sum in numpy; ``RadioScene.solve`` uses
it. Sionna's own call cannot be frozen (it reads its path count back to size its buffers).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import sys
import time

import numpy as np

from caviar_plugins.rt import configure_drjit

configure_drjit()  # before Dr.Jit and Mitsuba are imported
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from bench_common import machine  # noqa: E402
from caviar_plugins import DATA  # noqa: E402
from caviar_plugins.mobility import Path, read_waypoints  # noqa: E402

OUT = pathlib.Path("docs/results/solve-host.json")


class KernelClock:
    """Wall time of a call, split with Dr.Jit's kernel history; calls may nest (the step's
    solve): the history read by an inner call counts for the outer one too."""

    def __init__(self):
        self.rows: dict[str, list[tuple[float, float, float, int]]] = {}
        self._open: list[list] = []

    def _drain(self) -> None:
        hist = dr.kernel_history()  # (reading it empties it)
        for frame in self._open:
            frame.extend(hist)

    def __call__(self, label: str, fn, keep: bool = True):
        dr.sync_thread()
        if self._open:
            self._drain()
        else:
            dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        frame: list = []
        self._open.append(frame)
        t0 = time.perf_counter()
        out = fn()
        dr.sync_thread()
        wall = time.perf_counter() - t0
        self._drain()
        self._open.pop()
        if not self._open:
            dr.set_flag(dr.JitFlag.KernelHistory, False)
        run = sum(h.get("execution_time", 0.0) for h in frame) / 1e3
        compile_ = sum(h.get("codegen_time", 0.0) + h.get("backend_time", 0.0) for h in frame) / 1e3
        if keep:
            self.rows.setdefault(label, []).append((wall, run, compile_, len(frame)))
        return out

    def summary(self) -> dict[str, dict[str, float]]:
        out = {}
        for label, rows in self.rows.items():
            if not rows:
                continue
            wall, run, comp, n = (statistics.median(x) for x in zip(*rows, strict=True))
            host = [w - r - c for w, r, c, _ in rows]
            out[label] = {"wall_ms": 1e3 * wall, "kernels_ms": 1e3 * run, "compile_ms": 1e3 * comp,
                          "host_ms": 1e3 * statistics.median(host), "kernels": n, "n": len(rows)}
        return out


def solve_before(radio) -> dict:
    """``RadioScene.solve(force=True)`` as it was before issue #53's part 3 (commit 80c5581),
    for the before/after in one run."""
    from caviar_plugins.radio.beams import beam_gains
    from caviar_plugins.radio.link_report import line_of_sight_paths
    from caviar_plugins.radio.scene import Link

    c = radio.cfg
    paths = radio.tracer.solve()
    cfr = paths.cfr(frequencies=np.array([0.0]), normalize_delays=False, out_type="numpy")
    valid = np.array(paths.valid).reshape(len(radio.receivers), -1)
    tau = np.array(paths.tau).reshape(len(radio.receivers), -1)
    rx_pos = np.array([radio._where[key] for key in radio.receivers])
    direct = np.linalg.norm(rx_pos - np.asarray(c.tx_position, dtype=float), axis=1)
    los = np.any(line_of_sight_paths(tau, valid, direct[:, None]), axis=1)
    out = {}
    for i, key in enumerate(radio.receivers):
        h = cfr[i, :, 0, :, 0, 0]
        out[key] = Link(h=h, gains=beam_gains(h, radio.w_tx, radio.w_rx), los=bool(los[i]),
                        n_paths=int(valid[i].sum()), paths_dropped=radio.tracer.dropped)
    return out


def place_before(radio, positions: dict) -> None:
    """``RadioScene.place`` as it was before (commit 80c5581): each moved body through
    Sionna's ``position`` setter, one geometry update each."""
    offset = np.asarray(radio.cfg.antenna_offset, dtype=float)
    for key, pos in positions.items():
        pos = np.asarray(pos, dtype=float)
        moved = not np.array_equal(radio._where[key], pos + offset)
        if moved:
            radio.receivers[key].position = (pos + offset).tolist()
            radio.bodies[key].position = pos.tolist()
        radio._where[key] = pos + offset
    radio._placed = tuple((k, tuple(np.asarray(p, dtype=float))) for k, p in positions.items())


def plugin(samples: int, seed: int = 1, **params):
    from caviar.plugin import Context
    from caviar_plugins.radio.sionna_link import SionnaLink, SionnaLinkParams
    from caviar_plugins.rt.settings import with_raytracing

    p = with_raytracing(SionnaLinkParams, **{"samples_per_src": samples, "shoot_cache": False, "threads": 1, **params})
    link = SionnaLink()
    link.setup(Context(name="comm", params=p, seed=seed, ts=0.5, steps=None, every=1, offset=0,
                       run_dir=pathlib.Path("."), config_dir=pathlib.Path(".")))
    return link


def inbox(positions: dict[str, np.ndarray], t: float, forecast: dict[str, list] | None = None) -> list:
    from caviar.plugin import Message
    from caviar_plugins.mobility.waypoint_flight import forecast_payload

    out = [Message("3D.mobility.positions", {"UE_type": "UAV", "UE_Id": ue, "position":
                                             {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}},
                   source=ue, step=int(t / 0.5), time=t) for ue, p in positions.items()]
    return out + [Message("3D.mobility.forecast", forecast_payload(ue, ahead, 0.5), source=ue, step=int(t / 0.5),
                          time=t) for ue, ahead in (forecast or {}).items()]


def bench_lookahead(n_uav: int, samples: int, steps: int, depths: list | None = None) -> dict:
    """The comm module's steps along the route (5 m/s, Ts = 0.5 s, forecasts of 19 steps
    as waypoint-flight's ``forecast_steps`` gives them), UAV bodies on, the backend's
    default shoot cache: traced every step against ``lookahead = true`` with
    ``lookahead_steps`` each of ``depths`` (default ``["auto"]``; the label ``lookahead``
    for ``"auto"``, ``lookahead_<d>`` otherwise), interleaved step by step; wall time per
    step, solves, and the look-ahead's links against the step-by-step ones, beside those of
    another seed traced every step (the Monte Carlo noise the solver has anyway)."""
    from caviar_plugins.radio.scene import lookahead_depth

    depths = depths or ["auto"]
    route = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
    starts = np.linspace(10.0, 0.9 * route.length, n_uav)
    runs = {"every_step": plugin(samples, shoot_cache="auto")}
    for d in depths:
        runs["lookahead" if d == "auto" else f"lookahead_{d}"] = plugin(samples, shoot_cache="auto", lookahead=True,
                                                                        lookahead_steps=d)
    other = plugin(samples, seed=2, shoot_cache="auto")  # (every step, another seed: the Monte Carlo noise)
    walls: dict[str, list[float]] = {label: [] for label in runs}
    links: dict[str, list] = {label: [] for label in [*runs, "other_seed"]}
    order = list(runs)
    for k in range(steps):
        t = 0.5 * k
        pos = {f"uav{i}": route.at(s + 2.5 * k) for i, s in enumerate(starts)}
        forecast = {f"uav{i}": [route.at(s + 2.5 * (k + j)) for j in range(1, 20)] for i, s in enumerate(starts)}
        for label in order[k % len(order):] + order[:k % len(order)]:  # (each first in turn)
            t0 = time.perf_counter()
            out = list(runs[label].step(t, inbox(pos, t, forecast)))
            dr.sync_thread()
            walls[label].append(time.perf_counter() - t0)
            links[label] += [m for topic, m in out if topic == "communications.link"]
        links["other_seed"] += [m for topic, m in other.step(t, inbox(pos, t)) if topic == "communications.link"]
    res = {"uavs": n_uav, "samples_per_src": samples, "steps": steps,
           "lookahead_steps": {label: lookahead_depth(d, n_uav) for label, d in
                               zip([x for x in runs if x != "every_step"], depths, strict=True)},
           "step_ms_mean": {k: 1e3 * float(np.mean(v[2:])) for k, v in walls.items()},
           "first_steps_ms": {k: [round(1e3 * x, 1) for x in v[:2]] for k, v in walls.items()},
           "solves": {label: link.radio.solves for label, link in runs.items()}}
    for label in [*runs, "other_seed"][1:]:  # against every step
        a, b = links[label], links["every_step"]
        err = np.abs([x["path_gain_db"] - y["path_gain_db"] for x, y in zip(a, b, strict=True)])
        res[label] = {"same_best_pair_pct": 100 * float(np.mean([x["best_pair"] == y["best_pair"]
                                                                for x, y in zip(a, b, strict=True)])),
                      "path_gain_error_db": {"median": float(np.median(err)), "max": float(err.max())},
                      "best_throughput_error_pct_median": 100 * float(np.median(
                          [abs(x["best_throughput"] / y["best_throughput"] - 1) for x, y in zip(a, b, strict=True)]))}
    print(json.dumps(res), flush=True)
    return res


def bench_host(n_uav: int, samples: int, reps: int) -> dict:  # noqa: C901 (one interleaved loop)
    route = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
    starts = np.linspace(0.0, 0.9 * route.length, n_uav)
    link = plugin(samples)
    radio = link.radio
    c = radio.cfg
    from caviar_plugins.rt.scene import sionna_rt

    bare_solver = sionna_rt().PathSolver()
    options = dict(max_depth=c.max_depth, samples_per_src=c.samples_per_src, synthetic_array=True, los=c.los,
                   specular_reflection=c.specular_reflection, diffuse_reflection=c.diffuse_reflection,
                   refraction=c.refraction, diffraction=c.diffraction, seed=radio.seed,
                   max_num_paths_per_src=c.max_num_paths_per_src)

    def bare():
        paths = bare_solver(radio.scene, **options)
        dr.eval(paths.a, paths.tau, paths.valid)
        return paths

    def bare_cfr():
        paths = bare_solver(radio.scene, **options)
        return paths.cfr(frequencies=np.array([0.0]), normalize_delays=False, out_type="numpy")

    clock = KernelClock()
    sionna_inside: list[float] = []  # host time of the PathSolver call inside the last clocked call
    solver = radio.tracer.solver

    class TimedSolver:  # (the path tracer calls it as it calls Sionna's PathSolver)
        def __call__(self, *args, **kwargs):
            t0 = time.perf_counter()
            out = clock("sionna_in_solve", lambda: solver(*args, **kwargs))
            whole = time.perf_counter() - t0  # (with the clock's own reading of the kernel history)
            r = clock.rows["sionna_in_solve"].pop()
            sionna_inside.append(whole - r[1] - r[2])
            return out

    radio.tracer.solver = TimedSolver()
    added: dict[str, list[float]] = {"solve": [], "solve_before": []}

    def added_by(label: str, fn, keep: bool):
        """Clocks ``fn`` (a solve) and keeps its host time less its PathSolver call's."""
        sionna_inside.clear()
        out = clock(label, fn, keep)
        if keep:
            r = clock.rows[label][-1]
            added[label].append(r[0] - r[1] - r[2] - sum(sionna_inside))
        return out

    solve_inside: list[float] = []
    original_solve = radio.solve

    def timed_solve(force: bool = False):
        t0 = time.perf_counter()
        out = clock("solve_in_step", lambda: original_solve(force), keep=True)
        r = clock.rows["solve_in_step"][-1]
        solve_inside.append(time.perf_counter() - t0 - r[1] - r[2])  # (the clock's own time with it)
        return out

    place_inside: list[float] = []
    original_place = radio.place

    def timed_place(positions, **kw):
        t0 = time.perf_counter()
        clock("place_in_step", lambda: original_place(positions, **kw))
        r = clock.rows["place_in_step"].pop()
        place_inside.append(time.perf_counter() - t0 - r[1] - r[2])

    radio.solve = timed_solve  # type: ignore[method-assign]
    radio.place = timed_place  # type: ignore[method-assign]
    agree = []
    place_in_step: list[float] = []

    def step(pos, t, keep):
        n_inside = len(clock.rows.get("solve_in_step", []))
        place_inside.clear()
        clock("step", lambda: list(link.step(t, inbox(pos, t))), keep=keep)
        if not keep:  # (the step's solve of a warm-up is not kept either)
            clock.rows["solve_in_step"] = clock.rows["solve_in_step"][:n_inside]
            solve_inside[n_inside:] = []
        else:
            place_in_step.append(sum(place_inside))

    def solve_both(keep):
        before = added_by("solve_before", lambda: solve_before(radio), keep)
        agree.append(compare(before, original_solve(force=True)))

    placed = {"place_before": lambda pos, keep: clock("place_before", lambda: place_before(radio, pos), keep),
              "place": lambda pos, keep: clock("place", lambda: original_place(pos), keep)}
    solved = {"bare": lambda keep: clock("bare", bare, keep),
              "bare_cfr": lambda keep: clock("bare_cfr", bare_cfr, keep), "solve_before": solve_both,
              "solve": lambda keep: added_by("solve", lambda: original_solve(force=True), keep)}
    items = ["bare", "bare_cfr", "solve_before", "solve", "step", "place_before", "place"]
    for k in range(reps + 2):
        keep = k >= 2
        pos = {f"uav{i}": route.at(s + 0.5 * k) for i, s in enumerate(starts)}
        for item in items[k % len(items):] + items[:k % len(items)]:  # interleaved, each first in turn
            pos = {ue: p + [0.0, 0.0, 0.01] for ue, p in pos.items()}  # (a new position: a real solve)
            if item == "step":
                step(pos, 0.5 * k, keep)
            elif item in placed:
                placed[item](pos, keep)
            else:
                original_place(pos)
                solved[item](keep)
    radio.solve, radio.place = original_solve, original_place  # type: ignore[method-assign]
    radio.tracer.solver = solver
    res = clock.summary()
    step_host = [r[0] - r[1] - r[2] for r in clock.rows["step"]]
    res["step_place"] = {"host_ms": 1e3 * statistics.median(place_in_step)}
    res["step_after_solve"] = {"host_ms": 1e3 * statistics.median(
        [a - b - c for a, b, c in zip(step_host, solve_inside, place_in_step, strict=True)])}
    out = {"uavs": n_uav, "samples_per_src": samples, "reps": reps, "items": res,
           "project_adds_host_ms": 1e3 * statistics.median(added["solve"]),
           "project_adds_host_ms_min": 1e3 * min(added["solve"]),
           "project_added_before_host_ms": 1e3 * statistics.median(added["solve_before"]),
           "project_added_before_host_ms_min": 1e3 * min(added["solve_before"]),
           "project_adds_vs_bare_call_host_ms": res["solve"]["host_ms"] - res["bare"]["host_ms"],
           "comm_after_solve_host_ms": res["step_after_solve"]["host_ms"],
           "before_vs_after": {k: max(a[k] for a in agree) for k in agree[0]} if agree else {}}
    print(json.dumps(out, indent=1), flush=True)
    return out


def compare(before: dict, after: dict) -> dict[str, float]:
    """Largest differences between two solves' links (the same rays)."""
    gain_db = max(abs(10 * np.log10(max(a.path_gain, 1e-30) / max(after[k].path_gain, 1e-30)))
                  for k, a in before.items())
    h = max(float(np.abs(a.h - after[k].h).max() / max(np.abs(a.h).max(), 1e-30)) for k, a in before.items())
    return {"path_gain_db": float(gain_db), "h_relative": h,
            "best_pair_differs": float(sum(a.best_pair != after[k].best_pair for k, a in before.items())),
            "n_paths_differs": float(sum(a.n_paths != after[k].n_paths for k, a in before.items())),
            "los_differs": float(sum(a.los != after[k].los for k, a in before.items()))}


def carrier_numpy(paths, n_rx: int, frequency_hz: float) -> np.ndarray:
    """H at the carrier in numpy from one read of the paths' arrays (the sum in float64):
    the first version of issue #53's solve, before the frozen kernel."""
    a_re, a_im = paths.a
    dr.eval(a_re, a_im, paths.tau)
    a_re, a_im = np.asarray(a_re), np.asarray(a_im)  # [rx, rx_ant, tx, tx_ant, P]
    tau = np.asarray(paths.tau).reshape(n_rx, -1)
    two_pi = np.float32(2 * np.pi)
    phase = (-two_pi * np.float32(frequency_hz)) * np.where(tau == -1, np.float32(0), tau).astype(np.float32)
    phase = phase - two_pi * np.floor(phase * (np.float32(1) / two_pi))
    cos, sin = np.cos(phase)[:, None, None, None, :], np.sin(phase)[:, None, None, None, :]
    h_re = (a_re * cos - a_im * sin).sum(axis=-1, dtype=np.float64)
    h_im = (a_re * sin + a_im * cos).sum(axis=-1, dtype=np.float64)
    return (h_re + 1j * h_im)[:, :, 0, :].astype(np.complex64)


def freeze_trials(n_uav: int, samples: int, reps: int) -> dict:
    """``dr.freeze`` where the shapes do not change: the carrier channel H of a solve's paths.
    ``frozen``: the project's (:func:`~caviar_plugins.rt.solver.carrier_channels`, one kernel
    under ``dr.freeze``), ``drjit``: the same kernel unfrozen, ``numpy``:
    :func:`carrier_numpy`; host time outside kernels, on the paths of solves whose path count
    changes, and the recordings of the frozen function (1: replayed whatever the count).
    (The solver itself cannot be frozen from here: Sionna sizes its path buffer from a count
    it reads back, ``paths_buffer.shrink``, so its later kernels' sizes depend on data.)"""
    from caviar_plugins.rt import solver as rt_solver

    route = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
    radio = plugin(samples, uav_mesh=False).radio
    f = radio.cfg.frequency_hz
    clock = KernelClock()
    diff = 0.0
    counts = set()
    for k in range(reps + 2):
        radio.place({f"u{i}": route.at(20.0 + 40.0 * i + 0.5 * k) for i in range(n_uav)})
        radio.solve(force=True)
        paths = radio.last_paths
        dr.eval(paths.a, paths.tau, paths.valid)
        n_p = paths.tau.shape[-1]
        counts.add(n_p)
        n_ant = radio.w_rx.shape[0] * radio.w_tx.shape[0]
        out = {"numpy": clock("numpy", lambda p=paths: carrier_numpy(p, n_uav, f), k >= 2),
               "frozen": clock("frozen", lambda p=paths: rt_solver.carrier_channels(p, n_uav, f)[0], k >= 2)}
        args = (paths.a[0].array, paths.a[1].array, paths.tau.array, dr.opaque(mi.UInt, n_p),
                dr.opaque(mi.UInt, n_ant), dr.opaque(mi.Float, float(np.float32(f))), n_uav * n_ant)

        def unfrozen(args=args, shape=out["numpy"].shape):
            h_re, h_im = rt_solver.carrier_sums(*args)
            return (np.asarray(h_re) + 1j * np.asarray(h_im)).reshape(shape)

        out["drjit"] = clock("drjit", unfrozen, k >= 2)
        ref = np.abs(out["numpy"]).max()
        diff = max(diff, *(float(np.abs(out[x] - out["numpy"]).max() / ref) for x in ("drjit", "frozen")))
    frozen = rt_solver.FROZEN.get("carrier")
    res = {"uavs": n_uav, "path_counts": sorted(counts), "recordings": getattr(frozen, "n_recordings", None),
           "max_relative_difference": diff, **{k: v["host_ms"] for k, v in clock.summary().items()}}
    print(json.dumps(res), flush=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--uavs", type=int, nargs="+", default=[1, 10])
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--lookahead-steps", type=int, default=40, help="comm steps of the look-ahead item (0: none)")
    ap.add_argument("--lookahead-depths", nargs="+", default=["auto"],
                    help='lookahead_steps to compare (integers or "auto")')
    ap.add_argument("--only-lookahead", action="store_true", help="the look-ahead item only")
    ap.add_argument("--no-freeze", action="store_true", help="skip the dr.freeze trials")
    ap.add_argument("--out", type=pathlib.Path, default=OUT)
    args = ap.parse_args()
    import sionna.rt  # noqa: F401  (it chooses the variant: CUDA where a GPU is found)

    print(f"Dr.Jit variant: {mi.variant()}", flush=True)
    depths = [d if d == "auto" else int(d) for d in args.lookahead_depths]
    rows = [] if args.only_lookahead else [bench_host(n, args.samples, args.reps) for n in args.uavs]
    ahead = [bench_lookahead(n, args.samples, args.lookahead_steps, depths)
             for n in args.uavs] if args.lookahead_steps else []
    frozen = [] if args.no_freeze or args.only_lookahead else [freeze_trials(n, args.samples, args.reps)
                                                               for n in args.uavs]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": machine(), "variant": str(mi.variant()),
                                    "date": time.strftime("%Y-%m-%d"), "rows": rows, "lookahead": ahead,
                                    "freeze": frozen},
                                   indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
