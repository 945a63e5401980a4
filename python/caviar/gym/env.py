"""Gymnasium and PettingZoo environments over any configuration: one module is the agent.

The module named ``agent`` keeps its stage and schedule, but its plugin is replaced by
:class:`~caviar.gym.proxy.AgentProxy`: at its turn in a step it hands its inbox to the
environment, which returns it as the observation; the action the caller gives to
``step()`` becomes the messages the module publishes in that same step; the reward is
a function of the messages of the steps run until the module's next turn.
What an agent sees, does and earns is an :class:`AgentSpec`; nothing here knows a
domain.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import pathlib
import subprocess
import sys
from typing import Any, Callable, Iterable, Mapping, Sequence

import gymnasium
from gymnasium import spaces
from pettingzoo import ParallelEnv

from caviar.errors import ConfigError
from caviar.gym.driver import End, EpisodeDriver, Turn, default_out, pythonpath_env
from caviar.plugin import Inbox, Message
from caviar.simulation import _overrides

NO_STEP_TIMEOUT_S = 7 * 24 * 3600.0
"""``episode.step_timeout`` the environments set unless told otherwise: the agent
module's step lasts as long as the caller takes to choose an action (a notebook may
wait for hours), and the in-process watchdog would end the process after 600 s."""


@dataclasses.dataclass(frozen=True)
class AgentSpec:
    """What one agent observes, does and earns.

    ``observe(inbox)`` turns the agent module's inbox (the messages on ``subscribe``
    since its previous turn) into an observation in ``observation_space``;
    ``act(action)`` turns an action in ``action_space`` into the ``(topic, payload)``
    messages the module publishes; ``reward(messages)`` is the reward of the messages
    of the steps run from the action until the module's next turn (or the episode's
    end); ``info(messages)``, optional, the step's ``info`` dict.
    """

    subscribe: tuple[str, ...]
    observation_space: spaces.Space
    action_space: spaces.Space
    observe: Callable[[Inbox], Any]
    act: Callable[[Any], Iterable[tuple[str, Any]]]
    reward: Callable[[Sequence[Message]], float]
    info: Callable[[Sequence[Message]], dict[str, Any]] | None = None


class _Episodes:
    """What both environments share: the configuration checks and the episode driver."""

    def __init__(self, config: str | os.PathLike, agent: str, specs: Mapping[str, AgentSpec], *,
                 max_steps: int | None, overrides: Mapping[str, Any] | Iterable[str] | None,
                 out: str | os.PathLike | None, check_wiring: bool):
        self.config = pathlib.Path(config)
        self.agent_module = agent
        self.specs = dict(specs)
        if not self.specs:
            raise ValueError("specs: expected at least one agent")
        if max_steps is not None and max_steps < 1:
            raise ValueError(f"max_steps: expected a positive number of the agent's steps, got {max_steps}")
        self.max_steps = max_steps
        user = _overrides(overrides)
        if not any(o.split("=", 1)[0].strip() == "episode.step_timeout" for o in user):
            user = [f"episode.step_timeout={NO_STEP_TIMEOUT_S}", *user]
        subscribe = list(dict.fromkeys(t for s in self.specs.values() for t in s.subscribe))
        check_agent(self.config, agent, user)
        if check_wiring:
            check_observed_topics(self.config, agent, subscribe, user)
        self._driver = EpisodeDriver(self.config, agent, subscribe, user,
                                     pathlib.Path(out) if out is not None else default_out())
        self._turn: Turn | None = None
        self._last_obs: dict[str, Any] = {}
        self._turns = 0

    @property
    def run_dir(self) -> pathlib.Path | None:
        """The run directory of the current (or last) episode."""
        return self._driver.run_dir

    def _start(self, seed: int) -> dict[str, Any]:
        event = self._driver.start(seed)
        self._turns = 0
        if isinstance(event, End):
            raise RuntimeError(f"{self.config}: the episode ended ({event.status.get('end_reason')}) before module "
                               f"'{self.agent_module}' had its first step")
        self._turn = event
        self._last_obs = {a: self._observe(a, event.inbox) for a in self.specs}
        return self._last_obs

    def _observe(self, agent: str, inbox: Inbox) -> Any:
        spec = self.specs[agent]
        obs = spec.observe(inbox)
        if not spec.observation_space.contains(obs):
            raise ValueError(f"observation of agent '{agent}' (module '{self.agent_module}') is outside its "
                             f"observation space {spec.observation_space}: {obs!r}")
        return obs

    def _act(self, actions: Mapping[str, Any]) -> tuple[list[Message], bool, bool]:
        """Publishes the agents' actions; (messages until the next turn, terminated, truncated)."""
        if self._turn is None:
            raise RuntimeError(f"no episode of module '{self.agent_module}' is running: call reset() first")
        published: list[tuple[str, Any]] = []
        for agent, action in actions.items():
            spec = self.specs.get(agent)
            if spec is None:
                raise ValueError(f"action for '{agent}', which is not an agent of module '{self.agent_module}' "
                                 f"(agents: {', '.join(self.specs)})")
            if not spec.action_space.contains(action):
                raise ValueError(f"action {action!r} of agent '{agent}' (module '{self.agent_module}') is outside "
                                 f"its action space {spec.action_space}")
            published.extend((str(topic), payload) for topic, payload in spec.act(action))
        event = self._driver.answer(published)
        self._turns += 1
        if isinstance(event, End):
            self._turn = None
            reason = event.status.get("end_reason")
            return event.messages, reason == "module", reason in ("steps", "closed")
        self._turn = event
        self._last_obs = {a: self._observe(a, event.inbox) for a in self.specs}
        if self.max_steps is not None and self._turns >= self.max_steps:
            self._driver.finish()
            self._turn = None
            return event.messages, False, True
        return event.messages, False, False

    def _info(self, agent: str, messages: Sequence[Message]) -> dict[str, Any]:
        spec = self.specs[agent]
        return spec.info(messages) if spec.info is not None else {}

    def _close(self) -> None:
        self._turn = None
        self._driver.close()


class CaviarEnv(_Episodes, gymnasium.Env):
    """A Gymnasium environment: module ``agent`` of ``config`` is the agent.

    ``reset(seed=s)`` starts a new episode (a new run directory under ``out``) with
    ``episode.seed = s`` (without a seed: one drawn from the environment's generator,
    itself seeded by the last seed given); the same seed gives the same observations
    and rewards. ``terminated``: a module ended the episode (``caviar.episode.end``);
    ``truncated``: the episode's own step limit (``episode.steps``/``duration``) or
    ``max_steps`` of the agent's steps. ``close()`` ends the episode in progress
    (run.json: ``end_reason = "closed"``). A module that fails raises
    :class:`caviar.RunError` naming it. ``overrides`` as for
    :meth:`caviar.Simulation.from_toml` (``{"transport.kind": "nats"}`` runs the other
    modules as NATS workers).
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, config: str | os.PathLike, agent: str, spec: AgentSpec, *, max_steps: int | None = None,
                 overrides: Mapping[str, Any] | Iterable[str] | None = None, out: str | os.PathLike | None = None,
                 check_wiring: bool = True):
        super().__init__(config, agent, {agent: spec}, max_steps=max_steps, overrides=overrides, out=out,
                         check_wiring=check_wiring)
        self.spec_ = spec
        self.observation_space = spec.observation_space
        self.action_space = spec.action_space

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        episode_seed = seed if seed is not None else int(self.np_random.integers(2**31))
        obs = self._start(episode_seed)
        return obs[self.agent_module], {}

    def step(self, action):
        messages, terminated, truncated = self._act({self.agent_module: action})
        reward = float(self.spec_.reward(messages))
        return (self._last_obs[self.agent_module], reward, terminated, truncated,
                self._info(self.agent_module, messages))

    def close(self) -> None:
        self._close()


class CaviarParallelEnv(_Episodes, ParallelEnv):
    """A PettingZoo ``ParallelEnv``: module ``agent`` of ``config`` plays several agents
    (one per UAV, say), each with its :class:`AgentSpec`; at the module's turn every
    live agent acts, and the module publishes all their messages. Episodes, seeds,
    termination and closing as in :class:`CaviarEnv`; every agent ends with the episode.
    """

    metadata: dict[str, Any] = {"render_modes": [], "name": "caviar_parallel_v0"}

    def __init__(self, config: str | os.PathLike, agent: str, specs: Mapping[str, AgentSpec], *,
                 max_steps: int | None = None, overrides: Mapping[str, Any] | Iterable[str] | None = None,
                 out: str | os.PathLike | None = None, check_wiring: bool = True):
        super().__init__(config, agent, specs, max_steps=max_steps, overrides=overrides, out=out,
                         check_wiring=check_wiring)
        self.possible_agents = list(self.specs)
        self.agents: list[str] = []
        self._seed_rng = gymnasium.utils.seeding.np_random(None)[0]

    @functools.lru_cache(maxsize=None)  # noqa: B019 (the same space object every time, as PettingZoo asks)
    def observation_space(self, agent: str) -> spaces.Space:
        return self.specs[agent].observation_space

    @functools.lru_cache(maxsize=None)  # noqa: B019
    def action_space(self, agent: str) -> spaces.Space:
        return self.specs[agent].action_space

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is not None:
            self._seed_rng = gymnasium.utils.seeding.np_random(seed)[0]
        episode_seed = seed if seed is not None else int(self._seed_rng.integers(2**31))
        obs = self._start(episode_seed)
        self.agents = list(self.possible_agents)
        return dict(obs), {a: {} for a in self.agents}

    def step(self, actions: Mapping[str, Any]):
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"step: no action for agent(s) {', '.join(missing)} of module '{self.agent_module}'")
        messages, terminated, truncated = self._act(actions)
        live = list(self.agents)
        rewards = {a: float(self.specs[a].reward(messages)) for a in live}
        infos = {a: self._info(a, messages) for a in live}
        if terminated or truncated:
            self.agents = []
        return ({a: self._last_obs[a] for a in live}, rewards, dict.fromkeys(live, terminated),
                dict.fromkeys(live, truncated), infos)

    def close(self) -> None:
        self._close()


def make(config: str | os.PathLike, agent: str, spec: AgentSpec, **kwargs: Any) -> CaviarEnv:
    """A Gymnasium environment in which module ``agent`` of ``config`` is the agent
    (see :class:`CaviarEnv` for the keyword arguments)."""
    return CaviarEnv(config, agent, spec, **kwargs)


def make_parallel(config: str | os.PathLike, agent: str, specs: Mapping[str, AgentSpec],
                  **kwargs: Any) -> CaviarParallelEnv:
    """A PettingZoo ``ParallelEnv`` in which module ``agent`` plays the agents of ``specs``."""
    return CaviarParallelEnv(config, agent, specs, **kwargs)


# ---------------------------------------------------------------------------
# Checks before anything runs

def _modules_of(config: pathlib.Path) -> list[str]:
    if sys.version_info >= (3, 11):
        import tomllib
    else:
        import tomli as tomllib
    try:
        text = config.read_text(encoding="utf-8")
    except OSError as e:
        raise ConfigError(f"{config}: cannot read the configuration: {e.strerror or e}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{config}: not valid TOML: {e}") from None
    modules = data.get("modules", {})
    return list(modules) if isinstance(modules, dict) else []


def check_agent(config: pathlib.Path, agent: str, overrides: Sequence[str]) -> None:
    """ConfigError unless ``agent`` is a module of ``config`` (or one its overrides add)."""
    modules = _modules_of(config)
    added = any(o.split("=", 1)[0].strip().startswith(f"modules.{agent}.") for o in overrides)
    if agent not in modules and not added:
        raise ConfigError(f"{config}: agent '{agent}' is not a module of the configuration "
                          f"(modules: {', '.join(modules) or 'none'})", f"modules.{agent}")


def check_observed_topics(config: pathlib.Path, agent: str, subscribe: Sequence[str],
                          overrides: Sequence[str]) -> None:
    """ConfigError if the configuration is wrong or if no module publishes a topic the
    agent observes, as ``caviar-core validate`` sees the wiring with the agent module
    subscribed to ``subscribe`` (its plugin still the configured one). Where a module does
    not declare what it publishes, nothing can be said (the core's rule)."""
    import json

    args = [sys.executable, "-m", "caviar.cli", "validate", str(config)]
    for o in [*overrides, f"modules.{agent}.subscribe={json.dumps(list(subscribe))}"]:
        args += ["--set", o]
    p = subprocess.run(args, capture_output=True, text=True, env=pythonpath_env(), timeout=300)
    if p.returncode != 0:
        raise ConfigError((p.stderr.strip() or p.stdout.strip()).removeprefix("error: "))
    prefix = f"modules.{agent}.subscribe: '"
    missing = [line.split(prefix, 1)[1].split("'", 1)[0] for line in (p.stdout + p.stderr).splitlines()
               if prefix in line and "no module publishes it" in line]
    if missing:
        raise ConfigError(f"{config}: agent module '{agent}' observes {', '.join(repr(t) for t in missing)}, "
                          f"which no module of the configuration publishes", f"modules.{agent}.subscribe")
