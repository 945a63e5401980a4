"""A standing corpus of malformed input for the surface added after issue #13 (issue #55): the
radio network, the LiDAR, UAV energy, the network's traffic, devices, the transports' sections
and checkpoints (the ns-3 cases are in tests/test_ns3_bad_input.py, the calibrate command's in
tests/test_tools_bad_flags.py). Built as tests/test_bad_configs.py builds the older surface's
(its ``Case``, ``make_case``, ``rep``, ``after`` and message check): every case must be refused
by ``caviar-core validate`` with exit status 2 and one line naming the file, the line where
there is one and the key, no traceback; a representative subset by ``run`` too, which must
create nothing. Settings that run but name something no shipped module publishes are warnings
naming the key (exit 0). A setting over a bound of :mod:`caviar_plugins.limits` passes with
``allow_large = true``.

Cheap by construction: ``validate`` only (no step runs), in this process through
``caviar._core.main`` (Sionna and torch are imported once, by the first network case); one
network run (a payload without its ``size_field``) is the only case that steps. Measured: the
module's 84 tests (77 malformed configurations) take 32 s on the 2-core development machine
shared with other work, most of it that first import.
"""

from __future__ import annotations

import pathlib

import pytest

from caviar import _core
from test_bad_configs import BASE, NATS, Case, _check_message, _listing, after, make_case, rep

EPISODE = """\
[episode]
ts = 0.1
steps = 2
seed = 1
stages = ["mobility", "work"]

[output]
name = "bad"
dir = "runs"

[modules.uav]
stage = "mobility"
plugin = "waypoint-flight"
[modules.uav.params]
speed = 5.0
ue_id = "uav1"

"""

NET = EPISODE + """\
[modules.net]
stage = "work"
plugin = "radio-network"
[modules.net.params]
link_model = "shannon"
layout = { rings = 0, ues_per_sector = 2 }
"""

LIDAR = EPISODE + """\
[modules.lidar]
stage = "work"
plugin = "lidar"
[modules.lidar.params]
scene = "empty"
sensor = { channels = 32 }
"""

ENERGY = EPISODE + """\
[modules.energy]
stage = "work"
plugin = "uav-energy"
[modules.energy.params]
computing_w = 10.0
"""


def _no_cuda() -> bool:
    from caviar_plugins.torch_device import cuda_devices

    return cuda_devices() == 0


CASES: list[Case] = []


def case(id: str, text: str, key: str | None, at: str | None = "") -> None:
    CASES.append(make_case(id, text, key, at))


def net(line: str) -> str:
    return after("[modules.net.params]", line, NET)


def lidar(sensor: str) -> str:
    return rep("sensor = { channels = 32 }", f"sensor = {{ {sensor} }}", LIDAR)


def energy(line: str) -> str:
    return after("[modules.energy.params]", line, ENERGY)


P = "modules.net.params."
# --- the radio network: devices, resource bounds, names that must match, ranges ----------------
case("net-device-cuda99", net('device = "cuda:99"'), P + "device")
if _no_cuda():
    case("net-device-cuda", net('device = "cuda"'), P + "device")
case("net-device-gpu", net('device = "gpu"'), P + "device")
case("net-device-number", net("device = 0"), P + "device")
case("net-ues-per-sector-huge", rep("ues_per_sector = 2", "ues_per_sector = 2000000", NET), P + "layout.ues_per_sector",
     "layout = {")
case("net-ues-per-sector-negative", rep("ues_per_sector = 2", "ues_per_sector = -1", NET),
     P + "layout.ues_per_sector", "layout = {")
case("net-layout-rings", rep("rings = 0", "rings = 3", NET), P + "layout.rings", "layout = {")
case("net-layout-sectors", rep("rings = 0", "rings = 0, sectors = 4", NET), P + "layout.sectors", "layout = {")
case("net-layout-and-sites", net('sites = [{ name = "a", position = [0.0, 0.0, 25.0] }]'), P + "layout", "layout = {")
case("net-layout-bad-scenario", rep("rings = 0", 'rings = 0, scenario = "moon"', NET), P + "layout.scenario",
     "layout = {")
case("net-bandwidth-negative", net("bandwidth_hz = -20e6\nnum_prb = 51"), P + "bandwidth_hz")
case("net-carrier-zero", net("carrier_hz = 0.0"), P + "carrier_hz")
case("net-scs-zero", net("subcarrier_spacing_hz = 0.0"), P + "subcarrier_spacing_hz")
case("net-bandwidth-not-nr", net("bandwidth_hz = 21e6"), P + "num_prb")
case("net-array-huge", net("array = [64, 64]"), P + "array")
case("net-array-zero", net("array = [0, 4]"), P + "array")
case("net-site-array-huge", rep("layout = { rings = 0, ues_per_sector = 2 }",
                                'sites = [{ name = "a", position = [0.0, 0.0, 25.0], array = [128, 16] }]', NET),
     P + "sites.0.array", "sites = [")
case("net-channel-unknown", net('channel = "magic"'), P + "channel")
case("net-interference-unknown", net('interference = "some"'), P + "interference")
case("net-report-cells-negative", net("report_cells = -1"), P + "report_cells")
case("net-allow-large-type", net('allow_large = "yes"'), P + "allow_large")
case("net-radio-map-cells", net("radio_map = { cell_size_m = 0.01 }"), P + "radio_map.cell_size_m", "radio_map = {")
case("net-rays-huge", net('channel = "ray-traced"\nraytracing = { samples_per_src = 1000000000 }')
     .replace("rings = 0,", "rings = 0, wraparound = false, indoor_share = 0.0,"), P + "raytracing.samples_per_src",
     "raytracing = {")
case("net-ftp-rate-huge", net('traffic = { downlink = "ftp3", ftp = { arrival_rate_hz = 1e9 } }'),
     P + "traffic.ftp.arrival_rate_hz", "traffic = {")
case("net-ftp-rate-zero", net('traffic = { downlink = "ftp3", ftp = { arrival_rate_hz = 0.0 } }'),
     P + "traffic.ftp.arrival_rate_hz", "traffic = {")
case("net-traffic-model", net('traffic = { downlink = "bursty" }'), P + "traffic.downlink", "traffic = {")
case("net-size-field-missing", net('traffic = { carry = [{ topic = "mission.upload", size_field = "nope" }] }'),
     P + "traffic.carry.0.size_field", "traffic = {")
case("net-size-field-binary", net('traffic = { carry = [{ topic = "3D.camera.*", size_field = "bytes" }] }'),
     P + "traffic.carry.0.size_field", "traffic = {")
case("net-carry-topic", net('traffic = { carry = [{ topic = "a..b" }] }'), P + "traffic.carry.0.topic", "traffic = {")
case("net-carry-direction", net('traffic = { carry = [{ topic = "x.*", direction = "sideways" }] }'),
     P + "traffic.carry.0.direction", "traffic = {")
case("net-carry-deliver-to", net('traffic = { carry = [{ topic = "x.*", deliver_to = "a..b" }] }'),
     P + "traffic.carry.0.deliver_to", "traffic = {")
case("net-by-type-direction", net('traffic = { by_type = { UAV = { sideways = "none" } } }'),
     P + "traffic.by_type.UAV.sideways", "traffic = {")

L = "modules.lidar.params."
# --- the LiDAR: resource bounds and ranges ----------------------------------------------------
case("lidar-resolution-tiny", lidar("horizontal_resolution_deg = 1e-6"), L + "sensor.horizontal_resolution_deg",
     "sensor = {")
case("lidar-rate-huge", lidar("rate_hz = 1e7"), L + "sensor.rate_hz", "sensor = {")
case("lidar-rate-fast", lidar("rate_hz = 200.0"), L + "sensor.rate_hz", "sensor = {")
case("lidar-channels-huge", lidar("channels = 100000"), L + "sensor.channels", "sensor = {")
case("lidar-rays-per-second", lidar("channels = 128, horizontal_resolution_deg = 0.01, rate_hz = 80.0"),
     L + "sensor.rate_hz", "sensor = {")
case("lidar-rate-zero", lidar("rate_hz = 0.0"), L + "sensor.rate_hz", "sensor = {")
case("lidar-resolution-uneven", lidar("horizontal_resolution_deg = 0.7"), L + "sensor.horizontal_resolution_deg",
     "sensor = {")
case("lidar-fov-inverted", lidar("vertical_fov_deg = [10.0, -10.0]"), L + "sensor.vertical_fov_deg", "sensor = {")
case("lidar-dropout-one", lidar("dropout = 1.0"), L + "sensor.dropout", "sensor = {")
case("lidar-min-range", lidar("min_range_m = 200.0"), L + "sensor.min_range_m", "sensor = {")
case("lidar-mount-offset", lidar("mount_offset_m = [0.0, 0.0]"), L + "sensor.mount_offset_m", "sensor = {")
case("lidar-sensor-unknown", lidar("chanels = 32"), L + "sensor.chanels", "sensor = {")
case("lidar-ue-ids-empty", after("[modules.lidar.params]", "ue_ids = []", LIDAR), L + "ue_ids")
case("lidar-uav-body", after("[modules.lidar.params]", "uav_body_m = [1.0, 1.0]", LIDAR), L + "uav_body_m")
case("lidar-save-every", after("[modules.lidar.params]", "save_every = -1", LIDAR), L + "save_every")
case("lidar-raytracing-depth", after("[modules.lidar.params]", "raytracing = { max_depth = 3 }", LIDAR),
     L + "raytracing.max_depth", "raytracing = {")

E = "modules.energy.params."
# --- UAV energy ---------------------------------------------------------------------------------
case("energy-air-density-tiny", energy("airframe = { air_density = 1e-300 }"), E + "airframe.air_density",
     "airframe = {")
case("energy-air-density-water", energy("airframe = { air_density = 1000.0 }"), E + "airframe.air_density",
     "airframe = {")
case("energy-weight-overflow", energy("airframe = { weight_n = 1e300 }"), E + "airframe.weight_n", "airframe = {")
case("energy-solidity", energy("airframe = { rotor_solidity = 1.5 }"), E + "airframe.rotor_solidity", "airframe = {")
case("energy-airframe-unknown", energy("airframe = { rotors = 4 }"), E + "airframe.rotors", "airframe = {")
case("energy-ue-types-empty", energy("ue_types = []"), E + "ue_types")
case("energy-reserve", energy("battery = { reserve = 1.5 }"), E + "battery.reserve", "battery = {")
case("energy-initial-soc", energy("battery = { initial_soc = 0.0 }"), E + "battery.initial_soc", "battery = {")
case("energy-capacity", energy("battery = { capacity_wh = -1.0 }"), E + "battery.capacity_wh", "battery = {")
case("energy-communication", energy("communication_w = -5.0"), E + "communication_w")
case("energy-home", energy("home = [0.0, 0.0]"), E + "home")
case("energy-return-speed", energy("return_speed_mps = 500.0"), E + "return_speed_mps")

# --- [transport.nats], checked whichever transport runs -----------------------------------------
for k, line in [("step_timout", "step_timout = 5"), ("step_timeout", "step_timeout = 0"),
                ("mirror", 'mirror = ["a..b"]'), ("heartbeat_timeout", "heartbeat_timeout = -1"),
                ("run_id", 'run_id = "a.b"'), ("spawn", 'spawn = "yes"'), ("tls_cert", 'tls_cert = "c.pem"')]:
    case(f"inprocess-nats-{line}", BASE + f"[transport.nats]\n{line}\n", f"transport.nats.{k}")
case("inprocess-nats-both-timeouts", rep("steps = 3", "steps = 3\nstep_timeout = 5.0")
     + "[transport.nats]\nstep_timeout = 5\n", "transport.nats.step_timeout", "step_timeout = 5\n")
case("inprocess-unknown-transport", BASE + "[transport.zmq]\nport = 1\n", "transport.zmq")
case("nats-mirror", BASE + NATS + '[transport.nats]\nmirror = ["x.>.y"]\n', "transport.nats.mirror")

# --- checkpoints ---------------------------------------------------------------------------------
for new in ("checkpoint_interval_s = -1.0", "checkpoint_interval_s = nan", "checkpoint_interval_s = inf",
            'checkpoint_interval_s = "1m"'):
    case(f"checkpoint-{new}", after('dir = "runs"', new), "output.checkpoint_interval_s", new)
for new in ("checkpoint_every = -1", "checkpoint_every = 1.5", 'checkpoint_every = "often"'):
    case(f"checkpoint-{new}", after('dir = "runs"', new), "output.checkpoint_every", new)

IDS = [c.id for c in CASES]
assert len(set(IDS)) == len(IDS), [i for i in IDS if IDS.count(i) > 1]
RUN_TOO = {"net-device-cuda99", "net-ues-per-sector-huge", "net-size-field-missing", "lidar-resolution-tiny",
           "lidar-rate-huge", "energy-air-density-tiny", "inprocess-nats-step_timout = 5",
           "inprocess-nats-step_timeout = 0", "inprocess-nats-mirror = [\"a..b\"]",
           "checkpoint-checkpoint_interval_s = -1.0"}


def test_the_corpus_is_large():
    assert len(CASES) >= 60, len(CASES)


@pytest.fixture(scope="module")
def corpus_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("corpus55")


def _write(work: pathlib.Path, text: str) -> pathlib.Path:
    work.mkdir()
    path = work / "cfg.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("c", CASES, ids=IDS)
def test_malformed_input_is_refused_naming_the_key(c, corpus_dir, capfd, monkeypatch):
    work = corpus_dir / f"{IDS.index(c.id):03d}"
    path = _write(work, c.text)
    monkeypatch.chdir(work)
    before = _listing(work)
    code = _core.main(["caviar-core", "validate", str(path)])
    out, err = capfd.readouterr()
    assert code == 2, f"validate: exit {code}\n{out}{err}"
    _check_message(c, path, err, out)
    if c.id in RUN_TOO:
        code = _core.main(["caviar-core", "run", "-q", str(path)])
        out, err = capfd.readouterr()
        assert code == 2, f"run: exit {code}\n{out}{err}"
        _check_message(c, path, err, out)
        assert _listing(work) == before, "run created files"


WARNINGS = [
    ("net-by-type-tank", net('traffic = { by_type = { Tank = { downlink = "none" } } }'),
     P + "traffic.by_type.Tank"),
    ("energy-ue-types-tank", energy('ue_types = ["UAV", "Tank"]'), E + "ue_types"),
]


@pytest.mark.parametrize("cid, text, key", WARNINGS, ids=[w[0] for w in WARNINGS])
def test_a_name_that_matches_nothing_shipped_is_a_warning_naming_the_key(cid, text, key, tmp_path, capfd):
    path = _write(tmp_path / cid, text)
    assert _core.main(["caviar-core", "validate", str(path)]) == 0
    err = capfd.readouterr().err
    assert f"warning: {key}: no shipped module publishes UEs of type 'Tank'" in err, err
    assert "Traceback" not in err


@pytest.mark.parametrize("text", [lidar("rate_hz = 200.0"), lidar("horizontal_resolution_deg = 0.001"),
                                  net("array = [64, 64]")], ids=["lidar-rate", "lidar-resolution", "net-array"])
def test_allow_large_lifts_a_bound_knowingly(text, tmp_path, capfd):
    header = "[modules.lidar.params]" if "lidar" in text else "[modules.net.params]"
    path = _write(tmp_path / "w", after(header, "allow_large = true", text))
    assert _core.main(["caviar-core", "validate", str(path)]) == 0, capfd.readouterr().err


def test_a_payload_without_its_size_field_stops_the_run_naming_the_key(tmp_path, capfd, monkeypatch):
    """A topic whose payloads no schema lists passes validate; its first message without the
    field ends the run with exit 2 (bad input), one line naming the key, no traceback."""
    text = (rep('stages = ["mobility", "work"]', 'stages = ["mobility", "count", "work"]', net(
        'traffic = { carry = [{ topic = "count.*", size_field = "bytes" }] }'))
        .replace("ues_per_sector = 2", "ues_per_sector = 0")
        + '[modules.count]\nstage = "count"\nplugin = "sample_plugins:Counter"\nparams = { topic = "count.uav1" }\n')
    path = _write(tmp_path / "w", text)
    monkeypatch.chdir(tmp_path / "w")
    code = _core.main(["caviar-core", "run", "-q", str(path), "--out", "run"])
    err = capfd.readouterr().err
    assert code == 2 and "Traceback" not in err, err
    first = next(line for line in err.splitlines() if line.startswith("error: "))
    assert first.startswith("error: module 'net' failed at step 0"), err
    assert "params.traffic.carry.0.size_field: a message on count.uav1: the payload has no field 'bytes'" in first, err
