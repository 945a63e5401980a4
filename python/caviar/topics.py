"""NATS subject matching, the same rules as the core's router."""

from __future__ import annotations


def matches(pattern: str, topic: str) -> bool:
    """True if ``topic`` matches ``pattern`` (``*``: one token, ``>``: the rest)."""
    parts = topic.split(".")
    tokens = pattern.split(".")
    for i, token in enumerate(tokens):
        if token == ">":
            return len(parts) > i
        if i >= len(parts) or (token != "*" and token != parts[i]):
            return False
    return len(parts) == len(tokens)
