"""Random demand for a SUMO network with SUMO's randomTrips.py: a given number of
vehicles per vehicle class and of pedestrians, departing within a time window.

randomTrips is run with ``--validate`` (routes checked by duarouter), asked for half as
many trips again as needed, and the first ``count`` valid trips are kept, so counts are
exact unless the network cannot carry them. One run per class, all at once.
"""

from __future__ import annotations

import pathlib
import subprocess
import sys
import xml.etree.ElementTree as ET

from caviar_plugins.traffic.sumo import SumoError, sumo_home

OVERSAMPLE = 1.5


def random_trips(net: pathlib.Path, out_dir: pathlib.Path, counts: dict[str, int], pedestrians: int, seed: int,
                 window_s: float, min_distance_m: float = 300.0, fringe_factor: float = 5.0) -> list[pathlib.Path]:
    """Writes one trips file per vehicle class (``<class>.trips.xml``) and one for
    pedestrians (``pedestrians.trips.xml``) into ``out_dir``; returns their paths."""
    script = sumo_home() / "tools" / "randomTrips.py"
    jobs = []
    out_dir.mkdir(parents=True, exist_ok=True)
    wanted = [(vclass, n) for vclass, n in counts.items() if n > 0]
    if pedestrians > 0:
        wanted.append(("pedestrian", pedestrians))
    for k, (vclass, n) in enumerate(wanted):
        out = out_dir / f"{'pedestrians' if vclass == 'pedestrian' else vclass}.trips.xml"
        prefix = "ped" if vclass == "pedestrian" else vclass
        period = window_s / (n * OVERSAMPLE)
        args = [sys.executable, str(script), "-n", str(net), "-o", str(out), "--seed", str((seed + k) % 2**31),
                "--begin", "0", "--end", f"{window_s:.3f}", "--period", f"{period:.6f}", "--prefix", prefix,
                "--validate", "--min-distance", f"{min_distance_m:.1f}", "--fringe-factor", f"{fringe_factor}"]
        args += ["--pedestrians"] if vclass == "pedestrian" else ["--vehicle-class", vclass]
        # Each run in a folder of its own: randomTrips --validate writes fixed temporary names.
        cwd = out_dir / f"{prefix}.work"
        cwd.mkdir(exist_ok=True)
        log = open(cwd / "randomTrips.log", "w")
        jobs.append((vclass, n, out, log, subprocess.Popen(args, cwd=cwd, stdout=log, stderr=subprocess.STDOUT)))
    paths = []
    for vclass, n, out, log, proc in jobs:
        proc.wait()
        log.close()
        if proc.returncode != 0 or not out.exists():
            tail = pathlib.Path(log.name).read_text(errors="replace").strip().splitlines()[-3:]
            raise SumoError(f"randomTrips for {vclass} on {net} failed: {' '.join(tail)}")
        kept = keep_first(out, n)
        if kept == 0:
            raise SumoError(f"{net}: randomTrips found no valid {vclass} trip (does the network allow {vclass}?)")
        paths.append(out)
    return paths


def keep_first(path: pathlib.Path, n: int) -> int:
    """Keeps the vTypes and the first ``n`` trips/persons of a routes file; returns how many."""
    tree = ET.parse(path)
    root = tree.getroot()
    kept = 0
    for el in list(root):
        if el.tag in ("trip", "vehicle", "person", "flow", "personFlow"):
            if kept >= n:
                root.remove(el)
            else:
                kept += 1
    tree.write(path, encoding="UTF-8", xml_declaration=True)
    return kept
