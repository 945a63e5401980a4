"""The radio map's layer for the browser view (caviar_plugins.network.radio_map):
``radio-map-layer.png`` has one pixel per map cell in the figure's colours, north up,
transparent where no cell serves; ``layer_message`` lays it over the map's cells; and the
view serves it when the message is recorded. No ray tracing: a synthetic map."""

from __future__ import annotations

import http.client
import json
import urllib.parse

import numpy as np
import pytest

import caviar
from caviar.view import RunData, start_server
from caviar_plugins.network import radio_map
from conftest import write_config
from sample_plugins import synthetic_radio_map


def test_the_layer_is_the_sinr_one_pixel_per_cell_north_up(tmp_path):
    import matplotlib
    import matplotlib.image

    result, cells = synthetic_radio_map()
    files = radio_map.save(result, cells, tmp_path)
    assert [f.name for f in files] == ["radio-map.npz", "radio-map.png", "radio-map-layer.png"]
    assert files[2] == tmp_path / radio_map.LAYER_FILE
    png = np.round(matplotlib.image.imread(files[2]) * 255).astype(np.uint8)  # as written, RGBA
    assert png.shape == (3, 4, 4)
    viridis = matplotlib.colormaps["viridis"]
    for row in range(3):
        for col in range(4):
            v = result["sinr_db"][2 - row, col]  # row 0 is the northmost y (120 m)
            if np.isnan(v):
                assert png[row, col, 3] == 0, (row, col)
                continue
            want = viridis(min(max((v + 10.0) / 50.0, 0.0), 1.0), bytes=True)
            assert tuple(png[row, col]) == tuple(want), (row, col, v)
    assert tuple(png[2, 0]) == tuple(png[2, 1]) == viridis(0.0, bytes=True)  # -20 and -10 dB: the bottom
    assert tuple(png[0, 2]) == tuple(png[0, 3]) == viridis(1.0, bytes=True)  # 40 and 55 dB: the top
    assert (png[..., 3] == 255).sum() == 11


def test_the_layer_message_covers_the_map_cells():
    result, _ = synthetic_radio_map()
    msg = radio_map.layer_message(result, "radio-map-layer.png", height_m=1.5)
    assert msg == {"images": [{"file": "radio-map-layer.png", "extent": [-5.0, 35.0, 95.0, 125.0], "z": 1.5,
                               "opacity": 0.6, "label": "best-server SINR (dB)"}]}
    assert json.loads(json.dumps(msg, allow_nan=False)) == msg
    x0, x1, y0, y1 = msg["images"][0]["extent"]
    assert (x1 - x0, y1 - y0) == (4 * 10.0, 3 * 10.0)  # 4 x 3 pixels of 10 m
    one_row = dict(result, y=result["y"][:1], sinr_db=result["sinr_db"][:1])
    assert radio_map.layer_message(one_row, height_m=0.0)["images"][0]["extent"] == [-5.0, 35.0, 95.0, 105.0]
    with pytest.raises(ValueError, match="one cell"):
        radio_map.layer_message(dict(result, x=result["x"][:1], y=result["y"][:1]), height_m=0.0)


def test_the_view_serves_the_layer_the_network_names(tmp_path):
    """A module saves the map into its run directory and publishes layer_message on a
    view.* topic, as the radio network does: the view serves that PNG."""
    cfg = write_config(tmp_path, """
[episode]
ts = 0.5
steps = 2
seed = 1
stages = ["communications"]

[modules.net]
stage = "communications"
plugin = "sample_plugins:RadioMapLayer"
""")
    run = tmp_path / "run"
    caviar.Simulation.from_toml(cfg, out=run).run()
    data = RunData(run)
    [msg] = [v for v in data.view if v["topic"] == "view.radio_map"]
    name = msg["data"]["images"][0]["file"]
    assert name == "radio-map-layer.png" and data.view_images == {name}
    srv = start_server(run, pending=False)
    try:
        c = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=5)
        c.request("GET", "/api/layer?file=" + urllib.parse.quote(name))
        r = c.getresponse()
        assert (r.status, r.getheader("Content-Type")) == (200, "image/png")
        assert r.read() == (run / name).read_bytes()
        c.request("GET", "/api/layer?file=radio-map.png")  # in the run directory, but no message names it
        r = c.getresponse()
        assert r.status == 404
        r.read()
        c.close()
    finally:
        srv.stop()
