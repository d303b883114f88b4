"""The acting part: how an action is chosen from the Q-values of one state.

A policy part is a class built as `Class(config, num_actions)` and asked
`policy.choose(q_values, epsilon, rng) -> action`, where `epsilon` is the exploration rate
of the schedule at this step (training) or `eval_epsilon` (evaluation), `rng` the agent's
own generator (saved with every checkpoint, so a resumed run draws the same actions), and
`q_values` the online network's Q-values of the state: an array, or a function that
computes them, to call only when they are needed (a random action needs no forward pass).
Noisy networks (`noisy`) explore through the Q-values themselves: the agent draws fresh
noise before it computes them in training, whatever the policy.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from dqnlab.config import Config
from dqnlab.errors import ConfigError
from dqnlab.parts import load_part

QValues = np.ndarray | Callable[[], np.ndarray]


class Policy:
    """The interface of a policy part (and the base of the shipped one)."""

    def __init__(self, config: Config, num_actions: int) -> None:
        self.config = config
        self.num_actions = num_actions

    def choose(self, q_values: QValues, epsilon: float, rng: np.random.Generator) -> int:
        raise NotImplementedError


class EpsilonGreedy(Policy):
    """A uniform random action with probability epsilon, else the action of the highest
    Q-value, ties going to a random one of them (Lua NeuralQLearner:eGreedy and :greedy)."""

    def choose(self, q_values: QValues, epsilon: float, rng: np.random.Generator) -> int:
        if rng.random() < epsilon:
            return int(rng.integers(self.num_actions))
        values = q_values() if callable(q_values) else q_values
        best = np.flatnonzero(values == values.max())
        if len(best) == 0:  # a NaN among them (a diverged network): no greedy action, so a
            return int(rng.integers(self.num_actions))  # random one; the update says why
        return int(best[0] if len(best) == 1 else rng.choice(best))


def build_policy(config: Config, num_actions: int) -> Policy:
    """The policy part `policy` names: the shipped epsilon-greedy, or a user's `module:Class`."""
    if config.policy == "epsilon_greedy":
        return EpsilonGreedy(config, num_actions)
    policy = load_part("policy", config.policy, config, num_actions)
    if not callable(getattr(policy, "choose", None)):
        raise ConfigError(
            f"policy = {config.policy!r} built {type(policy).__name__}, which has no choose"
        )
    return policy  # type: ignore[no-any-return]
