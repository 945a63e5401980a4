"""A DeepMIMO v4 scenario from a run of the ray-traced link (``caviar-core export deepmimo``).

The run must have published path data (``sionna-link``'s ``publish_paths = true``: one
:class:`~caviar_plugins.radio.path_data.PathData` per UE and step on
``communications.paths.<UE_Id>``). The conversion is DeepMIMO's own: this module writes
each step's paths in the form of DeepMIMO's Sionna RT exporter (its ``sionna_*.pkl``
files) and runs the parts of DeepMIMO's Sionna RT converter on them
(``deepmimo.converters.sionna_rt``: ``read_rt_params``, ``read_txrx``, ``read_paths``,
``read_materials``, ``read_scene``), the scene's geometry and materials read from the
run's Sionna scene with DeepMIMO's exporter functions. What it adds:

* the path coefficient handed to DeepMIMO is the baseband one, ``a·exp(−j2π f τ)``
  (Sionna's ``a`` lacks the carrier phase, which DeepMIMO's ``phase`` must hold: its
  channel at subcarrier k is Σ √P·exp(jφ)·exp(−j2π k Δf τ)), at the array centres;
* each receiver's paths are sorted by power first, so that the 25 DeepMIMO keeps are the
  strongest (its converter keeps the first 25 in Sionna's order); the power share kept is
  reported;
* the scene is converted once for all steps (DeepMIMO's converter does it per call: 3 s
  for Central Park), material values are plain floats (DeepMIMO's exporter leaves
  1-element arrays that ``float()`` refuses on NumPy >= 2.3);
* every snapshot has the same receivers, in the order the UEs first appeared (DeepMIMO
  reads one receiver count for all snapshots): a UE not yet seen at a step is a receiver
  without paths at the position where it first appears; UEs at one position get
  positions one float64 ulp apart (DeepMIMO tells receivers apart by position).

Layout: one step → OUT is a static scenario (``params.json``, ``objects.json``,
``vertices.npz``, ``{key}_t000_tx000_r001.npz``); several → one sorted subfolder per
step (``step_000000``, …), each a scenario with ``num_scenes`` = the number of steps,
as DeepMIMO's time-varying scenarios are. ``caviar.json`` at the top says which run,
module and steps, which UE each receiver is, and how much of each link's power the
25 paths kept.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import pathlib
import pickle
import tempfile
from importlib import metadata
from typing import Any, Callable

import numpy as np

from caviar_plugins.radio.path_data import PathData
from caviar_plugins.schema import PATHS, every_ue, ue_of

MAX_PATHS = 25
"""Paths DeepMIMO keeps per receiver (deepmimo.consts.MAX_PATHS)."""

REFERENCE = ("power (dBW, 0 dBW transmitted) and phase (degrees, carrier phase included) are each path's "
             "baseband coefficient a*exp(-j*2*pi*f*tau) at the array centres (the points Sionna's synthetic "
             "arrays trace), the run's antenna element patterns included: generate channels with isotropic "
             "elements. Angles are Sionna's: zenith ('el', 0 = up) and azimuth, degrees, global frame.")


class ExportError(ValueError):
    """Bad input to the export: a message naming what is wrong and what was expected."""


@dataclasses.dataclass
class Snapshot:
    step: int
    time_s: float
    paths: dict[str, PathData]
    """UE id → its paths, in publication order."""


def read_run_paths(run_dir: pathlib.Path, module: str | None = None) -> tuple[list[Snapshot], str]:
    """The path data a run recorded, one :class:`Snapshot` per step that has some, and
    the module that published it. ExportError for a run without any."""
    import caviar
    from caviar.rundir import RunDir

    try:
        RunDir(run_dir).require("; give the folder of a run of `caviar-core run`")
    except FileNotFoundError as e:
        raise ExportError(str(e)) from None
    try:
        log = caviar.load_run(run_dir)
        messages = log.decoded(every_ue(PATHS))
    except (OSError, ValueError) as e:
        raise ExportError(f"{run_dir}: cannot read the run ({e})") from None
    sources = sorted({str(m.source) for m in messages})
    if not messages:
        raise ExportError(f"{run_dir}: no path data (no messages on {every_ue(PATHS)}); run it with the ray-traced "
                          f"link's publish_paths = true{_where_to_turn_it_on(log.config_text)}")
    if module is None and len(sources) > 1:
        raise ExportError(f"{run_dir}: modules {', '.join(sources)} published path data; choose one with --module")
    module = module or sources[0]
    if module not in sources:
        raise ExportError(f"{run_dir}: module '{module}' published no path data (those that did: "
                          f"{', '.join(sources)})")
    snapshots: dict[int, Snapshot] = {}
    for m in messages:
        step, time_s = int(m.step or 0), float(m.time or 0.0)  # recorded messages have both
        if m.source != module:
            continue
        where = f"{run_dir}: step {step}, {m.topic}"
        if not isinstance(m.data, (bytes, bytearray, memoryview)):
            raise ExportError(f"{where}: expected a binary path-data payload, got {type(m.data).__name__}")
        try:
            data = PathData.from_bytes(m.data, where)
        except ValueError as e:
            raise ExportError(str(e)) from None
        snap = snapshots.setdefault(step, Snapshot(step, time_s, {}))
        snap.paths[ue_of(m.topic)] = data
    return [snapshots[k] for k in sorted(snapshots)], module


def _where_to_turn_it_on(config_text: str) -> str:
    """`` (modules.NAME.params.publish_paths = true, ...)`` for the sionna-link modules of a config."""
    try:
        import tomllib
    except ImportError:  # Python 3.10
        return ""
    try:
        modules = tomllib.loads(config_text).get("modules", {})
    except tomllib.TOMLDecodeError:
        return ""
    names = [n for n, m in modules.items() if isinstance(m, dict) and m.get("plugin") == "sionna-link"]
    if not names:
        return " (this run has no sionna-link module)"
    return " (" + ", ".join(f"--set modules.{n}.params.publish_paths=true" for n in names) + ")"


def _receivers(snapshots: list[Snapshot]) -> tuple[list[str], dict[str, np.ndarray]]:
    """All UEs in order of first appearance, and where each first appeared."""
    order: list[str] = []
    first: dict[str, np.ndarray] = {}
    for snap in snapshots:
        for ue, p in snap.paths.items():
            if ue not in first:
                order.append(ue)
                first[ue] = p.rx_position
    return order, first


def _distinct(positions: np.ndarray) -> np.ndarray:
    """``positions`` (N, 3) with each repeated row moved one float64 ulp in x per repeat."""
    out = positions.astype(np.float64).copy()
    seen: set[bytes] = set()
    for i in range(len(out)):
        while out[i].tobytes() in seen:
            out[i, 0] = np.nextafter(out[i, 0], np.inf)
        seen.add(out[i].tobytes())
    return out


def sionna_paths_dict(paths: list[PathData | None], rx_positions: np.ndarray, tx_position: np.ndarray
                      ) -> tuple[dict[str, np.ndarray], list[tuple[int, int, float]]]:
    """One snapshot's receivers in the form of DeepMIMO's Sionna exporter (one transmitter,
    single antennas: ``a`` (N, 1, 1, 1, P), angles and ``tau`` (N, 1, P), ``interactions``
    (D, N, 1, P), ``vertices`` (D, N, 1, P, 3)), each receiver's paths sorted by power;
    and per receiver (paths kept, paths, share of the power kept)."""
    n = len(paths)
    width = max([p.n_paths for p in paths if p is not None] + [1])
    depth = max([p.interactions.shape[0] for p in paths if p is not None] + [1])
    d: dict[str, np.ndarray] = {
        "a": np.zeros((n, 1, 1, 1, width), np.complex128),
        **{k: np.zeros((n, 1, width), np.float64) for k in ("tau", "theta_t", "phi_t", "theta_r", "phi_r")},
        "interactions": np.zeros((depth, n, 1, width), np.uint32),
        "vertices": np.zeros((depth, n, 1, width, 3), np.float64),
        "sources": np.asarray(tx_position, np.float64)[None, :],
        "targets": rx_positions,
    }
    kept = []
    for i, p in enumerate(paths):
        if p is None or p.n_paths == 0:
            kept.append((0, 0, 1.0))
            continue
        coef = p.baseband()
        power = np.abs(coef) ** 2
        order = np.argsort(-power, kind="stable")
        k = p.n_paths
        d["a"][i, 0, 0, 0, :k] = coef[order]
        d["tau"][i, 0, :k] = p.tau_s[order]
        for name in ("theta_t", "phi_t", "theta_r", "phi_r"):
            d[name][i, 0, :k] = getattr(p, name)[order]
        d["interactions"][: p.interactions.shape[0], i, 0, :k] = p.interactions[:, order]
        d["vertices"][: p.vertices.shape[0], i, 0, :k] = p.vertices[:, order]
        nonzero = int(np.count_nonzero(power))
        total = float(power.sum())
        share = float(np.sort(power)[::-1][:MAX_PATHS].sum() / total) if total > 0 else 1.0
        kept.append((min(nonzero, MAX_PATHS), nonzero, share))
    return d, kept


def rt_params(settings: dict[str, Any]) -> dict[str, Any]:
    """The run's ray-tracing settings as DeepMIMO's Sionna exporter writes them
    (``sionna_rt_params.pkl``), for single antennas at the array centres; the run's own
    arrays and settings are kept under ``caviar_*`` keys."""
    def flag(name: str) -> bool:
        return bool(settings.get(name, False))

    zero = np.zeros((1, 3))
    return {
        "bandwidth": float(settings.get("bandwidth_hz", 0.0)), "frequency": float(settings["frequency_hz"]),
        "rx_array_size": 1, "rx_array_num_ant": 1, "rx_array_ant_pos": zero,
        "tx_array_size": 1, "tx_array_num_ant": 1, "tx_array_ant_pos": zero,
        "synthetic_array": True, "raytracer_version": settings.get("sionna_rt", ""),
        "max_depth": int(settings["max_depth"]), "max_num_paths_per_src": int(settings["max_num_paths_per_src"]),
        "samples_per_src": int(settings["samples_per_src"]), "num_samples": int(settings["samples_per_src"]),
        "los": flag("los"), "specular_reflection": flag("specular_reflection"),
        "reflection": flag("specular_reflection"),
        "diffuse_reflection": flag("diffuse_reflection"), "scattering": flag("diffuse_reflection"),
        "refraction": flag("refraction"), "diffraction": flag("diffraction"),
        **{f"caviar_{k}": settings[k] for k in ("tx_array", "rx_array", "spacing", "pattern", "polarization",
                                                 "tx_orientation", "rx_orientation", "scene", "module")
           if k in settings},
    }


def _scene_files(settings: dict[str, Any], folder: pathlib.Path) -> None:
    """The run's Sionna scene (its static geometry: no UAV bodies) as DeepMIMO's Sionna
    exporter writes it: materials, vertices, objects and faces."""
    from caviar_plugins.rt import configure_drjit
    from caviar_plugins.rt.scene import load_scene

    configure_drjit()  # before DeepMIMO's exporter imports Sionna RT
    from deepmimo.exporters.sionna_exporter import export_scene_buildings, export_scene_materials

    path = settings.get("scene_file")
    if path is not None and not pathlib.Path(path).exists():
        raise ExportError(f"the run's scene {path} is gone; the export reads its geometry and materials")
    scene = load_scene(str(path) if path else "empty")
    scene.frequency = float(settings["frequency_hz"])  # the ITU materials' values depend on it
    materials, indices = export_scene_materials(scene)
    # DeepMIMO's exporter keeps 1-element arrays (drjit's .numpy()); its converter calls float() on them.
    materials = [{k: (float(np.asarray(v).ravel()[0]) if isinstance(v, np.ndarray) else v) for k, v in m.items()}
                 for m in materials]
    vertices, objects, faces = export_scene_buildings(scene)
    for name, value in (("materials", materials), ("material_indices", indices), ("vertices", vertices),
                        ("objects", objects), ("faces", faces)):
        _pickle(folder / f"sionna_{name}.pkl", value)


def _pickle(path: pathlib.Path, value: Any) -> None:
    with open(path, "wb") as f:
        pickle.dump(value, f)


@contextlib.contextmanager
def _quiet():
    """DeepMIMO's converter prints and draws progress bars: keep them off our output."""
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        yield


def export_deepmimo(run_dir: str | pathlib.Path, out: str | pathlib.Path, *, module: str | None = None,
                    progress: Callable[[str], object] | None = print) -> dict[str, Any]:
    """Writes the DeepMIMO v4 scenario of ``run_dir``'s path data into the new folder
    ``out``; returns what ``caviar.json`` holds. ExportError for bad input."""
    run_dir, out = pathlib.Path(run_dir), pathlib.Path(out)
    say = progress or (lambda _: None)
    if out.exists():
        raise ExportError(f"{out}: exists; the export writes a new folder (choose another name or remove it)")
    if out.name != out.name.lower() or not out.name:
        raise ExportError(f"{out}: DeepMIMO looks scenarios up by lower-case folder name; name it "
                          f"'{out.name.lower()}'")
    snapshots, module = read_run_paths(run_dir, module)
    try:
        import deepmimo
    except ImportError:
        raise ExportError("the export needs the deepmimo package: pip install 'caviar-plugins[deepmimo]'") from None
    first = next(iter(snapshots[0].paths.values()))
    settings = first.settings
    ues, first_seen = _receivers(snapshots)
    say(f"{run_dir}: {len(snapshots)} step(s) of path data from module '{module}', {len(ues)} UE(s)")
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".deepmimo-", dir=out.parent) as tmp:
        work, staged = pathlib.Path(tmp) / "sionna", pathlib.Path(tmp) / out.name
        work.mkdir()
        staged.mkdir()
        _scene_files(settings, work)
        rows = _convert(snapshots, ues, first_seen, settings, work, staged, say)
        summary = {"run": str(run_dir.resolve()), "module": module, "deepmimo": deepmimo.__version__,
                   "caviar_plugins": metadata.version("caviar-plugins"), "receivers": ues, "reference": REFERENCE,
                   "settings": settings, "snapshots": rows}
        (staged / "caviar.json").write_text(json.dumps(summary, indent=1) + "\n")
        staged.rename(out)
    say(f"wrote {out}")
    return summary


def _convert(snapshots: list[Snapshot], ues: list[str], first_seen: dict[str, np.ndarray],
             settings: dict[str, Any], work: pathlib.Path, staged: pathlib.Path,
             say: Callable[[str], object]) -> list[dict[str, Any]]:
    """Each snapshot through DeepMIMO's Sionna RT converter, the scene converted once."""
    from deepmimo import consts as c
    from deepmimo.converters import converter_utils as cu
    from deepmimo.converters.sionna_rt.sionna_materials import read_materials
    from deepmimo.converters.sionna_rt.sionna_paths import read_paths
    from deepmimo.converters.sionna_rt.sionna_rt_params import read_rt_params
    from deepmimo.converters.sionna_rt.sionna_scene import read_scene
    from deepmimo.converters.sionna_rt.sionna_txrx import read_txrx

    raw = rt_params(settings)
    # DeepMIMO's converter refuses settings without the LOS path; the run's own flag goes back after.
    _pickle(work / "sionna_rt_params.pkl", {**raw, "los": True})
    with _quiet():
        params = read_rt_params(str(work))
        params["raw_params"]["los"] = raw["los"]
        materials, material_indices = read_materials(str(work))
        scene = read_scene(str(work), material_indices)
    many = len(snapshots) > 1
    rows = []
    for n, snap in enumerate(snapshots):
        dest = staged / f"step_{snap.step:06d}" if many else staged
        dest.mkdir(exist_ok=True)
        paths = [snap.paths.get(ue) for ue in ues]
        rx = _distinct(np.array([first_seen[ue] if p is None else p.rx_position
                                 for ue, p in zip(ues, paths, strict=True)]))
        tx = next(p for p in paths if p is not None).tx_position
        sionna, kept = sionna_paths_dict(paths, rx, tx)
        _pickle(work / "sionna_paths.pkl", [sionna])
        with _quiet():
            txrx = read_txrx(params)
            read_paths(str(work), str(dest), txrx)
            scene_dict = scene.export_data(str(dest)) if scene else {}
        scene_dict[c.SCENE_PARAM_NUMBER_SCENES] = len(snapshots)
        cu.save_params({c.VERSION_PARAM_NAME: c.VERSION, c.RT_PARAMS_PARAM_NAME: params, c.TXRX_PARAM_NAME: txrx,
                        c.MATERIALS_PARAM_NAME: materials, c.SCENE_PARAM_NAME: scene_dict}, str(dest))
        row = {"folder": dest.name if many else ".", "step": snap.step, "time_s": snap.time_s,
               "absent": [ue for ue, p in zip(ues, paths, strict=True) if p is None],
               "paths": {ue: {"kept": k, "of": total, "power_kept": round(share, 6)}
                         for ue, (k, total, share) in zip(ues, kept, strict=True)}}
        rows.append(row)
        least = min(share for _, _, share in kept)
        say(f"snapshot {n + 1}/{len(snapshots)}: step {snap.step} (t = {snap.time_s:g} s), {len(ues)} receiver(s), "
            f"{sum(k for k, _, _ in kept)} of {sum(t for _, t, _ in kept)} paths kept, "
            f"least power kept {100 * least:.2f} %")
    return rows
