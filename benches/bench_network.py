"""Benchmark of the radio network (issue #23): 21 cells (7 sites × 3 sectors) and 100 UEs
(60 cars, 30 pedestrians, 10 UAVs) in the osm-city scene, 0.5 ms slots, 0.1 s steps.

Runs of the same virtual time, in one process:

- ``sys only``: the channels are traced once and held; every step runs the
  measurements, mobility management and the Sionna SYS slots: slot by slot on a
  wideband channel (the baseline), ``--harq-processes`` slots per call on a wideband
  channel, and the same on ``--subbands`` subbands (frequency-selective: PF per subband,
  EESM);
  and the last through ``torch.compile`` (``LinkSettings.compile``);
- ``with rt``: the last, and every UE's paths are ray traced again every ``--refresh``
  seconds of virtual time (all sites in one solve), the channel evolving in between as
  the UEs move (each path's phase at its Doppler shift), evaluated every step;
- ``plugin``: the ``radio-network`` plugin itself, stepped on the same UEs' positions, with
  ray tracing, beams and the uplink, ``interference = "scheduled"``: with full buffers, and
  with FTP model 3 load both ways (queues, buffer-aware scheduling, ``network.transfers``).
  The delays of its files go in the results too.

Writes ``docs/results/network.json`` with T_p/T_v of each, the split of a step between
ray tracing, the channel's evolution and the SYS layer, and the machine. Not a test: it
takes minutes.

    .venv/bin/python benches/bench_network.py [--seconds 4.0] [--refresh 1.0]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import time

import numpy as np

from bench_common import machine
from caviar_plugins.network.beams import BeamSettings, all_beam_gains
from caviar_plugins.network.cells import parse_sites
from caviar_plugins.network.downlink import downlink_sinr, received
from caviar_plugins.network.handover import HandoverSettings, MobilityManager
from caviar_plugins.network.raytraced import NETWORK_RAYS, SiteTracer, TracedChannels
from caviar_plugins.network.ues import link_columns
from caviar_plugins.network.uplink import UplinkSettings, uplink
from caviar_plugins.radio.link_level import LinkLevel, LinkSettings  # (link_level's, as a --baseline checkout has it)

ROOT = pathlib.Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "results" / "network.json"
SCENE = ROOT / "blueprints" / "osm-city" / "scene" / "scene.xml"
TS, SCS, NUM_PRB = 0.1, 30e3, 51


def sites() -> list[dict]:
    """7 sites: a centre and a ring of 6 at 280 m, masts 35 m high, 3 sectors each."""
    out = [{"name": "s0", "position": [0.0, 0.0, 35.0]}]
    for k in range(6):
        a = np.radians(60 * k + 30)
        out.append({"name": f"s{k + 1}", "position": [280 * np.cos(a), 280 * np.sin(a), 35.0]})
    for s in out:
        s["azimuths_deg"], s["downtilt_deg"] = [30.0, 150.0, 270.0], 6.0
    return out


def ues(rng: np.random.Generator, n: int = 100):
    """``n`` UEs (60 % cars, 30 % pedestrians, 10 % UAVs): start positions and velocities
    (cars 10 m/s, pedestrians 1.4 m/s, UAVs 8 m/s at 40 m)."""
    kinds = ["car"] * (6 * n // 10) + ["pedestrian"] * (3 * n // 10)
    kinds += ["uav"] * (n - len(kinds))
    speed = {"car": 10.0, "pedestrian": 1.4, "uav": 8.0}
    pos = np.column_stack([rng.uniform(-380, 380, n), rng.uniform(-380, 380, n),
                           [40.0 if k == "uav" else 1.5 for k in kinds]])
    heading = rng.uniform(0, 2 * np.pi, n)
    vel = np.column_stack([np.cos(heading), np.sin(heading), np.zeros(n)]) * [[speed[k]] for k in kinds]
    return kinds, pos, vel


def compile_outside(settings: LinkSettings | tuple[LinkSettings, ...], n_cell: int, n_ue: int) -> float:
    """Compiles a link level of these settings (one link's, or several links' run together)
    outside the timed loop (once per process), on a link level of its own; returns the seconds
    it took."""
    a = time.perf_counter()
    warm = LinkLevel(settings, n_cell, seed=9)
    links = getattr(warm, "links", (settings,))  # (a baseline's link level runs one link)
    zeros, serving = np.zeros((links[0].harq_processes, n_ue, links[0].subbands)), np.zeros(n_ue, dtype=int)
    for _ in range(2):
        if len(links) > 1:
            warm.run_links([zeros] * len(links), serving, len(zeros))
        else:
            warm.run(zeros, serving)
    return time.perf_counter() - a


def link_levels(net) -> list:
    """The radio-network plugin's link levels: one for both directions (since 2026-11-29), or a
    baseline's downlink's and uplink's."""
    return [link for link in (net.link, getattr(net, "ul_link", None)) if link is not None]


def run(seconds: float, refresh: float | None, tracer: SiteTracer, cells, pos0, vel, initial: TracedChannels,
        processes: int, subbands: int, compiled: bool = False, beams: BeamSettings | None = None,
        up: UplinkSettings | None = None) -> dict:
    """``refresh`` None: the initial trace's channels held (wideband: the power sum; per
    subband: at the trace's instant); else traced every ``refresh`` s and evolved. ``beams``:
    the SSB beams' path (L1-RSRP, scheduled interfering beams per slot); ``up``: and the
    uplink (power control, the other cells' scheduled UEs, a second link level on PUSCH)."""
    settings = LinkSettings(num_prb=NUM_PRB, subcarrier_spacing_hz=SCS, harq_processes=processes,
                            subbands=subbands, compile=compiled)
    link = LinkLevel(settings, len(cells), seed=1)
    compile_s = compile_outside(settings, len(cells), len(pos0)) if compiled else 0.0
    ul_link = None
    if up is not None:
        ul_settings = dataclasses.replace(settings, direction="uplink", mcs_table=up.mcs_table)
        ul_link = LinkLevel(ul_settings, len(cells), seed=3)
        if compiled:
            compile_s += compile_outside(ul_settings, len(cells), len(pos0))
    mm = MobilityManager(HandoverSettings(), [c.name for c in cells])
    slots = round(TS / link.s.slot_s)
    freqs, weights = settings.subband_frequencies_hz, settings.subband_prbs
    codebooks = None if beams is None else [beams.codebook(cell.array) for cell in cells]
    channels = initial
    held = initial.power_sum_db[..., None] if subbands == 1 else initial.gain_db(pos0, freqs)
    ids, rows = [str(u) for u in range(len(pos0))], np.arange(len(pos0))
    last_sinr = np.full(len(pos0), np.nan)
    t_rt, t_evolve, t_sys, t_beams, t_uplink, t_uplink_sinr = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    steps = round(seconds / TS)
    t0 = time.perf_counter()
    for k in range(steps):
        # The plugin's step (radio-network: network.downlink's received and downlink_sinr, the
        # mobility manager's rows, the link level on UE columns), on channels held or evolved here.
        t = k * TS
        pos = pos0 + vel * t
        a = time.perf_counter()
        if refresh is not None and k and k % round(refresh / TS) == 0:
            channels = tracer.trace(pos)
        b = time.perf_counter()
        at = pos0 if refresh is None else pos
        gains = held if refresh is None else channels.gain_db(pos, freqs)
        beam_gains = None
        if codebooks is not None:
            beam_gains = all_beam_gains(cells, codebooks, channels.amplitudes(at, freqs), channels.departure)
        c = time.perf_counter()
        t_rt, t_evolve = t_rt + b - a, t_evolve + c - b
        rx, wideband, rsrp, best = received(cells, gains, weights, NUM_PRB, beam_gains)
        mm.ensure(len(pos0))
        mm.update_rows(t, rows, ids, rsrp, last_sinr)
        serving = mm.serving_cell[rows]
        chosen = None if beam_gains is None or best is None else (beam_gains, best)
        per_slot, sinr, _ = downlink_sinr(cells, rx, wideband, serving, None, noise_figure_db=7.0, scheduled=False,
                                          beams=chosen, slots=slots, subband_prbs=weights)
        t_beams += time.perf_counter() - c if chosen is not None else 0.0
        link.run(*link_columns(per_slot, serving, rows, slots))
        if up is not None and ul_link is not None:
            d = time.perf_counter()
            _, ul_sinr = uplink(cells, up, serving, rx, beam_gains, best, NUM_PRB, SCS, slots)
            t_uplink_sinr += time.perf_counter() - d
            ul_link.run(*link_columns(ul_sinr, serving, rows, slots))
            t_uplink += time.perf_counter() - d
        last_sinr = np.where(serving >= 0, sinr, np.nan)
        t_sys += time.perf_counter() - c
    wall = time.perf_counter() - t0
    return {"harq_processes": processes, "subbands": subbands, "compiled": compiled,
            "compile_s": round(compile_s, 1), "virtual_s": seconds, "wall_s": round(wall, 3),
            "tp_tv": round(wall / seconds, 3), "rt_s": round(t_rt, 3), "evolve_s": round(t_evolve, 3),
            "sys_s": round(t_sys - t_beams - t_uplink, 3), "beams_s": round(t_beams, 3),
            "uplink_s": round(t_uplink, 3), "uplink_sinr_s": round(t_uplink_sinr, 3), "slots": steps * slots,
            "ms_per_slot": round(1e3 * t_sys / (steps * slots), 3), "covered_ues": int((serving >= 0).sum())}


def plugin_run(seconds: float, refresh: float, samples: int, kinds: list[str], pos0, vel,
               traffic: dict | None, compiled: bool = True, ue_reports: str = "per-ue",
               groups_per_call: int = 1, cuda_graphs: bool = False) -> dict:
    """The ``radio-network`` plugin stepped on the UEs' positions (its messages collected; its UE
    reports ``ue_reports``; ``groups_per_call`` groups of slots a compiled call; ``cuda_graphs``:
    each compiled group replayed as a CUDA graph):
    T_p/T_v of its steps after the first (the first traces and compiles), and, with a load,
    its completed files' delays."""
    import tempfile

    from caviar._host import Hosted, check_params
    from caviar.plugin import Inbox, Message
    from caviar_plugins.network.plugin import RadioNetwork
    from caviar_plugins.schema import position_payload

    params = {"sites": sites(), "carrier_hz": 3.5e9, "bandwidth_hz": 20e6, "tx_power_dbm": 43.0, "array": [4, 4],
              "subcarrier_spacing_hz": SCS, "harq_processes": 8, "subbands": 8, "compile": compiled,
              "channel": "ray-traced", "interference": "scheduled", "antenna_height_m": 0.0,
              "scene": str(SCENE), "raytracing": {"max_depth": 2, "samples_per_src": samples},
              "evolution": {"refresh_s": refresh},
              "beams": {"horizontal": 4, "vertical": 1}, "uplink": {}}
    if ue_reports != "per-ue":  # (a baseline's plugins may not know the setting)
        params["ue_reports"] = ue_reports
    if traffic is not None:
        params["traffic"] = traffic
    if groups_per_call > 1:  # (likewise)
        params["groups_per_call"] = groups_per_call
    if cuda_graphs:
        params["cuda_graphs"] = True
    hosted = Hosted("net", RadioNetwork(), check_params(RadioNetwork, params))
    with tempfile.TemporaryDirectory() as run_dir:
        hosted.setup(seed=1, ts=TS, steps=None, every=1, offset=0, run_dir=run_dir, config_dir=str(ROOT))
        assert hosted.ctx is not None
        net = hosted.plugin
        if compiled:
            for link in link_levels(net):
                compile_outside(getattr(link, "links", link.s), len(net.cells), len(pos0))
        out: list[tuple[str, object]] = []
        steps = round(seconds / TS)
        first = 0.0
        t0 = time.perf_counter()
        for k in range(steps + 1):
            t = k * TS
            pos = pos0 + vel * t
            inbox = Inbox([Message("3D.mobility.positions", position_payload(f"{kinds[u]}{u}", pos[u], kinds[u]),
                                   step=k, time=t) for u in range(len(pos))])
            hosted.ctx.step = k
            out += [(m[0], m[1]) for m in hosted.plugin.step(t, inbox) or ()]
            if k == 0:
                first = time.perf_counter() - t0
                t0 = time.perf_counter()
        wall = time.perf_counter() - t0
    files = [d for topic, d in out if topic == "network.transfers" and isinstance(d, dict) and not d.get("lost")]
    ues = [d for topic, d in out if topic == "network.ue" and isinstance(d, dict)]
    if any(topic == "network.ues" for topic, _ in out):
        from caviar_plugins.network.ues import table_rows  # (here: a baseline's plugins may not have it)

        ues += [r for topic, d in out if topic == "network.ues" for r in table_rows(d)]
    result = {"virtual_s": seconds, "wall_s": round(wall, 3), "tp_tv": round(wall / seconds, 3),
              "first_step_s": round(first, 1), "ue_reports": len(ues),
              "dl_throughput_mbps_mean": round(float(np.mean([u["throughput_mbps"] for u in ues])), 3)}
    for direction in ("downlink", "uplink"):
        mine = [f for f in files if f["direction"] == direction]
        if mine:
            delay = np.array([f["delay_s"] for f in mine])
            result[f"{direction}_files"] = {
                "delivered": len(mine), "delay_s": {p: round(float(np.percentile(delay, q)), 4)
                                                    for p, q in (("p5", 5), ("p50", 50), ("p95", 95))},
                "upt_mbps_p50": round(float(np.median([f["upt_mbps"] for f in mine])), 3)}
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=4.0, help="virtual seconds per run")
    ap.add_argument("--refresh", type=float, default=1.0, help="ray-tracing refresh, virtual seconds")
    ap.add_argument("--samples", type=int, default=20000, help="rays per site")
    ap.add_argument("--harq-processes", type=int, default=8, help="slots per call (1: the slot-by-slot baseline)")
    ap.add_argument("--subbands", type=int, default=8, help="frequencies of the channel (PF per subband, EESM)")
    ap.add_argument("--plugin-only", type=int, metavar="N_UE",
                    help="only the plugin, full buffers, with N_UE UEs; prints its result as JSON (the GPU check)")
    ap.add_argument("--eager", action="store_true", help="with --plugin-only: without torch.compile")
    ap.add_argument("--ue-reports", default="per-ue", choices=["per-ue", "table"],
                    help="with --plugin-only: the network's UE reports (a message a UE, or a table a step)")
    ap.add_argument("--groups-per-call", type=int, default=1,
                    help="with --plugin-only: groups of slots a compiled call (groups_per_call; not with --eager)")
    ap.add_argument("--cuda-graphs", action="store_true",
                    help="with --plugin-only: each compiled group a CUDA graph (cuda_graphs; not with --eager)")
    args = ap.parse_args()
    if args.plugin_only:
        kinds, pos0, vel = ues(np.random.default_rng(7), args.plugin_only)
        result = plugin_run(args.seconds, args.refresh, args.samples, kinds, pos0, vel, None, compiled=not args.eager,
                            ue_reports=args.ue_reports, groups_per_call=args.groups_per_call,
                            cuda_graphs=args.cuda_graphs)
        print(json.dumps({"cells": 21, "ues": args.plugin_only, "compiled": not args.eager,
                          "ue_reports_as": args.ue_reports, "groups_per_call": args.groups_per_call,
                          "cuda_graphs": args.cuda_graphs, **result,
                          "machine": machine()}))
        return
    cells = parse_sites(sites(), {"tx_power_dbm": 43.0, "carrier_hz": 3.5e9, "bandwidth_hz": 20e6,
                                  "array": [4, 4]})
    kinds, pos0, vel = ues(np.random.default_rng(7))
    tracer = SiteTracer(str(SCENE), dataclasses.replace(NETWORK_RAYS, max_depth=2, samples_per_src=args.samples), cells,
                        seed=1)
    a = time.perf_counter()
    initial = tracer.trace(pos0)
    first_trace = time.perf_counter() - a
    print(f"first trace (kernel compilation included): {first_trace:.2f} s", flush=True)
    d, sub = args.harq_processes, args.subbands
    baseline = run(args.seconds, None, tracer, cells, pos0, vel, initial, 1, 1)
    print("sys only, slot by slot, wideband", baseline, flush=True)
    wideband = run(args.seconds, None, tracer, cells, pos0, vel, initial, d, 1)
    print(f"sys only, {d} HARQ processes per call, wideband", wideband, flush=True)
    eager = run(args.seconds, None, tracer, cells, pos0, vel, initial, d, sub)
    print(f"sys only, {d} HARQ processes per call, {sub} subbands", eager, flush=True)
    sys_only = run(args.seconds, None, tracer, cells, pos0, vel, initial, d, sub, compiled=True)
    print(f"sys only, {d} HARQ processes per call, {sub} subbands, compiled", sys_only, flush=True)
    with_rt = run(args.seconds, args.refresh, tracer, cells, pos0, vel, initial, d, sub, compiled=True)
    print("with rt", with_rt, flush=True)
    beams = BeamSettings(horizontal=4, vertical=1)  # the 4×4 panels' SSB sweep
    sys_only_beams = run(args.seconds, None, tracer, cells, pos0, vel, initial, d, sub, compiled=True, beams=beams)
    print("sys only, beams", sys_only_beams, flush=True)
    with_rt_beams = run(args.seconds, args.refresh, tracer, cells, pos0, vel, initial, d, sub, compiled=True,
                        beams=beams)
    print("with rt, beams", with_rt_beams, flush=True)
    up = UplinkSettings()
    sys_only_up = run(args.seconds, None, tracer, cells, pos0, vel, initial, d, sub, compiled=True, beams=beams,
                      up=up)
    print("sys only, beams, uplink", sys_only_up, flush=True)
    with_rt_up = run(args.seconds, args.refresh, tracer, cells, pos0, vel, initial, d, sub, compiled=True,
                     beams=beams, up=up)
    print("with rt, beams, uplink", with_rt_up, flush=True)
    plugin_full = plugin_run(args.seconds, args.refresh, args.samples, kinds, pos0, vel, None)
    print("plugin, rt, beams, uplink, full buffer", plugin_full, flush=True)
    ftp = {"downlink": "ftp3", "uplink": "ftp3", "ftp": {"file_bytes": 512000, "arrival_rate_hz": 1.0}}
    plugin_ftp = plugin_run(args.seconds, args.refresh, args.samples, kinds, pos0, vel, ftp)
    print("plugin, rt, beams, uplink, FTP model 3", plugin_ftp, flush=True)
    result = {
        "cells": len(cells), "ues": len(pos0), "ue_types": {k: kinds.count(k) for k in sorted(set(kinds))},
        "slot_s": 1e-3 * 15e3 / SCS, "step_s": TS, "rt_refresh_s": args.refresh, "samples_per_src": args.samples,
        "harq_processes": d, "subbands": sub, "tp_tv_sys_only": sys_only["tp_tv"], "tp_tv_with_rt": with_rt["tp_tv"],
        "tp_tv_sys_only_slot_by_slot": baseline["tp_tv"], "tp_tv_sys_only_wideband": wideband["tp_tv"],
        "speedup_of_harq_batching": round(baseline["wall_s"] / wideband["wall_s"], 2),
        "cost_of_subbands": round(eager["wall_s"] / wideband["wall_s"], 2),
        "speedup_of_torch_compile": round(eager["wall_s"] / sys_only["wall_s"], 2),
        "sys_share_of_step": round(with_rt["sys_s"] / with_rt["wall_s"], 3),
        "rt_share_of_step": round(with_rt["rt_s"] / with_rt["wall_s"], 3),
        "evolve_share_of_step": round(with_rt["evolve_s"] / with_rt["wall_s"], 3),
        "tp_tv_sys_only_beams": sys_only_beams["tp_tv"], "tp_tv_with_rt_beams": with_rt_beams["tp_tv"],
        "tp_tv_sys_only_beams_uplink": sys_only_up["tp_tv"], "tp_tv_with_rt_beams_uplink": with_rt_up["tp_tv"],
        "uplink": dataclasses.asdict(up),
        "beams": {"horizontal": beams.horizontal, "vertical": beams.vertical},
        "cost_of_beams_sys_only": round(sys_only_beams["wall_s"] / sys_only["wall_s"], 2),
        "cost_of_beams_with_rt": round(with_rt_beams["wall_s"] / with_rt["wall_s"], 2),
        "tp_tv_plugin_full_buffer": plugin_full["tp_tv"], "tp_tv_plugin_ftp": plugin_ftp["tp_tv"],
        "cost_of_ftp_load": round(plugin_ftp["wall_s"] / plugin_full["wall_s"], 2), "ftp": ftp,
        "targets": {"tp_tv_sys_only": 1.0, "tp_tv_with_rt": 3.0, "tp_tv_sys_only_beams_uplink": 1.5,
                    "tp_tv_with_rt_beams_uplink": 4.0},
        "runs": {"sys_only_slot_by_slot": baseline, "sys_only_wideband": wideband, "sys_only_eager": eager,
                 "sys_only": sys_only,
                 "with_rt": with_rt, "sys_only_beams": sys_only_beams, "with_rt_beams": with_rt_beams,
                 "sys_only_beams_uplink": sys_only_up, "with_rt_beams_uplink": with_rt_up,
                 "plugin_full_buffer": plugin_full, "plugin_ftp": plugin_ftp},
        "first_trace_s": round(first_trace, 2),
        "machine": machine(),
    }
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: result[k] for k in ("tp_tv_sys_only", "tp_tv_with_rt", "tp_tv_sys_only_beams",
                                             "tp_tv_with_rt_beams", "tp_tv_sys_only_beams_uplink",
                                             "tp_tv_with_rt_beams_uplink", "tp_tv_plugin_full_buffer",
                                             "tp_tv_plugin_ftp", "sys_share_of_step")}))


if __name__ == "__main__":
    main()
