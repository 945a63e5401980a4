"""The radio network's step, wrapped for timing (``bench_host_overhead.py``): its compiled
programs (:func:`compiled_calls`) and its phases (:func:`phases_timed`), each call's wall time
added to a dict."""

from __future__ import annotations

import sys
import time
from typing import Any

RUNS = ("run", "run_linear", "run_links")
"""A link level's calls (numpy dB SINRs, or linear ones as a tensor): the link levels' phases."""
COMPILED = ("_group", "_groups")
"""A link level's calls of its compiled programs: one group of slots, several (``groups_per_call``)."""


def compiled_calls(net) -> list[tuple[Any, str]]:
    """(object, name) of the step's compiled programs: the plugin's link levels' :data:`COMPILED`
    calls (a baseline's has no ``_groups``) and, once made (since 2026-11-29, evening), the uplink's
    powers and SINR and the downlink's SINRs (``power_and_ratio_compiled``, ``sinr_and_wideband_compiled``
    in ``caviar_plugins.network``'s ``uplink``, ``beams``; since that night, both as one: ``sinrs``)."""
    from bench_network import link_levels

    calls = [(link, name) for link in link_levels(net) for name in COMPILED if hasattr(link, name)]
    programs = {"uplink": "power_and_ratio_compiled", "beams": "sinr_and_wideband_compiled",
                "sinrs": "both_directions_compiled"}
    owners = {m: sys.modules.get(f"caviar_plugins.network.{m}") for m in programs}
    return calls + [(owners[m], name) for m, name in programs.items() if getattr(owners[m], name, None) is not None]


def timed(obj, name: str, into: dict, key: str) -> None:
    """Wraps ``obj.name`` to add its wall time to ``into[key]`` (and count its calls)."""
    inner = getattr(obj, name)

    def wrapper(*args, **kwargs):
        a = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            into[key] = into.get(key, 0.0) + time.perf_counter() - a
            into[key + "_calls"] = into.get(key + "_calls", 0) + 1

    setattr(obj, name, wrapper)


def phases_timed(net, timing: dict) -> None:
    """The step's phases wrapped to add their wall time to ``timing`` (``bench_host_overhead.one``'s ``phases_ms``)."""
    from bench_network import link_levels

    timed(net.channel.tracer, "trace", timing, "rt")
    for link, name in compiled_calls(net):
        timed(link, name, timing, "sys")
    timed(net, "_measure", timing, "measure")
    plugin = sys.modules[type(net).__module__]
    for name, key in (("downlink_sinr", "downlink_sinr"), ("uplink", "uplink_sinr"), ("step_sinrs", "sinrs")):
        if hasattr(plugin, name):  # (the uplink's: powers and SINR; both: step_sinrs, since 2026-11-29, night)
            timed(plugin, name, timing, key)
    keys = ("dl_link_run", "ul_link_run") if len(link_levels(net)) > 1 else ("dl_ul_link_run",)
    for link, key in zip(link_levels(net), keys, strict=True):
        for name in RUNS:
            if hasattr(link, name):
                timed(link, name, timing, key)
