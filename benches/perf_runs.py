"""The run-level items of bench_perf_steps.py: the main job against an earlier commit's
plugins, the osm-traffic link step, and the multi-UAV SAR loop (wall over virtual time)."""

from __future__ import annotations

import contextlib
import os
import pathlib
import shutil
import time

import numpy as np

from caviar_plugins.rt import configure_drjit

configure_drjit()

from bench_common import accuracy_summary, interleaved, machine  # noqa: E402, F401

OUT = pathlib.Path("docs/results")
ROUTE = "central_park_path0_scene.csv"


ISSUE_24_FILED_AT = "ef1d136"
"""The last commit before issue #24's work: "today's" main job of the issue's target."""


@contextlib.contextmanager
def plugins_at(work: pathlib.Path, rev: str):
    """A git worktree of ``rev`` under ``work`` (removed afterwards, even when a run fails) and
    the environment that runs its plugins: the tree's ``plugins`` first on ``PYTHONPATH``, with
    this checkout's Rust core. Yields (tree, env)."""
    import subprocess

    tree = work / f"tree-{rev}"
    if not tree.exists():
        subprocess.run(["git", "worktree", "add", "--detach", str(tree), rev], check=True)
    try:
        yield tree, {**os.environ, "PYTHONPATH": str(tree / "plugins")}
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(tree)], check=False)


def bench_main_job(work: pathlib.Path, old_rev: str = ISSUE_24_FILED_AT) -> dict:
    """The main job (the SAR blueprint, to the end of its mission), old then new,
    whole wall time:

    * ``old``: the plugins as they were at ``old_rev`` (a git worktree of that commit put
      first on ``PYTHONPATH``; the Rust core is this checkout's): every solve with the UAV
      body runs Sionna's loop, and a hovering UAV is rendered, detected and placed anew;
    * ``new``: this checkout.

    Also per module: the wall time of the steps where the UAV moved and of those where it
    hovered. Links are compared where the UAV was at the same place."""
    import subprocess
    import sys

    import caviar

    exe = pathlib.Path(sys.executable).parent / "caviar-core"
    res: dict = {"old_rev": old_rev}
    logs = {}
    with plugins_at(work, old_rev) as (old_tree, old_env):
        for label, tree, env in (("old", old_tree, old_env), ("new", pathlib.Path.cwd(), None)):
            out = work / f"main-job-{label}"
            t0 = time.perf_counter()
            subprocess.run([str(exe), "run", str(tree / "blueprints/sar/config.toml"), "--quiet", "--out", str(out)],
                           check=True, env=env)
            wall = time.perf_counter() - t0
            log = caviar.load_run(out)
            status = log.status
            comm = log.timings.filter(log.timings["module"] == "comm")["wall_s"].to_numpy()
            res[label] = {"wall_s": wall, "run_wall_s": float(status["wall_s"]), "steps": int(status["steps_done"]),
                          "virtual_s": float(status["virtual_time_s"]),
                          "comm_s_per_step_median": float(np.median(comm)),
                          "comm_share_pct": 100 * float(comm.sum()) / float(status["wall_s"]),
                          "modules_s": module_times(log)}
            logs[label] = log
            print(f"main job {label}: {res[label]}", flush=True)
    res["ratio"] = res["new"]["wall_s"] / res["old"]["wall_s"]
    # The two missions drift apart after the first rescue (hover times follow the throughput):
    # links are compared where the UAV was at the same place (to the millimetre), not by step.
    a, b = (links_by_place(logs[k]) for k in ("old", "new"))
    same = [a[key] == pair for key, pair in b.items() if key in a]
    res["links_compared"] = len(same)
    res["links_new"] = len(b)
    res["same_best_pair_pct"] = float(100 * np.mean(same)) if same else None
    return res


def module_times(log) -> dict:
    """Per module, the wall seconds of the steps in which the UAV moved and of those in
    which it hovered (did not move since the step before)."""
    import polars as pl

    pos = log.topic("3D.mobility.positions").sort("step")
    xyz = np.array([[r[c] for c in "xyz"] for r in pos["position"].to_list()])
    moved = pl.DataFrame({"step": pos["step"],
                          "moved": np.r_[True, np.any(np.diff(xyz, axis=0) != 0, axis=1)]})
    t = log.timings.join(moved, on="step", how="left").with_columns(pl.col("moved").fill_null(True))
    out = {}
    for (module,), g in t.group_by("module"):
        out[module] = {"moved_s": round(float(g.filter(pl.col("moved"))["wall_s"].sum()), 2),
                       "hovered_s": round(float(g.filter(~pl.col("moved"))["wall_s"].sum()), 2)}
    out["steps_moved"] = int(moved["moved"].sum())
    return dict(sorted(out.items()))


def links_by_place(log) -> dict:
    """(UE, position rounded to the millimetre) -> the best pair of a run's link there."""
    pos = log.topic("3D.mobility.positions")
    where = {(r["step"], r["UE_Id"]): tuple(round(r["position"][c], 3) for c in "xyz")
             for r in pos.select("step", "UE_Id", "position").to_dicts()}
    links = log.topic("communications.link").select("step", "UE_Id", "best_pair").to_dicts()
    return {(r["UE_Id"], where[(r["step"], r["UE_Id"])]): r["best_pair"] for r in links
            if (r["step"], r["UE_Id"]) in where}


TRAFFIC = pathlib.Path("blueprints/osm-traffic/config.toml")


def bench_traffic_step(work: pathlib.Path, steps: int, skip: int = 10, reps: int = 2,
                       old_rev: str = ISSUE_24_FILED_AT) -> dict:
    """The osm-traffic blueprint (about 50 vehicles and 20 persons from SUMO moving through
    the Helsinki scene, 5 connected cars and a UAV as receivers, 1e5 samples) for ``steps``
    steps, in four variants, each run ``reps`` times in turn (old, loop, new, floor, old, ...):

    * ``old``: the plugins as they were at ``old_rev`` (before #24; a git worktree of that
      commit first on ``PYTHONPATH``, this checkout's Rust core): Sionna's loop every step;
    * ``loop``: this checkout with ``shoot_cache = false``: Sionna's loop every step, with
      the link's other per-step work as it is now;
    * ``new``: the default, the shoot cache with the pools' boxes as moving objects;
    * ``floor``: the shoot cache without the traffic boxes (``scatterers = false``; the UAV's
      body still moves): what serving six receivers from recorded bounces costs, about the
      least ``new`` can cost.

    A step's time is the sum of its modules' wall times (SUMO, the UAV, the link, the
    monitor), median over the steps after the first ``skip`` of all runs of a variant (SUMO's
    vehicles depart over the first 10 s; kernel compilation, the first solve of the geometry
    and the recording come before).

    Accuracy: the new run's positions replayed step by step into a ``sionna-traffic-link``
    with the default settings; after each step its paths (the cache's), Sionna's loop (the
    old path) and Sionna's loop on the next seed (the Monte Carlo noise) are compared, per
    connected receiver, with Sionna's loop with an 8x larger specular-chain table on the same
    geometry."""
    import subprocess
    import sys

    import polars as pl
    import tomllib

    import caviar
    from caviar._host import check_params
    from caviar.plugin import Context, Inbox, Message
    from caviar_plugins.schema import POSITIONS
    from caviar_plugins.traffic.link import SionnaTrafficLink

    exe = pathlib.Path(sys.executable).parent / "caviar-core"
    variants = {"old": [], "loop": ["modules.comm.params.raytracing.shoot_cache=false"], "new": [],
                "floor": ["modules.comm.params.scatterers=false"]}
    per_step: dict[str, list] = {k: [] for k in variants}
    comm: dict[str, list] = {k: [] for k in variants}
    res: dict = {"steps": steps, "reps": reps, "old_rev": old_rev}
    log = None
    with plugins_at(work, old_rev) as (old_tree, old_env):
        for rep in range(reps):
            for label, sets in variants.items():
                out = work / f"traffic-{label}-{rep}"
                tree, env = (old_tree, old_env) if label == "old" else (pathlib.Path.cwd(), None)
                subprocess.run([str(exe), "run", str(tree / TRAFFIC), "--quiet", "--out", str(out), "--set",
                                f"episode.steps={steps}", *(x for kv in sets for x in ("--set", kv))],
                               check=True, env=env)
                run = caviar.load_run(out)
                t = run.timings.filter(pl.col("step") >= skip)
                per_step[label] += t.group_by("step").agg(pl.col("wall_s").sum())["wall_s"].to_list()
                comm[label] += t.filter(pl.col("module") == "comm")["wall_s"].to_list()
                res.setdefault(label, {"runs_wall_s": [], "sumo_step_s": []})
                res[label]["runs_wall_s"].append(float(run.status["wall_s"]))
                res[label]["sumo_step_s"].append(float(np.median(t.filter(pl.col("module") == "traffic")["wall_s"])))
                if label == "new":
                    log = run
                    statuses = run.topic(caviar.STATUS_TOPIC)
                    res[label]["status"] = statuses["value"].to_list()[-1] if len(statuses) else None
    for label in variants:
        res[label].update(step_s_median=float(np.median(per_step[label])),
                          comm_s_median=float(np.median(comm[label])))
    res["ratio"] = res["new"]["step_s_median"] / res["old"]["step_s_median"]
    res["loop_ratio"] = res["loop"]["step_s_median"] / res["old"]["step_s_median"]
    res["new_over_loop"] = res["new"]["step_s_median"] / res["loop"]["step_s_median"]
    res["floor_ratio"] = res["floor"]["step_s_median"] / res["old"]["step_s_median"]
    res["target_ratio"] = 0.35
    assert log is not None
    traffic = log.topic("3D.mobility.traffic")
    res["vehicles_median"] = float(np.median(traffic["vehicles"].to_numpy()[skip:]))
    res["persons_median"] = float(np.median(traffic["persons"].to_numpy()[skip:]))

    cfg = tomllib.loads(TRAFFIC.read_text())["modules"]["comm"]["params"]
    plugin = SionnaTrafficLink()
    plugin.setup(Context(name="comm", params=check_params(SionnaTrafficLink, cfg), seed=1, ts=1.0, steps=None, every=1,
                         offset=0, run_dir=work, config_dir=TRAFFIC.parent.resolve()))
    radio = plugin.radio
    rays = radio.cfg.raytracing
    from caviar_plugins.rt.scene import sionna_rt

    solver = sionna_rt().PathSolver()

    def sionna(table: int, seed: int) -> np.ndarray:
        options = {**rays.path_options(seed), "max_num_paths_per_src": table}
        paths = solver(radio.scene, synthetic_array=True, **options)
        return paths.cfr(frequencies=np.array([0.0]), normalize_delays=False, out_type="numpy")[:, :, 0, :, 0, 0]

    pos = log.topic(POSITIONS)
    labels = ("old", "new", "other_seed")
    errors: dict[str, list] = {k: [] for k in labels}
    same: dict[str, list] = {k: [] for k in labels}
    for step in range(steps):
        rows = pos.filter(pl.col("step") == step).to_dicts()
        msgs = [Message(POSITIONS, {k: v for k, v in r.items()
                                    if v is not None and k not in ("step", "time", "topic", "source")})
                for r in rows]
        list(plugin.step(float(step), Inbox(msgs)))
        if step < skip:
            continue
        h = {"new": radio.last_paths.cfr(frequencies=np.array([0.0]), normalize_delays=False,
                                         out_type="numpy")[:, :, 0, :, 0, 0],
             "old": sionna(rays.max_num_paths_per_src, radio.seed),
             "other_seed": sionna(8 * rays.max_num_paths_per_src, radio.seed + 1)}
        ref = sionna(8 * rays.max_num_paths_per_src, radio.seed)
        for i in range(len(ref)):
            ref_gain = np.mean(np.abs(ref[i]) ** 2)
            if ref_gain == 0:  # a parked receiver (its car not in the scene)
                continue
            ref_best = np.argmax(radio_gains(radio, ref[i]))
            for label in labels:
                gain = np.mean(np.abs(h[label][i]) ** 2)
                errors[label].append(abs(10 * np.log10(max(gain, 1e-30) / ref_gain)))
                same[label].append(int(np.argmax(radio_gains(radio, h[label][i])) == ref_best))
    accuracy = accuracy_summary(errors, same)
    accuracy["links"] = len(errors["new"])
    accuracy["served_from_cache"] = radio.shoot_cache.connects if radio.shoot_cache else 0
    res["accuracy"] = accuracy
    print(f"traffic: step {res['old']['step_s_median']:.3f} s -> {res['new']['step_s_median']:.3f} s "
          f"({res['ratio']:.2f}x; floor {res['floor']['step_s_median']:.3f} s = {res['floor_ratio']:.2f}x); "
          f"{res}", flush=True)
    return res


def radio_gains(radio, h: np.ndarray) -> np.ndarray:
    from caviar_plugins.radio.beams import beam_gains

    return beam_gains(h, radio.w_tx, radio.w_rx)


def sar_config(n: int, duration: float, samples: int, new: bool, forecast: int) -> str:
    """bench_scaling's SAR loop, with the new code paths (batches, look-ahead) or the old."""
    from bench_scaling import config

    batch = f"batch = {str(new).lower()}"
    return config(n, duration, samples, uav_extra=f"forecast_steps = {forecast if new else 0}\n", camera=batch,
                  comm=f"uav_mesh = false, lookahead = true, lookahead_steps = {forecast}" if new else "",
                  detector=batch)


def bench_sar(n: int, duration: float, samples: int, forecast: int, work: pathlib.Path) -> dict:
    import polars as pl

    import caviar
    from caviar.report import summary
    from caviar_plugins.rt.shoot_cache import ShootCache

    res: dict = {"uavs": n, "virtual_s": duration, "lookahead_steps": forecast}
    logs = {}
    # new_without_cull: the new path testing every target at every reflection, as Sionna
    # does (ShootCache.cull_behind = False): what the cull of targets behind a plane saves.
    for label, new in (("old", False), ("new", True), ("new_without_cull", True)):
        cfg = work / f"sar-{n}-{label}.toml"
        cfg.write_text(sar_config(n, duration, samples, new, forecast))
        run = work / f"run-{n}-{label}"
        if run.exists():
            shutil.rmtree(run)
        ShootCache.cull_behind = label != "new_without_cull"
        try:
            logs[label] = caviar.Simulation.from_toml(cfg, out=run).run()
        finally:
            ShootCache.cull_behind = True
        s = summary(run)
        m = s["modules"]
        res[label] = {"wall_s": s["wall_s"], "tp_tv": s["wall_s"] / s["virtual_time_s"],
                      **{f"{k}_s_per_step": m[k]["wall_s_per_step"] for k in ("comm", "camera", "detector")}}
        print(f"SAR {n} UAV(s) {label}: T_p/T_v = {res[label]['tp_tv']:.2f} {res[label]}", flush=True)
    res["ratio"] = res["new"]["tp_tv"] / res["old"]["tp_tv"]
    res["cull_ratio"] = res["new"]["tp_tv"] / res["new_without_cull"]["tp_tv"]
    # The first solve (steps 0..forecast, traced together) runs Sionna's own loop on several
    # threads, which is not reproducible to the path: its links are left out.
    a, b = (logs[k].topic("communications.link").sort(["step", "UE_Id"]).filter(pl.col("step") > forecast)
            for k in ("new", "new_without_cull"))
    gain = np.abs(a["path_gain_db"].to_numpy() - b["path_gain_db"].to_numpy())
    res["cull_vs_without"] = {
        "links": len(a), "from_step": forecast + 1,
        "best_pair_differs": int((a["best_pair"].to_numpy() != b["best_pair"].to_numpy()).sum()),
        "n_paths_differs": int((a["n_paths"].to_numpy() != b["n_paths"].to_numpy()).sum()),
        "path_gain_diff_db_max": float(gain.max()) if len(gain) else None,
    }
    # Accuracy of the new run's links against the old run's (every step traced, UAV bodies on).
    a, b = (logs[k].topic("communications.link").sort(["step", "UE_Id"]) for k in ("old", "new"))
    thr_a, thr_b = a["best_throughput"].to_numpy(), b["best_throughput"].to_numpy()
    res["accuracy_vs_old"] = {
        "links": len(a),
        "same_best_pair_pct": float(100 * np.mean(a["best_pair"].to_numpy() == b["best_pair"].to_numpy())),
        "best_throughput_error_mbps_median": float(np.median(np.abs(thr_a - thr_b))),
        "best_throughput_error_mbps_p95": float(np.percentile(np.abs(thr_a - thr_b), 95)),
        "old_best_throughput_mbps_median": float(np.median(thr_a)),
        "los_agreement_pct": float(100 * np.mean(a["los"].to_numpy() == b["los"].to_numpy())),
        "note": "new = look-ahead with uav_mesh = false; old = every step traced with the UAV bodies (default). "
                "Look-ahead against every step traced with uav_mesh = false is exact up to float32 rounding "
                "(tests/test_perf_correctness.py): the differences here are the UAV bodies'.",
    }
    print(f"  accuracy: {res['accuracy_vs_old']}", flush=True)
    return res
