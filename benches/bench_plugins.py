"""Plugins for the benchmarks."""

import caviar


class Noop(caviar.Plugin):
    publishes = ()

    def step(self, t, inbox):
        return None


class Relay(caviar.Plugin):
    """Publishes one small JSON message per step (paper schema) and reads its inbox."""

    subscribe = ["bench.>"]
    publishes = ("bench.*",)

    def step(self, t, inbox):
        for m in inbox:
            _ = m.data  # decoded, as a real module would
        return [("bench." + self.ctx.name, {"UE_type": "UAV", "UE_Id": self.ctx.name, "throughput": t})]
