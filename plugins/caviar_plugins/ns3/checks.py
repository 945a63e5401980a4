"""Every ns-3 setting checked against what ns-3 accepts, before anything runs.

ns-3 itself is asked, in a way that cannot abort this process: the attribute is looked up
by name (``TypeId::LookupAttributeByName``), and the value parsed by the attribute's own
checker (``CreateValidValue``, as ``Config::SetDefault`` does) in a child process
(``caviar_ns3::CheckValue`` forks): ns-3 aborts on some values it cannot parse (an enum
name it does not know, a time or a rate it cannot read), and then only the child does, its
message in hand. Each check costs about 20 ms.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from caviar_plugins.ns3.native import load, ns3_words

DATA_RATE = "ns3::PointToPointNetDevice::DataRate"
"""The attribute whose checker reads a data rate ("10Mbps")."""
QUEUE_SIZE = "ns3::DropTailQueue<Packet>::MaxSize"
"""The attribute whose checker reads a queue size ("100p", "64KB")."""
SCHEDULER_BASE = "ns3::FfMacScheduler"

EXPECTED = {
    "ns3::DoubleValue": "a number",
    "ns3::UintegerValue": "an integer >= 0 within the attribute's range",
    "ns3::IntegerValue": "an integer within the attribute's range",
    "ns3::BooleanValue": "true or false",
    "ns3::TimeValue": 'a time with its unit, such as "10ms" or "1.5s"',
    "ns3::DataRateValue": 'a rate with its unit, such as "10Mbps"',
    "ns3::QueueSizeValue": 'a size in packets or bytes, such as "100p" or "64KB"',
    "ns3::TypeIdValue": 'an ns-3 type name, such as "ns3::PfFfMacScheduler"',
}
"""What a value of each attribute type looks like, in words (an enum's names come in ns-3's
own message)."""


def not_taken(attribute: str, text: str) -> str:
    """ns-3's words on ``text`` as a value of ``attribute`` ("ns3::Class::Name"): "" if it
    takes it."""
    said = str(load().caviar_ns3.CheckValue(attribute, text))
    return ns3_words(said) if said else ""


def attribute_text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def check_attributes(attributes: Mapping[str, Any], *, set_defaults: bool = True) -> None:
    """Checks ns-3 attribute defaults (``{"ns3::LteUePhy::TxPower": 23}``) and sets them
    (``set_defaults``); raises ``ValueError('attributes."NAME": …')`` for one that does not
    exist, whose value ns-3 does not take, or that cannot be set as a default."""
    c = load().caviar_ns3
    for name, value in attributes.items():
        text = attribute_text(value)
        kind = str(c.AttributeType(name))
        if not kind:
            raise ValueError(f'attributes."{name}": ns-3 has no such attribute (expected '
                             '"ns3::Class::Attribute" = value, e.g. "ns3::LteUePhy::TxPower" = 23)')
        said = not_taken(name, text)
        if said:
            expected = ("one of the enum's names" if kind.startswith("ns3::EnumValue")
                        else EXPECTED.get(kind, f"a value ns-3 reads as a {kind}"))
            raise ValueError(f'attributes."{name}": expected {expected}, got {text!r} (ns-3: {said})')
        if set_defaults and not c.SetDefault(name, text):
            raise ValueError(f'attributes."{name}": ns-3 cannot set it as a default (an attribute of a parent '
                             "class? name the class that declares it)")


def check_settings(lte: Any, p2p: Any) -> None:
    """The LTE and point-to-point settings (:class:`~caviar_plugins.ns3.simulator.LteSettings`,
    :class:`~caviar_plugins.ns3.simulator.P2pSettings`) against ns-3; raises
    ``ValueError("lte.scheduler: …")``."""
    c = load().caviar_ns3
    schedulers = str(c.ChildrenOf(SCHEDULER_BASE)).split(",")
    if lte.scheduler not in schedulers:
        raise ValueError(f"lte.scheduler: expected one of ns-3's LTE MAC schedulers ({', '.join(schedulers)}), "
                         f"got {lte.scheduler!r}")
    for key, text in (("lte.backhaul_rate", lte.backhaul_rate), ("p2p.rate", p2p.rate)):
        said = not_taken(DATA_RATE, text) if isinstance(text, str) else "not a string"
        if said or not c.RateBps(text) > 0:
            raise ValueError(f"{key}: expected a rate > 0 with its unit, such as \"10Mbps\" or \"1Gbps\", "
                             f"got {text!r}" + (f" (ns-3: {said})" if said else ""))
    said = not_taken(QUEUE_SIZE, p2p.queue) if isinstance(p2p.queue, str) else "not a string"
    if said:
        raise ValueError(f"p2p.queue: expected a size in packets or bytes, such as \"100p\" or \"64KB\", "
                         f"got {p2p.queue!r} (ns-3: {said})")


def check_seconds(key: str, value: Any) -> None:
    """A duration in seconds: a finite number >= 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
        raise ValueError(f"{key}: expected a duration >= 0 in seconds, got {value!r}")
