"""Small plugins for the tests of caviar.gym: a target to guess, a guesser (the module the
environment replaces) and a judge that scores the guess in the same step."""

import dataclasses

import caviar


class Target(caviar.Plugin):
    """A random target in [-1, 1] each step, from the module's seeded generator; ends the
    episode at step ``end_at`` (0: never)."""

    publishes = ("toy.target", caviar.END_TOPIC)
    stateless = True

    @dataclasses.dataclass
    class Params:
        end_at: int = 0

    def step(self, t, inbox):
        yield "toy.target", {"value": float(self.ctx.rng.uniform(-1.0, 1.0))}
        if self.ctx.params.end_at and self.ctx.step == self.ctx.params.end_at:
            yield caviar.END_TOPIC, {"why": "target reached its last step"}


class Guesser(caviar.Plugin):
    """Guesses the target (what an agent would publish)."""

    subscribe = ["toy.target"]
    publishes = ("toy.guess",)
    stateless = True

    def step(self, t, inbox):
        m = inbox.latest("toy.target")
        if m is not None:
            yield "toy.guess", {"value": m.data["value"]}


class Judge(caviar.Plugin):
    """Scores the step's guess against the step's target; fails on a guess of ``fail_on``."""

    subscribe = ["toy.target", "toy.guess"]
    publishes = ("toy.score",)
    stateless = True

    @dataclasses.dataclass
    class Params:
        fail_on: float = 99.0

    def step(self, t, inbox):
        target, guess = inbox.latest("toy.target"), inbox.latest("toy.guess")
        if target is None or guess is None:
            return
        if guess.data["value"] == self.ctx.params.fail_on:
            raise ValueError(f"the judge refuses the guess {guess.data['value']}")
        yield "toy.score", {"error": abs(guess.data["value"] - target.data["value"])}
