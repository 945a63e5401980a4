"""The radio network's test pieces, on top of configs.py: the UEs that drive straight lines
(``sample_plugins:LineMover``), the sites table, the ``radio-network`` module with its
params, the ray-traced channel's keys (``scene``, ``raytracing``, ``evolution``), and the
configurations several tests share: two one-sector sites 400 m apart with a victim UE and
another, and cars in Sionna's simple street canyon. Then cells without a run (site_cells:
parse_sites with the tests' DEFAULTS; sector: one Cell), running a configuration, reading its
``network.ue`` reports, its ``caviar-core report``, and a link level's decisions checked
against eager's:

    from network_configs import BAND, line_movers, mover, radio_network, site

Each TOML builder returns text ending in a newline and a blank line, like configs.py's."""

from __future__ import annotations

import pathlib

import numpy as np

from configs import episode, module, output, run_config, table

STAGES = ["mobility", "communications"]
BAND = {"carrier_hz": 3.5e9, "bandwidth_hz": 20e6}
# the defaults the tests give parse_sites
DEFAULTS = {"tx_power_dbm": 40.0, **BAND, "array": [1, 1]}
# what the network tests record for analysis
REPORTS = ["communications.throughput", "network.ue", "network.events", "network.cells"]
MAPS = ["network.radio_map", "view.radio_map"]


def site(name: str, position, azimuths_deg, downtilt_deg: float | None = None, **more) -> dict:
    """A site of ``sites``: its name, position, sectors' azimuths and (where given) downtilt."""
    keys = {"name": name, "position": [float(v) for v in position],
            "azimuths_deg": [float(v) for v in azimuths_deg], "downtilt_deg": downtilt_deg, **more}
    return {k: v for k, v in keys.items() if v is not None}


def site_cells(*sites: dict, **defaults):
    """parse_sites of ``sites`` with DEFAULTS (and ``defaults`` over them): the cells."""
    from caviar_plugins.network.cells import parse_sites

    return parse_sites(list(sites), {**DEFAULTS, **defaults})


def sector(name: str, index: int, position, azimuth_deg: float, *, site: str | None = None,
           downtilt_deg: float = 0.0, tx_power_dbm: float = 46.0, array: tuple[int, int] = (1, 8)):
    """One Cell (a sector) at 3.5 GHz, 20 MHz, of site ``site`` (its own name unless given)."""
    from caviar_plugins.network.cells import Cell

    return Cell(name=name, site=name if site is None else site, index=index, position=position,
                azimuth_deg=azimuth_deg, downtilt_deg=downtilt_deg, tx_power_dbm=tx_power_dbm, array=array, **BAND)


def mover(ue_id: str, start, end=None, speed: float = 1.0, **more) -> dict:
    """A LineMover UE: from ``start`` to ``end`` (without one, standing at ``start``) at ``speed`` m/s."""
    return {"id": ue_id, **more, "start": [float(v) for v in start],
            "end": [float(v) for v in (start if end is None else end)], "speed": speed}


def line_movers(*ues: dict, name: str = "ues") -> str:
    """``[modules.<name>]``: ``sample_plugins:LineMover`` in stage mobility, a
    ``[[modules.<name>.params.ues]]`` table a UE (see :func:`mover`)."""
    return (table(f"modules.{name}", {"stage": "mobility", "plugin": "sample_plugins:LineMover"})
            + "".join(table(f"modules.{name}.params.ues", ue, array=True) for ue in ues) + "\n")


def radio_network(sites=(), *, name: str = "net", subscribe: list[str] | None = None, **params) -> str:
    """``[modules.<name>]``: ``radio-network`` in stage communications (``subscribe`` where
    given), its ``params`` as a table and a ``[[modules.<name>.params.sites]]`` table a site."""
    keys = {} if subscribe is None else {"subscribe": subscribe}
    text = module(name, "communications", "radio-network", params, params_table=True, **keys)
    return text + "".join(table(f"modules.{name}.params.sites", s, array=True) for s in sites) + ("\n" if sites else "")


def ray_traced(scene: str | None = None, *, refresh_s: float | None = None, mode: str | None = None,
               paths_per_link: int | None = None, **raytracing) -> dict:
    """The params of the ray-traced channel: ``channel``, the ``scene`` (where given), its
    ``raytracing`` (samples_per_src, max_depth, threads...) and its ``evolution`` between
    traces (refresh_s, mode, paths_per_link; where any is given)."""
    evolution = {k: v for k, v in {"refresh_s": refresh_s, "mode": mode, "paths_per_link": paths_per_link}.items()
                 if v is not None}
    keys = {"channel": "ray-traced", "scene": scene, "raytracing": raytracing, "evolution": evolution or None}
    return {k: v for k, v in keys.items() if v is not None}


# Two one-sector sites facing each other 400 m apart at 25 m, a victim UE served by A and
# another (served by B).
SITE_A = site("A", [0.0, 0.0, 25.0], [0.0], 0.0)
SITE_B = site("B", [400.0, 0.0, 25.0], [180.0], 0.0)
VICTIM = (180.0, 60.0, 25.0)
OTHER = (250.0, -120.0, 25.0)


def two_sites(other=OTHER, steps: int = 3, **params) -> str:
    """``steps`` steps of 10 ms (seed 4) of the victim and the other UE standing still, A and B at
    46 dBm with 1×8 arrays at 3.5 GHz (20 MHz, 30 kHz) and ``params``; REPORTS for analysis."""
    return (episode(0.01, STAGES, steps=steps, seed=4) + output(analysis=REPORTS)
            + line_movers(mover("victim", VICTIM), mover("other", other))
            + radio_network([SITE_A, SITE_B], **BAND, subcarrier_spacing_hz=30e3, tx_power_dbm=46.0, array=[1, 8],
                            **params))


# Sionna's simple street canyon: a one-sector site at its west end looking down the street
# (and one at its east end looking back), a car driving east along it.
WEST = site("west", [-80.0, 0.0, 10.0], [0.0])
EAST = site("east", [80.0, 0.0, 10.0], [180.0])
CAR1 = mover("car1", [-20.0, 2.0, 0.0], [60.0, 2.0, 0.0], 15.0)
CAR2 = mover("car2", [50.0, -2.0, 0.0], [-30.0, -2.0, 0.0], 10.0)


def canyon_scene() -> str:
    """The path of Sionna's simple street canyon."""
    import sionna.rt as rt

    return pathlib.Path(rt.scene.simple_street_canyon).as_posix()


def in_the_canyon(ues=(CAR1,), sites=(WEST,), *, seed: int = 3, duration: float | None = None, **params) -> str:
    """Steps of 20 ms (``seed``; ``duration`` where given) of ``ues`` driving and the radio
    network of ``sites`` with ``params`` (e.g. :func:`ray_traced`'s in :func:`canyon_scene`)."""
    return episode(0.02, STAGES, seed=seed, duration=duration) + line_movers(*ues) + radio_network(sites, **params)


def cars_in_the_canyon(sites=(WEST, EAST), scene: str | None = None, **params) -> str:
    """The resume tests' network: car1 and car2 in the street canyon, ray-traced with few
    rays to depth 2 on one thread and refreshed every 0.1 s (``scene``: the canyon's unless
    given), 4 HARQ processes, 4 subbands, a short time-to-trigger; ``params`` over those."""
    keys = {"subcarrier_spacing_hz": 30e3, "harq_processes": 4, "subbands": 4, "handover": {"time_to_trigger_s": 0.04},
            **ray_traced(scene or canyon_scene(), max_depth=2, samples_per_src=5000, threads=1, refresh_s=0.1),
            **params}
    return in_the_canyon((CAR1, CAR2), sites, **keys)


def run_network(tmp_path: pathlib.Path, text: str, out: str = "run", name: str = "net.toml"):
    """``text`` written as ``name`` in tmp_path and run into tmp_path/out: the RunLog."""
    return run_config(tmp_path, text, out, name)


def ue_reports(log) -> list[dict]:
    """The run's ``network.ue`` reports, in order."""
    return [m.data for m in log.decoded("network.ue")]


def last_reports(log) -> dict[str, dict]:
    """Each UE's last ``network.ue`` report, by UE_Id."""
    return {u["UE_Id"]: u for u in ue_reports(log)}


def reported(tmp_path: pathlib.Path, run: str = "run") -> pathlib.Path:
    """``caviar-core report`` of tmp_path/run (asserted to succeed) into tmp_path/rep: that folder."""
    from caviar.report import main as report

    assert report([str(tmp_path / run), "--out", str(tmp_path / "rep")]) == 0
    return tmp_path / "rep"


def assert_decides_as(got, eager) -> None:
    """A link level's first call decided as eager's: the same MCS and PRBs, the effective
    SINR and TBLER to float32's precision."""
    np.testing.assert_array_equal(got.mcs, eager.mcs)
    np.testing.assert_array_equal(got.prbs, eager.prbs)
    np.testing.assert_allclose(got.sinr_eff_db, eager.sinr_eff_db, atol=1e-4)
    np.testing.assert_allclose(got.tbler, eager.tbler, atol=1e-5)


def top_level_torch_ops(call) -> int:
    """The torch operations ``call`` runs that no other torch operation called."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        call()
    return sum(1 for e in prof.events() if e.name.startswith("aten::")
               and (e.cpu_parent is None or not e.cpu_parent.name.startswith("aten::")))


def eager_and_compiled(function, args: tuple, compiles: bool) -> dict:
    """``function(*args, compiled=c)`` eager (False) and compiled (True): each a first call (which
    may compile; under torch's ``fail_on_recompile`` where not ``compiles``), then a second, whose
    results and :func:`top_level_torch_ops` are returned, ``{c: (*results, ops)}``."""
    import torch

    out: dict = {}
    for compiled in (False, True):
        with torch.compiler.set_stance("default" if compiles else "fail_on_recompile"):
            function(*args, compiled=compiled)
        ops = top_level_torch_ops(lambda c=compiled: out.__setitem__(c, function(*args, compiled=c)))
        out[compiled] = (*out[compiled], ops)
    return out
