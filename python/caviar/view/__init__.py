"""Watch the twin: a live and replay view of a run in the browser.

``caviar-core view RUN_DIR`` (:func:`caviar.view.cli.main`) serves a page with the
run's 3D scene (three.js), a timeline to scrub and play the recorded steps, and plots
(throughput and SNR per UE, events, time per module, the camera frame). While
the run is still going the page follows its newest step (server-sent events, from the
per-step Parquet parts the recorder writes). ``caviar-core run CONFIG --view`` uses
:func:`start_server`, which serves from a background thread.

The server binds 127.0.0.1 by default, answers GET and HEAD only and hands out only
its own static files, files under the run directory and the meshes the run's scene
XML references. The page loads nothing from any other host.

What is drawn
=============

The view itself knows only the core's topics. Which topics carry positions, link data,
frames and events, where scenes are, the default scene and transmitter, are the
plugins' to say: each package registers a :class:`~caviar.view.contract.ViewContract`
in entry-point group ``caviar.view`` and the view merges them (the page gets the
topics in ``/api/run``, ``contract``, and labels its plots with them). Without any,
the view shows the steps, the timings and the ``view.*`` drawings. With
``caviar_plugins`` installed (its contract is ``caviar_plugins.schema.VIEW``):

* Entities: every ``UE_Id`` on ``3D.mobility.positions`` (payload
  ``{"UE_type", "UE_Id", "position": {"x", "y", "z"}}`` or a list of them; scene
  frame, metres), with its trail up to the current step. Markers are not to scale.
* The transmitter: ``tx_position`` of a module's parameters, else the default of its
  plugin (``free-space-link``, ``sionna-link``).
* Beams: for each UE with a radio message at the step, a cone from the Tx toward the
  UE. The beam's steering angle is not recorded by the shipped plugins, so the cone
  shows *which UE is served by the selected beam pair* (its index from
  ``communications.link`` ``pair``), not the lobe's true direction; a
  ``communications.link`` message with ``beam_azimuth_deg`` and ``beam_elevation_deg``
  (Tx frame: azimuth from +x toward +y, elevation from the xy plane) is drawn in that
  direction instead. Colour: LOS green, NLOS red, unknown grey
  (``communications.link`` ``los``).
* Plots: ``communications.throughput`` ``throughput`` (Mbit/s) and
  ``communications.link`` ``snr_db`` per UE; ``mission.*`` events, ``network.events``
  (attach, handover, radio-link failure) and ``ai.detections`` with a non-zero
  ``count``; wall time per module per step (``timings``); the image on
  ``3D.camera.<UE_Id>`` or ``ai.images.<UE_Id>`` (uint8 H×W×3 array) at the current
  step, where recorded.

``view.*`` topics: primitives any module can draw
=================================================

A module publishes a JSON object on a topic starting with ``view.`` (for example
``view.detector``); the page draws the latest such message of each (source, topic) at
or before the current step, so a module republishes only when its drawing changes
and publishes ``{}`` to clear it::

    {
      "points": [{"x": 1.0, "y": 2.0, "z": 0.0, "color": "#ff0000", "size": 6, "label": "p1"}],
      "lines":  [{"points": [[0, 0, 0], [10, 0, 5]], "color": "#00ffff"}],
      "labels": [{"x": 0, "y": 0, "z": 30, "text": "hello", "color": "#ffffff"}],
      "images": [{"file": "artifacts/map.png", "extent": [-200, 200, -150, 150], "z": 1.5,
                  "opacity": 0.6, "label": "a map"}]
    }

Coordinates are the scene frame (x east, y north, z up, metres). Every key is
optional; ``color`` is a CSS hex colour (default yellow), ``size`` is in pixels
(default 6), ``label`` puts a text label next to a point.

``images`` are ground overlays (a map of the area, say): the PNG ``file`` (its path
relative to the run directory; the module writes it there, e.g. under
``ctx.run_dir``) drawn on a horizontal plane at height ``z`` (metres, default 0) that
covers ``extent`` = ``[x0, x1, y0, y1]`` (metres), with ``opacity`` (0 to 1, default
0.6) on top of the PNG's own alpha and an optional ``label`` at its north-west corner.
The image is read as a normal picture: its first row is the north edge (``y1``), its
first column the west edge (``x0``); pixels are not smoothed, so a map with one pixel
per cell shows its cells. The page's *layers* box shows or hides them all. The server
hands out only files an ``images`` entry of a recorded message names, and only PNGs
inside the run directory (``/api/layer?file=NAME``).
"""

from caviar.view.data import RunData, RunDirError
from caviar.view.server import ViewServer, start_server

__all__ = ["RunData", "RunDirError", "ViewServer", "start_server"]
