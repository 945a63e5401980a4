"""The calibration's runs: the phase-1 calibration through the ``radio-network`` plugin
(:func:`calibrate`) and the ray-traced channel beside 38.901 UMi on one layout in a scene
(:func:`side_by_side`), each writing its JSON and its figures."""

from __future__ import annotations

import json
import pathlib
import tempfile
import time
from typing import Any

import numpy as np

from caviar_plugins.tools.calibration.config import (
    METRICS,
    PERCENTILES,
    REFERENCE_NAMES,
    SIDE_BY_SIDE_CHANNELS,
    SIDE_BY_SIDE_LAYOUT,
    SPEC_VERSION,
    CalibrationError,
    cell_radius,
    config_toml,
    settings,
    side_by_side_toml,
)
from caviar_plugins.tools.calibration.plots import draw, draw_side_by_side, draw_where


def metrics_of(log) -> dict[str, np.ndarray]:
    """The three metrics of every dropped UE the run reported."""
    from caviar_plugins.network.report import ue_rows

    rows = [r for _, r in ue_rows(log) if r.get("UE_type") == "dropped"]
    return {"coupling_loss_db": np.array([r["coupling_loss_db"] for r in rows], dtype=float),
            "geometry_sinr_db": np.array([r["sinr_db"] for r in rows], dtype=float),
            "wideband_sir_db": np.array([r["sir_db"] for r in rows], dtype=float)}


def reference(path: pathlib.Path | None, scenario: str,
              carrier_hz: float) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
    """The companies' CDFs of the scenario per metric: (percentiles [n], values [company, n]),
    coupling loss as a positive loss; None where the file has none for this case. A file
    that is not the companies' CDFs is a :class:`CalibrationError` naming ``--reference``."""
    if path is None:
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CalibrationError(f"--reference: {path} cannot be read as JSON ({e})") from None
    entry = data.get("scenarios", {}).get(case_name(scenario, carrier_hz)) if isinstance(data, dict) else None
    if entry is None:
        return None
    out = {}
    try:
        for metric, name in REFERENCE_NAMES.items():
            table = entry["metrics"][name]
            pct = np.array(table["cdf_percentiles"], dtype=float)
            curves = np.array([c for c in table["data"].values()
                               if len(c) == len(pct) and all(v is not None for v in c)], dtype=float)
            if metric == "coupling_loss_db":  # a gain's percentile p is the loss's 100 − p
                curves, pct = -curves[:, ::-1], 100.0 - pct[::-1]
            if curves.ndim != 2 or not len(curves) or not all(np.any(pct == p) for p in (5, 50, 95)):
                raise ValueError(f"no complete curve at the percentiles 5, 50, 95 for {name}")
            out[metric] = (pct, curves)
    except (KeyError, TypeError, ValueError) as e:
        raise CalibrationError(f"--reference: {path}: {case_name(scenario, carrier_hz)} is not the companies' CDFs "
                               f"({type(e).__name__}: {e})") from None
    return out


def case_name(scenario: str, carrier_hz: float) -> str:
    """The case as the companies' file names it (``UMa-6GHz``)."""
    return f"{scenario}-{carrier_hz / 1e9:g}GHz"


def compare(ours: dict[str, list[float]], ref: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, Any]:
    """At the percentiles 5, 50, 95: ours, the companies' min, median and max, whether ours
    is within their range, and (at 50) its distance to their median."""
    out: dict[str, Any] = {}
    for metric, (pct, curves) in ref.items():
        out[metric] = {}
        for p in (5, 50, 95):
            at = curves[:, int(np.flatnonzero(pct == p)[0])]
            lo, med, hi = float(at.min()), float(np.median(at)), float(at.max())
            v = ours[metric][p]
            out[metric][f"p{p}"] = {"ours": round(v, 2), "min": round(lo, 2), "median": round(med, 2),
                                    "max": round(hi, 2), "within_range": lo <= v <= hi,
                                    "from_median_db": round(v - med, 2)}
    return out


def calibrate(scenario: str, carrier_hz: float, drops: int, out: pathlib.Path, seed: int = 1,
              reference_file: pathlib.Path | None = None, progress: bool = True,
              spec_version: str = SPEC_VERSION) -> dict[str, Any]:
    """Runs the calibration (the 38.901 channel's tables of release ``spec_version``) and
    writes ``out/<scenario>-<GHz>GHz.{json,png}``; returns what the JSON holds. Its
    ``reference`` compares with the companies' curves of ``reference_file``, or says why
    there are none (``missing``)."""
    import caviar

    s = settings(scenario, carrier_hz, spec_version)
    if drops < 1:
        raise CalibrationError(f"--drops: expected at least one drop, got {drops}")
    ref = reference(reference_file, s["scenario"], carrier_hz)  # (read before the work: a bad file stops it)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="caviar-calibration-") as tmp:
        cfg = pathlib.Path(tmp) / "config.toml"
        cfg.write_text(config_toml(s, drops, seed))
        with caviar.Simulation.from_toml(cfg, out=pathlib.Path(tmp) / "runs") as sim:
            log = sim.run(progress=progress)
        values = metrics_of(log)
    wall = time.perf_counter() - started
    result: dict[str, Any] = {"percentiles": PERCENTILES}
    for metric, v in values.items():
        result[metric] = [round(float(x), 3) for x in np.percentile(v, PERCENTILES)]
    result.update(drops=drops, samples=int(values["coupling_loss_db"].size), seed=seed, settings=s,
                  wall_s=round(wall, 1))
    case = case_name(s["scenario"], carrier_hz)
    if ref is not None:
        result["reference"] = {"file": reference_file.name if reference_file else None,
                               "companies": int(len(ref["coupling_loss_db"][1])), **compare(result, ref)}
    elif reference_file is None:
        result["reference"] = {"file": None, "missing": f"no companies' curves given (--reference) for {case}"}
    else:
        result["reference"] = {"file": reference_file.name,
                               "missing": f"{reference_file.name} has no companies' curves for {case}: nothing to "
                                          "compare with, the figure has no band"}
    stem = case
    (out / f"{stem}.json").write_text(json.dumps(result, indent=1) + "\n")
    draw(result, ref, out / f"{stem}.png")
    return result


# --- ray-traced against stochastic on one layout -------------------------------------------


def find_center(scene: Any, layout: dict[str, Any], step_m: float = 10.0) -> tuple[float, float]:
    """A centre for the layout in ``scene`` (Sionna RT) where every site has open sky above
    it (none inside a building) and every sector lies inside the scene's extent; the one
    nearest the scene's middle."""
    from caviar_plugins.network.layout import LayoutSettings, site_positions
    from caviar_plugins.rt.scene import open_sky

    box = scene.mi_scene.bbox()
    lo, hi = np.array(box.min, dtype=float)[:2], np.array(box.max, dtype=float)[:2]
    sites = site_positions(LayoutSettings(**{**layout, "center_m": (0.0, 0.0)}))
    reach = np.abs(sites).max(axis=0) + cell_radius(layout)
    first, last = lo + reach, hi - reach
    if np.any(first > last):
        raise CalibrationError(f"--scene: the layout ({2 * reach[0]:.0f} × {2 * reach[1]:.0f} m) does not fit in "
                               f"the scene ({hi[0] - lo[0]:.0f} × {hi[1] - lo[1]:.0f} m)")
    middle = np.round((lo + hi) / 2 / step_m) * step_m
    gx, gy = (m + step_m * np.arange(np.ceil((a - m) / step_m), np.floor((b - m) / step_m) + 1)
              for m, a, b in zip(middle, first, last, strict=True))
    centres = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
    centres = centres[np.argsort(np.linalg.norm(centres - middle, axis=1), kind="stable")]
    points = np.concatenate([centres[:, None, :] + sites[None], np.full((len(centres), len(sites), 1),
                                                                     float(layout["height_m"]))], axis=-1)
    ok = open_sky(scene, points.reshape(-1, 3)).reshape(len(centres), len(sites)).all(axis=1)
    if not ok.any():
        raise CalibrationError("--center: no centre puts every site of the layout in the open in this scene; "
                               "give one with --center X,Y")
    x, y = centres[int(np.argmax(ok))]
    return float(x), float(y)


def _covered(values: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], int]:
    """The metrics of the UEs some cell reaches, and how many no cell reaches (no traced
    path: a coupling loss at :data:`~caviar_plugins.network.raytraced.NO_PATH_DB`)."""
    from caviar_plugins.network.raytraced import NO_PATH_DB

    loss = values["coupling_loss_db"]
    ok = np.isfinite(loss) & (loss < -NO_PATH_DB - 50.0)
    return {k: v[ok] for k, v in values.items()}, int((~ok).sum())


def side_by_side(scene: str, drops: int, out: pathlib.Path, center: tuple[float, float] | None = None,
                 seed: int = 1, samples_per_src: int = 100_000, max_depth: int = 2, threads: int = 0,
                 progress: bool = True) -> dict[str, Any]:
    """Runs the UMi-like 7-site layout with ``channel = "ray-traced"`` in ``scene`` and with
    ``38.901-umi``, the same drops' settings, and writes
    ``out/raytraced-vs-38.901-umi.{json,png}``: both channels' CDFs and, at the
    percentiles 5, 50 and 95, by how much the ray-traced one differs."""
    import caviar
    from caviar_plugins.rt.scene import load_scene

    if drops < 1:
        raise CalibrationError(f"--drops: expected at least one drop, got {drops}")
    scene_file = pathlib.Path(scene).resolve()
    if not scene_file.is_file():
        raise CalibrationError(f"--scene: expected a Mitsuba scene file (scene build's scene.xml), got {scene!r}")
    s = settings("UMi", 6e9)
    s["layout"] = dict(SIDE_BY_SIDE_LAYOUT)
    if center is None:
        center = find_center(load_scene(str(scene_file)), s["layout"])
    s["layout"]["center_m"] = [round(center[0], 3), round(center[1], 3)]
    s["raytracing"] = {"scene": str(scene), "max_depth": max_depth, "samples_per_src": samples_per_src,
                       "diffraction": True, "threads": threads}
    out.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {"percentiles": PERCENTILES, "drops": drops, "seed": seed, "channels": {}}
    ues: dict[str, list[dict[str, Any]]] = {}
    for channel in SIDE_BY_SIDE_CHANNELS:
        started = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix="caviar-side-by-side-") as tmp:
            cfg = pathlib.Path(tmp) / "config.toml"
            cfg.write_text(side_by_side_toml(s, channel, drops, seed, scene_file))
            with caviar.Simulation.from_toml(cfg, out=pathlib.Path(tmp) / "runs") as sim:
                log = sim.run(progress=progress)
            values, uncovered = _covered(metrics_of(log))
            ues[channel] = dropped_ues(log)
        if values["coupling_loss_db"].size == 0:
            raise CalibrationError(f"--center/--max-depth: no cell reaches any UE with channel {channel!r} "
                                   f"({uncovered} UEs dropped); place the layout elsewhere or trace deeper")
        r: dict[str, Any] = {m: [round(float(x), 3) for x in np.percentile(v, PERCENTILES)] for m, v in values.items()}
        r.update(samples=int(values["coupling_loss_db"].size), uncovered=uncovered,
                 wall_s=round(time.perf_counter() - started, 1))
        result["channels"][channel] = r
    traced, stochastic = (result["channels"][c] for c in SIDE_BY_SIDE_CHANNELS)
    result["difference_db"] = {m: {f"p{q}": round(traced[m][q] - stochastic[m][q], 2) for q in (5, 50, 95)}
                               for m in METRICS}
    s["tr38901"] = "Sionna's UMi: pathloss, LOS probability, shadow fading (no O2I: outdoor UEs), no fast fading"
    result["settings"] = s
    (out / "raytraced-vs-38.901-umi.json").write_text(json.dumps(result, indent=1) + "\n")
    draw_side_by_side(result, out / "raytraced-vs-38.901-umi.png")
    draw_where(result, ues, load_scene(str(scene_file)), out / "raytraced-vs-38.901-umi-map.png")
    return result


def dropped_ues(log) -> list[dict[str, Any]]:
    """Every dropped UE the run reported: its position, serving cell and coupling loss."""
    from caviar_plugins.network.report import ue_rows

    return [{k: r[k] for k in ("position_m", "serving_cell", "coupling_loss_db")}
            for _, r in ue_rows(log) if r.get("UE_type") == "dropped"]
