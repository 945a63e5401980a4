"""The plugin that stands in for the agent module: it hands its inbox to the environment
and publishes what the environment answers.

The environment replaces the agent module's plugin with :class:`AgentProxy` (keeping its
stage, ``every``/``offset`` and giving it the observation's topics as subscriptions)
and passes the address of its socket as the only parameter. The proxy speaks to the
environment over that local socket (:mod:`multiprocessing.connection`, pickled tuples)
whether it runs in-process or in a NATS worker process, so both transports take the
same path:

* proxy → environment: ``("hello", module)`` at setup, then every step
  ``("inbox", step, time, [(topic, source, step, time, data), ...])``, payloads decoded;
* environment → proxy: ``("publish", [(topic, payload), ...])``, the messages of the
  agents' actions, or ``("skip",)`` when the environment is closing the episode.
"""

from __future__ import annotations

import dataclasses
from multiprocessing.connection import Client, Connection
from typing import Any

from caviar.plugin import Inbox, Message, Plugin

WireMessage = tuple[str, "str | None", "int | None", "float | None", Any]
"""A message as it crosses the socket: topic, source, step, time and decoded payload."""


def to_wire(inbox: Inbox) -> list[WireMessage]:
    return [(m.topic, m.source, m.step, m.time, m.data) for m in inbox]


def from_wire(messages: list[WireMessage]) -> Inbox:
    return Inbox([Message(topic, data, source=source, step=step, time=time)
                  for topic, source, step, time, data in messages])


class AgentProxy(Plugin):
    """The agent module of a :mod:`caviar.gym` environment (set by the environment, not
    by hand). It declares no ``publishes``: it publishes what the agents' actions
    become."""

    @dataclasses.dataclass
    class Params:
        address: str = ""
        """The environment's socket (a path in a private temporary directory)."""

        def __post_init__(self):
            if not self.address:
                raise ValueError("address: the socket of the caviar.gym environment that drives this module "
                                 "(set by the environment; AgentProxy is not for configuration files)")

    def setup(self, ctx):
        self.ctx = ctx
        try:
            self.conn: Connection = Client(ctx.params.address, family="AF_UNIX")
        except OSError as e:
            raise RuntimeError(f"cannot reach the caviar.gym environment at {ctx.params.address}: {e}") from None
        self.conn.send(("hello", ctx.name))

    def step(self, t, inbox):
        try:
            self.conn.send(("inbox", self.ctx.step, t, to_wire(inbox)))
            answer = self.conn.recv()
        except (EOFError, OSError):
            raise RuntimeError("the caviar.gym environment went away (closed or its process ended)") from None
        if answer[0] == "skip":
            return []
        return answer[1]

    def teardown(self):
        conn = getattr(self, "conn", None)
        if conn is not None:
            conn.close()
