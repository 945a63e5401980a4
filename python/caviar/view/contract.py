"""What the view draws, by topic: a small contract that plugin packages fill.

The generic view knows the core's topics only (``caviar.*``, and ``view.*`` for drawing
primitives any module may publish). Which topics carry positions, per-UE link data,
camera frames and events, and where the scenes are, is the plugins' knowledge: a
package declares it as a :class:`ViewContract` and registers it in the entry-point
group ``caviar.view`` (``caviar_plugins``: ``paper = "caviar_plugins.schema:VIEW"``).
The view merges every registered contract when it starts and sends the page the
topics (:meth:`ViewContract.for_page`).
"""

from __future__ import annotations

import dataclasses
from importlib.metadata import entry_points

GROUP = "caviar.view"


@dataclasses.dataclass(frozen=True)
class ViewContract:
    positions: tuple[str, ...] = ()
    """Topics whose payloads are positions, ``{"UE_Id", "UE_type", "position": {x, y, z}}``
    (or a list of them): the moving entities."""
    throughput: tuple[str, ...] = ()
    """Topics with ``{"UE_Id", "throughput"}`` (Mbit/s): the throughput plot."""
    link: tuple[str, ...] = ()
    """Topics with per-UE link details ``{"UE_Id", "snr_db", "los", "pair"}`` (and
    ``throughput`` when no throughput topic gave one)."""
    frame_prefixes: tuple[str, ...] = ()
    """Prefixes of topics carrying images (uint8 H×W×{1,3,4} binary payloads)."""
    event_prefixes: tuple[str, ...] = ()
    """Prefixes of topics whose messages are events on the timeline."""
    event_topics: tuple[str, ...] = ()
    """Single topics whose messages are events."""
    event_requires: tuple[tuple[str, str], ...] = ()
    """``(topic, field)``: a message of ``topic`` is an event only when ``field`` of its
    payload is truthy (detections that found nothing are not events)."""
    default_transmitters: tuple[tuple[str, tuple[float, float, float]], ...] = ()
    """``(plugin, position)``: where a plugin's transmitter is when its module's
    parameters give no ``tx_position``."""
    scene_dirs: tuple[str, ...] = ()
    """Folders holding scenes as ``NAME/NAME.xml``: where a scene named by a ``scene``
    parameter (or :attr:`default_scene`) is looked for."""
    default_scene: str = ""
    """The scene a run shows when no module names one (``scene`` parameter)."""

    def merged(self, other: ViewContract) -> ViewContract:
        """Both contracts' entries (each once, in order); the first default scene."""
        fields = {f.name: tuple(dict.fromkeys(getattr(self, f.name) + getattr(other, f.name)))
                  for f in dataclasses.fields(self) if f.name != "default_scene"}
        return ViewContract(**fields, default_scene=self.default_scene or other.default_scene)

    def is_event(self, topic: str) -> bool:
        return topic.startswith(self.event_prefixes) or topic in self.event_topics

    def is_frame(self, topic: str) -> bool:
        return topic.startswith(self.frame_prefixes)

    def for_page(self) -> dict[str, list[str]]:
        """The topics, as the page gets them (``contract`` in ``/api/run``): it labels its
        plots with them and shows frames of the first prefix first."""
        return {name: list(getattr(self, name)) for name in PAGE_FIELDS}


PAGE_FIELDS = ("positions", "throughput", "link", "frame_prefixes", "event_prefixes", "event_topics")
"""The fields of a :class:`ViewContract` the page is sent."""


CORE = ViewContract(event_topics=("caviar.episode.end",))
"""The core's own: the end of an episode is an event."""


def registered() -> ViewContract:
    """:data:`CORE` merged with every contract registered in group ``caviar.view``."""
    contract = CORE
    for ep in sorted(entry_points(group=GROUP), key=lambda e: e.name):
        value = ep.load()
        if not isinstance(value, ViewContract):
            raise TypeError(f"entry point '{ep.name}' of group {GROUP} ({ep.value}) is not a ViewContract")
        contract = contract.merged(value)
    return contract
