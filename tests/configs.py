"""The pieces of TOML that the tests' configurations share, built in one place: an
[episode] header, a module table, the waypoint-flight UAV, the camera-to-detector image
chain, a small-ray-count sionna-link; the route CSVs the flights follow; running a
configuration to its RunLog; and the environment for the `caviar-core` command. Tests
import it like conftest's helpers (conftest puts tests/ on sys.path):

    from configs import episode, module, run_config, waypoint_uav

Each builder returns TOML text ending in a newline, with a blank line after each table,
so that pieces concatenate: ``episode(...) + waypoint_uav() + module(...)``."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import pathlib
import sys
import time

import caviar

TESTS = pathlib.Path(__file__).resolve().parent
# caviar_plugins.DATA's route of a UAV over Central Park, scene frame (found without importing the plugins)
CENTRAL_PARK = (pathlib.Path(importlib.util.find_spec("caviar_plugins").submodule_search_locations[0]) / "data"
                / "central_park_path0_scene.csv")

SAR_STAGES = ["mobility", "camera", "communications", "link", "detection", "mission"]


def value(v) -> str:
    """A Python value as TOML: str, bool, int, float, path, list and dict (inline table)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, pathlib.PurePath):
        v = v.as_posix()
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(map(value, v)) + "]"
    if isinstance(v, dict):
        return inline(v)
    raise TypeError(f"no TOML for {v!r}")


def inline(params: dict | str) -> str:
    """``{ a = 1, b = "x" }``; a str is the table's inside, written as it is."""
    inside = params if isinstance(params, str) else ", ".join(f"{k} = {value(v)}" for k, v in params.items())
    return "{ " + inside + " }"


def table(header: str, keys: dict, *, array: bool = False) -> str:
    """``[header]`` (``[[header]]``, a table of an array of tables, with ``array``) and one
    ``key = value`` line a key."""
    brackets = ("[[", "]]") if array else ("[", "]")
    return header.join(brackets) + "\n" + "".join(f"{k} = {value(v)}\n" for k, v in keys.items())


def episode(ts: float, stages: list[str], steps: int | None = None, seed: int | None = None, **more) -> str:
    """The [episode] table (keys in the order ts, steps, seed, stages, then ``more``)."""
    keys = {"ts": ts, "steps": steps, "seed": seed, "stages": stages, **more}
    return table("episode", {k: v for k, v in keys.items() if v is not None}) + "\n"


def output(**keys) -> str:
    """The [output] table."""
    return table("output", keys) + "\n"


def nats_transport(**nats) -> str:
    """[transport] over NATS, and [transport.nats] with ``nats`` where given."""
    return table("transport", {"kind": "nats"}) + (table("transport.nats", nats) if nats else "") + "\n"


def module(name: str, stage: str, plugin: str, params: dict | str | None = None, *, params_table: bool = False,
           **keys) -> str:
    """``[modules.<name>]`` with its stage, plugin, any other ``keys`` (every, subscribe...) and
    its params: inline (``params = { ... }``; a str is the inside of the braces) or, with
    ``params_table``, as a ``[modules.<name>.params]`` table (a str is then its lines)."""
    text = table(f"modules.{name}", {"stage": stage, "plugin": plugin, **keys})
    if params is not None and params_table:
        text += f"[modules.{name}.params]\n" + (params if isinstance(params, str) else
                                                "".join(f"{k} = {value(v)}\n" for k, v in params.items()))
    elif params is not None:
        text += f"params = {inline(params)}\n"
    return text + "\n"


def waypoint_uav(waypoints: str | pathlib.Path = "route.csv", speed: float = 5.0, *, name: str = "uav",
                 frame: str = "scene", **params) -> str:
    """The UAV flying a route CSV: ``waypoint-flight`` in stage mobility."""
    return module(name, "mobility", "waypoint-flight", {"waypoints": waypoints, "frame": frame, "speed": speed,
                                                        **params})


def image_chain(detector: dict | str | None = None, *, camera: dict | str | None = None,
                comm: dict | str | None = None, radio: str | None = None,
                mission: dict | str | bool | None = True) -> str:
    """The search-and-rescue loop after the flight: the camera, a free-space link (or
    ``radio``, the TOML of the modules in its place, e.g. a beam selector and
    sionna_link()), the image link, the person detector and (unless ``mission`` is False)
    the mission; each one's params where given."""
    text = (module("camera", "camera", "camera", camera)
            + (radio if radio is not None else module("comm", "communications", "free-space-link", comm))
            + module("link", "link", "image-link")
            + module("detector", "detection", "person-detector", detector))
    if mission is not False:
        text += module("mission", "mission", "mission", None if mission is True else mission)
    return text


def sionna_link(samples_per_src: int = 10000, *, name: str = "comm", stage: str = "communications",
                raytracing: dict | None = None, params_table: bool = False, **params) -> str:
    """A ray-traced ``sionna-link`` with few rays (``raytracing = { samples_per_src = ... }``,
    plus any other ray-tracing keys), then ``params`` (inline, or a table with ``params_table``)."""
    return module(name, stage, "sionna-link", {"raytracing": {"samples_per_src": samples_per_src,
                                                              **(raytracing or {})}, **params},
                  params_table=params_table)


def planned_flight(waypoints: str | pathlib.Path = CENTRAL_PARK, forecast_steps: int = 4, *, name: str = "uav1",
                   **params) -> str:
    """uav1 (``name``) flying ``waypoints`` (the Central Park route) and publishing its plan
    ``forecast_steps`` ahead: waypoint-flight, its params as a table."""
    return module(name, "mobility", "waypoint-flight", {"waypoints": waypoints, "frame": "scene",
                                                        "forecast_steps": forecast_steps, **params}, params_table=True)


def traced_flight(forecast_steps: int, **link) -> str:
    """8 steps of 0.5 s (seed 2): the planned Central Park flight (not ending at its last
    waypoint) and its sionna-link with few rays to depth 3 on one thread, no UAV mesh, and
    ``link``'s other params."""
    return (episode(0.5, ["mobility", "communications"], steps=8, seed=2)
            + planned_flight(forecast_steps=forecast_steps, end_at_last=False)
            + sionna_link(raytracing={"max_depth": 3, "threads": 1}, params_table=True, uav_mesh=False, **link))


def write_route(tmp_path: pathlib.Path, points, name: str = "route.csv") -> pathlib.Path:
    """The route CSV (``X,Y,Z`` and a row a point, each value as ``str`` writes it)."""
    path = tmp_path / name
    path.write_text("X,Y,Z\n" + "".join(f"{x},{y},{z}\n" for x, y, z in points))
    return path


def route_past(tmp_path: pathlib.Path, target, half: float = 8.0, z: float = 9.23,
               name: str = "route.csv") -> pathlib.Path:
    """A straight route along x over ``target`` (x, y): from ``half`` metres before it to
    ``half`` after, at height ``z`` (x and y to the centimetre)."""
    tx, ty = target
    return write_route(tmp_path, [(f"{tx - half:.2f}", f"{ty:.2f}", z), (f"{tx + half:.2f}", f"{ty:.2f}", z)], name)


def run_config(tmp_path: pathlib.Path, text: str, out: str = "run", name: str = "exp.toml", **kw):
    """Writes ``text`` as ``name`` in tmp_path and runs it to the end into tmp_path/out: the RunLog."""
    (tmp_path / name).write_text(text)
    return caviar.Simulation.from_toml(tmp_path / name, out=tmp_path / out, **kw).run()


def the_rescue(log, target, within_m: float = 1.5) -> dict:
    """The run's one rescue (asserted: one, within ``within_m`` of ``target`` (x, y)), as a dict."""
    rescues = log.topic("mission.rescue")
    assert rescues.height == 1, rescues
    r = rescues.row(0, named=True)
    assert math.dist((r["x"], r["y"]), target) < within_m
    return r


def caviar_env(**more) -> dict[str, str]:
    """This environment with tests/ on PYTHONPATH (the test plugins), for a `caviar-core` process."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]), **more)


def caviar_core() -> str:
    """The installed `caviar-core` console script."""
    return str(pathlib.Path(sys.executable).parent / "caviar-core")


def ended_in(proc, timeout: float, send: int | None = None) -> tuple[str, float]:
    """Sends the signal ``send`` (if any) to ``proc`` and waits for it to end (at most
    ``timeout`` s): its stderr and the seconds it took to end."""
    if send is not None:
        proc.send_signal(send)
    t0 = time.monotonic()
    _, err = proc.communicate(timeout=timeout)
    return err, time.monotonic() - t0
