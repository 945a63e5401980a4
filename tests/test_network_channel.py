"""The radio network's structure (issue #57 part 2): one channel protocol with a model per
module chosen once at set-up, settings that hold settings only, one torch device, and no
global Sionna seed left set."""

from __future__ import annotations

import ast
import dataclasses
import pathlib

import numpy as np
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
NETWORK = ROOT / "plugins" / "caviar_plugins" / "network"
SITES = [{"name": "A", "position": [0.0, 0.0, 25.0], "azimuths_deg": [0.0, 120.0, 240.0]},
         {"name": "B", "position": [400.0, 0.0, 25.0], "azimuths_deg": [180.0]}]


def _class_lines(path: pathlib.Path, name: str) -> tuple[int, ast.ClassDef]:
    tree = ast.parse(path.read_text())
    node = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == name)
    return node.end_lineno - node.lineno + 1, node


def test_the_network_plugin_is_small_and_never_asks_which_channel_it_has():
    lines, node = _class_lines(NETWORK / "plugin.py", "RadioNetwork")
    assert lines <= 250, lines
    names = {n.id for n in ast.walk(node) if isinstance(n, ast.Name)} | {
        n.attr for n in ast.walk(node) if isinstance(n, ast.Attribute)}
    strings = {n.value for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)}
    assert not names & {"SiteTracer", "StochasticChannel", "tracer", "stochastic", "line_of_sight_gain_db"}, names
    assert not strings & {"ray-traced", "free-space", "38.901-uma", "38.901-umi", "38.901-rma"}, strings


@pytest.mark.parametrize("kind, module", [("free-space", "free_space"), ("ray-traced", "traced_channel"),
                                          ("38.901-umi", "tr38901")])
def test_each_channel_is_one_model_of_its_own_module_behind_the_protocol(kind, module):
    from caviar._host import check_params
    from caviar_plugins.network.channel import UePlaces
    from caviar_plugins.network.plugin import RadioNetwork
    from caviar_plugins.network.settings import make_channel, plan
    from caviar_plugins.torch_device import resolve, to_numpy

    p = check_params(RadioNetwork, {"sites": SITES, "channel": kind, "link_model": "shannon", "carrier_hz": 3.5e9,
                                    "raytracing": {"samples_per_src": 1000, "max_depth": 0}})
    made = plan(p)
    channel = make_channel(kind, p, made.cells, link=made.link, device=resolve("cpu"), seed=3)
    assert type(channel).__module__ == f"caviar_plugins.network.{module}" and channel.kind == kind
    for member in ("kind", "directions", "flat", "gains_db", "beam_gains", "forget", "outdoors", "state", "restore"):
        assert hasattr(channel, member), member
    ues = UePlaces(["u1", "u2"], np.array([[100.0, 30.0, 1.5], [300.0, -40.0, 1.5]]), np.zeros(2, bool), np.zeros(2))
    gains = channel.gains_db(0.0, ues)
    gains = gains if isinstance(gains, np.ndarray) else to_numpy(gains)  # (a tensor where the channel computes)
    assert gains.shape[:2] == (2, len(made.cells)) and np.isfinite(gains).all()
    assert gains.shape[2] == (1 if channel.flat else made.link.subbands)
    assert channel.outdoors(ues.positions).all()  # (free space, an empty scene, no scene)
    if not channel.directions:
        with pytest.raises(ValueError, match="no path directions"):
            channel.beam_gains(ues, [])


def test_settings_hold_settings_only_and_the_plan_makes_the_rest():
    """``NetworkParams`` keeps its fields and nothing else; :func:`plan` builds the cells,
    codebooks and link settings from it (and checks them when the settings are made)."""
    from caviar._host import check_params
    from caviar_plugins.network.plugin import RadioNetwork
    from caviar_plugins.network.settings import plan

    p = check_params(RadioNetwork, {"sites": SITES, "beams": {"horizontal": 4}, "link_model": "shannon"})
    fields = {f.name for f in dataclasses.fields(p)}
    assert set(vars(p)) == fields, set(vars(p)) - fields
    made = plan(p)
    assert [c.name for c in made.cells] == ["A/0", "A/1", "A/2", "B/0"]
    assert made.codebooks is not None and len(made.codebooks) == 4 and made.link.num_prb == p.num_prb


def test_no_global_sionna_seed_stays_set_after_a_drop_or_a_38901_draw():
    """A drop and the 38.901 channel draw from seeds of their own and put Sionna's random
    state (and torch's default generator, which Sionna's seed setter reseeds) back as it was."""
    import torch
    from sionna.phy import config

    from caviar._host import check_params
    from caviar_plugins.network.channel import UePlaces
    from caviar_plugins.network.layout import drop_ues
    from caviar_plugins.network.plugin import RadioNetwork
    from caviar_plugins.network.settings import make_channel, plan
    from caviar_plugins.torch_device import resolve

    config.seed = 1234
    before = (config.seed, torch.default_generator.get_state().clone(),
              config.torch_rng("cpu").get_state().clone(), config.np_rng.bit_generator.state)
    p = check_params(RadioNetwork, {"channel": "38.901-uma", "link_model": "shannon", "layout": {
        "kind": "hex", "rings": 1, "isd_m": 500.0, "ues_per_sector": 2}})
    made = plan(p)
    assert p.layout is not None
    first = drop_ues(p.layout, "uma", p.carrier_hz, seed=7)
    again = drop_ues(p.layout, "uma", p.carrier_hz, seed=7)
    np.testing.assert_array_equal(first.positions, again.positions)  # (its own seed: the same drop)
    channel = make_channel("38.901-uma", p, made.cells, link=made.link, device=resolve("cpu"), seed=3)
    channel.gains_db(0.0, UePlaces([f"u{i}" for i in range(len(first.positions))], first.positions,
                                   first.indoor, first.distance_2d_in))
    after = (config.seed, torch.default_generator.get_state(), config.torch_rng("cpu").get_state(),
             config.np_rng.bit_generator.state)
    assert after[0] == before[0] == 1234
    assert torch.equal(after[1], before[1]) and torch.equal(after[2], before[2]) and after[3] == before[3]


def test_the_torch_device_is_resolved_once_at_set_up(tmp_path):
    import torch

    import caviar
    from caviar._host import check_params
    from caviar_plugins.network.plugin import RadioNetwork
    from caviar_plugins.radio.link_level import LinkLevel

    net = RadioNetwork()
    params = check_params(RadioNetwork, {"sites": SITES, "link_model": "sys", "device": "cpu"})
    net.setup(caviar.Context(name="net", params=params, seed=1, ts=0.01, steps=1, every=1, offset=0,
                             run_dir=tmp_path, config_dir=tmp_path))
    assert isinstance(net.device, torch.device) and net.device.type == "cpu"
    assert isinstance(net.link, LinkLevel) and net.link.device == net.device


def test_one_site_with_wraparound_runs(tmp_path):
    """``rings = 0`` (one site) with the default wraparound: nothing to wrap (it stopped at
    set-up on Sionna's "The number of rings must be positive"); the UEs are dropped and served."""
    import caviar

    cfg = tmp_path / "one.toml"
    cfg.write_text('[episode]\nts = 0.01\nsteps = 2\nseed = 2\nstages = ["c"]\n[output]\n'
                   'analysis = ["network.ue", "network.events", "network.cells", "communications.throughput"]\n'
                   '[modules.net]\nstage = "c"\nplugin = "radio-network"\n[modules.net.params]\n'
                   'channel = "38.901-uma"\nlink_model = "shannon"\n'
                   'layout = { kind = "hex", rings = 0, isd_m = 500.0, ues_per_sector = 2 }\n')
    log = caviar.Simulation.from_toml(cfg, out=tmp_path / "run").run(progress=False)
    ues = [m.data for m in log.decoded("network.ue")]
    assert len(ues) == 2 * 3 * 2 and {u["UE_Id"] for u in ues} == {f"drop{k}" for k in range(6)}


def test_a_link_level_draws_from_its_own_stream_and_sets_no_global_seed():
    """Two link levels (a downlink's and an uplink's) each keep their own stream: making the
    second leaves the first's draws and Sionna's and torch's global generators as they were."""
    import torch
    from sionna.phy import config

    from caviar_plugins.radio.link_level import LinkLevel
    from caviar_plugins.radio.link_settings import LinkSettings

    config.seed = 99
    before = (config.seed, torch.default_generator.get_state().clone(), config.torch_rng("cpu").get_state().clone())
    settings = LinkSettings(num_prb=51, subcarrier_spacing_hz=30e3, device="cpu")
    down = LinkLevel(settings, n_cell=2, seed=1)
    first = torch.rand(4, generator=down.phy.torch_rng)
    alone = LinkLevel(settings, n_cell=2, seed=1)
    LinkLevel(settings, n_cell=2, seed=2)  # (the uplink's, made after: it used to reseed the first)
    assert torch.equal(torch.rand(4, generator=alone.phy.torch_rng), first)
    assert down.phy.torch_rng is not alone.phy.torch_rng
    after = (config.seed, torch.default_generator.get_state(), config.torch_rng("cpu").get_state())
    assert after[0] == before[0] == 99 and torch.equal(after[1], before[1]) and torch.equal(after[2], before[2])
