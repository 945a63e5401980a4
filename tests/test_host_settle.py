"""The host freezes what a plugin's set-up and first step made out of Python's cyclic garbage
collector (``gc.freeze``: the collections a step's allocations trigger then walk only the step's
own objects) and gives it back at teardown (``gc.unfreeze``), so that a process running one
simulation after another (a test session, a notebook) collects each run's objects again."""

from __future__ import annotations

import dataclasses
import gc

import caviar
from caviar._host import Hosted


class _Keeper(caviar.Plugin):
    """Keeps a cycle made at set-up and one made at its first step."""

    stateless = True

    @dataclasses.dataclass
    class Params:
        pass

    def setup(self, ctx):
        self.made = [[]]
        self.made[0].append(self.made)  # (a cycle)

    def step(self, t, inbox):
        if not hasattr(self, "later"):
            self.later = {"self": None}
            self.later["self"] = self.later
        yield "keeper.t", {"t": t}


def test_setup_and_the_first_step_are_frozen_until_teardown(tmp_path):
    gc.unfreeze()
    hosted = Hosted("keeper", _Keeper(), _Keeper.Params())
    hosted.setup(seed=1, ts=0.1, steps=None, every=1, offset=0, run_dir=str(tmp_path), config_dir=str(tmp_path))
    after_setup = gc.get_freeze_count()
    assert after_setup > 0 and not hosted.settled
    assert hosted.step(0, 0.0, []) == [("keeper.t", "json", '{"t":0.0}', None)]
    assert hosted.settled and gc.get_freeze_count() > after_setup  # (the first step's objects too)
    frozen = gc.get_freeze_count()
    hosted.step(1, 0.1, [])
    assert gc.get_freeze_count() <= frozen  # (later steps: nothing more frozen; a frozen object freed leaves)
    hosted.teardown()
    assert gc.get_freeze_count() == 0  # (all given back to the collector)


class _Quiet(caviar.Plugin):
    """Publishes nothing (its step returns None)."""

    stateless = True

    @dataclasses.dataclass
    class Params:
        pass

    def step(self, t, inbox):
        return None


def test_a_plugin_that_publishes_nothing_settles_after_its_first_step_too(tmp_path):
    gc.unfreeze()
    hosted = Hosted("quiet", _Quiet(), _Quiet.Params())
    hosted.setup(seed=1, ts=0.1, steps=None, every=1, offset=0, run_dir=str(tmp_path), config_dir=str(tmp_path))
    assert hosted.step(0, 0.0, []) == [] and hosted.settled
    hosted.teardown()
    assert gc.get_freeze_count() == 0
