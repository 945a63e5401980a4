"""NATS subject matching: the core's own rules, from ``caviar._core``."""

from __future__ import annotations

from caviar._core import matches

__all__ = ["matches"]
