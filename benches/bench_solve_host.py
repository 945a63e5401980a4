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

"project adds" = the host time of ``solve`` less that of ``bare`` (the issue's target:
<= 2 ms); the comm step after the solve: ``step_after_solve`` (target: <= 2 ms).

``--freeze`` adds the trials of ``dr.freeze`` (see :func:`freeze_trials`).

Writes docs/results/solve-host.json (the machine from ``bench_common.machine()``).
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
    paths = radio.tracer.solve(max_depth=c.max_depth, samples_per_src=c.samples_per_src, synthetic_array=True,
                               los=c.los, specular_reflection=c.specular_reflection,
                               diffuse_reflection=c.diffuse_reflection, refraction=c.refraction,
                               diffraction=c.diffraction, seed=radio.seed)
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


def plugin(samples: int, **params):
    from caviar.plugin import Context
    from caviar_plugins.radio.sionna_link import SionnaLink, SionnaLinkParams

    p = SionnaLinkParams(samples_per_src=samples, shoot_cache=False, threads=1, **params)
    link = SionnaLink()
    link.setup(Context(name="comm", params=p, seed=1, ts=0.5, steps=None, every=1, offset=0,
                       run_dir=pathlib.Path("."), config_dir=pathlib.Path(".")))
    return link


def inbox(positions: dict[str, np.ndarray], t: float) -> list:
    from caviar.plugin import Message

    return [Message("3D.mobility.positions", {"UE_type": "UAV", "UE_Id": ue, "position":
                                              {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])}},
                    source=ue, step=int(t / 0.5), time=t) for ue, p in positions.items()]


def bench_host(n_uav: int, samples: int, reps: int) -> dict:
    route = Path(read_waypoints(DATA / "central_park_path0_scene.csv"))
    starts = np.linspace(0.0, 0.9 * route.length, n_uav)
    link = plugin(samples)
    radio = link.radio
    c = radio.cfg
    bare_solver = radio.rt.PathSolver()
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
    solve_inside: list[float] = []
    original_solve = radio.solve

    def timed_solve(force: bool = False):
        out = clock("solve_in_step", lambda: original_solve(force), keep=True)
        r = clock.rows["solve_in_step"][-1]
        solve_inside.append(r[0] - r[1] - r[2])
        return out

    place_inside: list[float] = []
    original_place = radio.place

    def timed_place(positions, **kw):
        clock("place_in_step", lambda: original_place(positions, **kw))
        r = clock.rows["place_in_step"].pop()
        place_inside.append(r[0] - r[1] - r[2])

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
        before = clock("solve_before", lambda: solve_before(radio), keep)
        agree.append(compare(before, original_solve(force=True)))

    placed = {"place_before": lambda pos, keep: clock("place_before", lambda: place_before(radio, pos), keep),
              "place": lambda pos, keep: clock("place", lambda: original_place(pos), keep)}
    solved = {"bare": lambda keep: clock("bare", bare, keep),
              "bare_cfr": lambda keep: clock("bare_cfr", bare_cfr, keep), "solve_before": solve_both,
              "solve": lambda keep: clock("solve", lambda: original_solve(force=True), keep)}
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
    res = clock.summary()
    step_host = [r[0] - r[1] - r[2] for r in clock.rows["step"]]
    res["step_place"] = {"host_ms": 1e3 * statistics.median(place_in_step)}
    res["step_after_solve"] = {"host_ms": 1e3 * statistics.median(
        [a - b - c for a, b, c in zip(step_host, solve_inside, place_in_step, strict=True)])}
    out = {"uavs": n_uav, "samples_per_src": samples, "reps": reps, "items": res,
           "project_adds_host_ms": res["solve"]["host_ms"] - res["bare"]["host_ms"],
           "project_added_before_host_ms": res["solve_before"]["host_ms"] - res["bare"]["host_ms"],
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--uavs", type=int, nargs="+", default=[1, 10])
    ap.add_argument("--samples", type=int, default=1_000_000)
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--out", type=pathlib.Path, default=OUT)
    args = ap.parse_args()
    import sionna.rt  # noqa: F401  (it chooses the variant: CUDA where a GPU is found)

    print(f"Dr.Jit variant: {mi.variant()}", flush=True)
    rows = [bench_host(n, args.samples, args.reps) for n in args.uavs]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": machine(), "variant": str(mi.variant()),
                                    "date": time.strftime("%Y-%m-%d"), "rows": rows}, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
