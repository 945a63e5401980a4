"""The twin for machine learning: Gymnasium and PettingZoo environments over any
configuration (``pip install caviar[ml]``).

One module of the configuration becomes the agent: its inbox is the observation, the
action is what it publishes, and the reward is a function of the step's messages::

    env = caviar.gym.make("blueprints/beam-gym/config.toml", agent="beams", spec=spec)
    obs, info = env.reset(seed=1)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())

``spec`` (an :class:`AgentSpec`) says which topics the agent observes and how its inbox
becomes an observation, how an action becomes messages and what the reward is;
:func:`make_parallel` makes a PettingZoo ``ParallelEnv`` in which the module plays
several agents (one per UAV). The domain's specs live with the domain's plugins (the
beam-selection task: :mod:`caviar_plugins.beam_selection.gym_task`).
"""

from caviar.gym.env import AgentSpec, CaviarEnv, CaviarParallelEnv, make, make_parallel
from caviar.gym.proxy import AgentProxy

__all__ = ["AgentProxy", "AgentSpec", "CaviarEnv", "CaviarParallelEnv", "make", "make_parallel"]
