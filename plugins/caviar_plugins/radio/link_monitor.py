"""Collects throughput per UE and, at the end of the episode, writes a CSV and a
plot of throughput against time into the run directory (as artifacts)."""

from __future__ import annotations

import csv
import dataclasses

import caviar
from caviar_plugins.schema import LINK_REPORT, POSITIONS, THROUGHPUT, read_position

NO_POSITION = (None, None, None)


class LinkMonitor(caviar.Plugin):
    subscribe = [THROUGHPUT, POSITIONS, caviar.END_TOPIC]
    publishes = (LINK_REPORT,)

    @dataclasses.dataclass
    class Params:
        plot: bool = True

    def setup(self, ctx):
        self.ctx = ctx
        self.rows = []  # (time, UE_Id, throughput, x, y, z)
        self.pos = {}

    def step(self, t, inbox):
        for m in inbox:
            if m.topic == POSITIONS:
                self.pos[m.data["UE_Id"]] = tuple(read_position(m.data).tolist())
            elif m.topic == THROUGHPUT:
                x, y, z = self.pos.get(m.data["UE_Id"], NO_POSITION)
                self.rows.append((m.time, m.data["UE_Id"], m.data["throughput"], x, y, z))
        last = self.ctx.steps is not None and self.ctx.step + 1 >= self.ctx.steps
        if inbox.latest(caviar.END_TOPIC) or last:
            yield LINK_REPORT, caviar.Artifact(self.write_report())
            if self.ctx.params.plot:
                yield LINK_REPORT, caviar.Artifact(self.write_plot())

    def state(self):
        return {"rows": self.rows, "pos": self.pos}

    def restore(self, state):
        self.rows, self.pos = state["rows"], state["pos"]

    def write_report(self):
        path = self.ctx.artifact_dir / "throughput.csv"
        with path.open("w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["time_s", "UE_Id", "throughput_mbps", "x", "y", "z"])
            w.writerows(self.rows)
        return path

    def write_plot(self):
        # A Figure of its own, not pyplot: the plot is drawn without a display and the host's
        # backend (a notebook's inline plots, say) is left as it was.
        from matplotlib.figure import Figure

        fig = Figure(figsize=(11, 4))
        ax1, ax2 = fig.subplots(1, 2)
        for ue in sorted({r[1] for r in self.rows}):
            rows = [r for r in self.rows if r[1] == ue]
            ax1.plot([r[0] for r in rows], [r[2] for r in rows], label=ue)
            ax2.plot([r[3] for r in rows], [r[4] for r in rows], label=ue)
        ax1.set(xlabel="virtual time (s)", ylabel="throughput (Mbit/s)", title="Throughput")
        ax2.set(xlabel="x (m)", ylabel="y (m)", title="Flight (scene frame)", aspect="equal")
        ax1.grid(True)
        ax2.grid(True)
        ax1.legend()
        fig.tight_layout()
        path = self.ctx.artifact_dir / "throughput.png"
        fig.savefig(path, dpi=100)
        return path
