"""Starting SUMO and reading its state: libsumo in-process (default) or TraCI to a
``sumo``/``sumo-gui`` process, started here or already running.

Nothing of caviar here. Errors SUMO reports while loading (a network or route file it
cannot read, a route on edges the network lacks, an unknown vehicle type) become
:class:`SumoError` with SUMO's own error lines, read from its log file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import math
import pathlib
import shutil

# SUMO vehicle classes (sumo.dlr.de/docs/Definition_of_Vehicles,_Vehicle_Types,_and_Routes.html#abstract_vehicle_class)
# and the paper schema's UE_type for each.
UE_TYPES = {
    "passenger": "car", "private": "car", "taxi": "car", "evehicle": "car", "custom1": "car", "custom2": "car",
    "emergency": "emergency", "authority": "emergency", "army": "emergency", "vip": "car",
    "bus": "bus", "coach": "bus",
    "delivery": "truck", "truck": "truck", "trailer": "truck",
    "motorcycle": "motorcycle", "moped": "motorcycle",
    "bicycle": "bicycle", "scooter": "bicycle",
    "tram": "tram", "rail_urban": "tram", "rail": "train", "rail_electric": "train", "rail_fast": "train",
    "pedestrian": "pedestrian",
}
VEHICLE_CLASSES = tuple(k for k in UE_TYPES if k != "pedestrian")


class SumoError(RuntimeError):
    """SUMO refused to load or to step; the message carries SUMO's error lines."""


def ue_type_of(vclass: str) -> str:
    return UE_TYPES.get(vclass, "vehicle")


def sumo_home() -> pathlib.Path:
    try:
        import sumo

        return pathlib.Path(sumo.SUMO_HOME)
    except ImportError:
        raise SumoError("SUMO is not installed: install the 'traffic' extra of caviar-plugins "
                        "(eclipse-sumo, libsumo)") from None


def binary(name: str) -> str:
    exe = sumo_home() / "bin" / name
    if exe.exists():
        return str(exe)
    found = shutil.which(name)
    if not found:
        raise SumoError(f"{name} not found in {sumo_home() / 'bin'} nor on PATH")
    return found


@dataclasses.dataclass
class Entity:
    """A vehicle or person as the scene sees it: ``xyz`` is the centre of its footprint
    on the ground (SUMO reports the front bumper of vehicles)."""

    id: str
    ue_type: str
    vclass: str
    xyz: tuple[float, float, float]
    yaw: float
    """radians, counter-clockwise from the scene's x axis (east)."""
    speed: float
    length: float
    width: float
    height: float

    @property
    def velocity(self) -> tuple[float, float, float]:
        return (self.speed * math.cos(self.yaw), self.speed * math.sin(self.yaw), 0.0)


class Sumo:
    """One running SUMO. ``backend``: ``libsumo`` (in this process; one per process),
    ``traci`` (starts ``binary`` and connects) or ``traci-connect`` (connects to a SUMO
    already listening on ``port``, e.g. ``sumo-gui --remote-port PORT``)."""

    _libsumo_in_use = False

    def __init__(self, args: list[str], log: pathlib.Path, *, backend: str = "libsumo", binary_name: str = "sumo",
                 port: int = 0, host: str = "localhost", label: str = "caviar"):
        self.log = log
        self.backend = backend
        self.label = label
        args = [*args, "--log", str(log)]
        if backend == "libsumo":
            if Sumo._libsumo_in_use:
                raise SumoError("libsumo runs one simulation per process and one is already running here; "
                                "use backend = 'traci' for a second traffic module")
            with contextlib.redirect_stdout(io.StringIO()):  # libsumo prints a pyarrow version warning
                import libsumo

            self.api = libsumo
            try:
                # SUMO writes its load errors to stderr (the log file is flushed only at close).
                with _stderr_to(log.with_suffix(".stderr")):
                    libsumo.start([binary(binary_name), *args])
            except Exception as e:  # libsumo.TraCIException, FatalTraCIError
                self._fail(e)
            Sumo._libsumo_in_use = True
        else:
            import traci

            try:
                if backend == "traci-connect":
                    traci.init(port=port, host=host, label=label)
                else:
                    traci.start([binary(binary_name), *args], port=port or None, label=label)
            except Exception as e:  # traci.exceptions.FatalTraCIError / TraCIException
                self._fail(e)
            self.api = traci.getConnection(label)
            if backend == "traci-connect" and args:
                pass  # the external SUMO was started with its own options
        self.closed = False

    def _fail(self, e: Exception):
        lines = []
        for path in (self.log, self.log.with_suffix(".stderr")):
            try:
                lines += [ln.strip() for ln in path.read_text(errors="replace").splitlines()
                          if ln.startswith(("Error", "Fatal"))]
            except OSError:
                pass
        raise SumoError("; ".join(lines) or f"{type(e).__name__}: {e}") from None

    @property
    def time(self) -> float:
        return float(self.api.simulation.getTime())

    def advance_to(self, t: float, dt: float) -> tuple[list[str], list[str]]:
        """Steps until SUMO's time reaches ``t``; the ids that departed and arrived meanwhile
        (vehicles and persons, in SUMO's order)."""
        sim = self.api.simulation
        departed, arrived = [], []
        while self.time < t - 1e-6 * dt:
            try:
                sim.step()
            except Exception as e:
                self._fail(e)
            departed += list(sim.getDepartedIDList()) + list(sim.getDepartedPersonIDList())
            arrived += list(sim.getArrivedIDList()) + list(sim.getArrivedPersonIDList())
        return departed, arrived

    def save_state(self, path: pathlib.Path) -> bytes:
        """SUMO's state now (``simulation.saveState``), as the bytes of the file it wrote."""
        try:
            self.api.simulation.saveState(str(path))
        except Exception as e:
            self._fail(e)
        data = path.read_bytes()
        path.unlink()
        return data

    def load_state(self, path: pathlib.Path, data: bytes) -> None:
        """Puts back a state :meth:`save_state` returned (``simulation.loadState``)."""
        path.write_bytes(data)
        try:
            self.api.simulation.loadState(str(path))
        except Exception as e:
            self._fail(e)
        finally:
            path.unlink()

    def entities(self) -> list[Entity]:
        """Every vehicle and person in the network now, vehicles first, each sorted by id."""
        out = []
        v, p = self.api.vehicle, self.api.person
        for vid in sorted(v.getIDList()):
            vclass = v.getVehicleClass(vid)
            out.append(_entity(vid, ue_type_of(vclass), vclass, v.getPosition3D(vid), v.getAngle(vid), v.getSpeed(vid),
                               v.getLength(vid), v.getWidth(vid), v.getHeight(vid)))
        for pid in sorted(p.getIDList()):
            out.append(_entity(pid, "pedestrian", "pedestrian", p.getPosition3D(pid), p.getAngle(pid), p.getSpeed(pid),
                               p.getLength(pid), p.getWidth(pid), p.getHeight(pid)))
        return out

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self.api.close()
        except Exception:  # already gone (SUMO ended, or the GUI was closed)
            pass
        if self.backend == "libsumo":
            Sumo._libsumo_in_use = False


@contextlib.contextmanager
def _stderr_to(path: pathlib.Path):
    """Sends this process's file descriptor 2 to ``path`` meanwhile (C++ output included)."""
    import os
    import sys

    sys.stderr.flush()
    saved = os.dup(2)
    with open(path, "wb") as f:
        os.dup2(f.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)


def _entity(eid, ue_type, vclass, pos3d, angle_deg, speed, length, width, height) -> Entity:
    # SUMO's angle: degrees clockwise from north; its position: the front bumper.
    yaw = math.radians(90.0 - angle_deg)
    yaw = math.atan2(math.sin(yaw), math.cos(yaw))
    x, y, z = pos3d
    x -= 0.5 * length * math.cos(yaw)
    y -= 0.5 * length * math.sin(yaw)
    return Entity(eid, ue_type, vclass, (float(x), float(y), float(z)), yaw, float(speed), float(length),
                  float(width), float(height))
