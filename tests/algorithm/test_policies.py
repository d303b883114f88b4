"""The acting part: epsilon-greedy as the Lua code acts, and a user's own policy."""

from __future__ import annotations

import dataclasses
import sys
import types

import numpy as np
import pytest
import torch
from torch import nn

from dqnlab.algorithm.agent import Agent
from dqnlab.algorithm.policies import EpsilonGreedy, Policy, build_policy
from dqnlab.config import resolve_config
from dqnlab.errors import ConfigError

NATURE = resolve_config("nature", env="pong")


def test_epsilon_greedy_breaks_ties_at_random_and_needs_no_q_values_to_explore() -> None:
    policy = EpsilonGreedy(NATURE, 3)
    rng = np.random.default_rng(0)
    ties = {policy.choose(np.array([1.0, 1.0, 0.0]), 0.0, rng) for _ in range(50)}
    assert ties == {0, 1}

    def no_forward() -> np.ndarray:
        raise AssertionError("a random action asked for the Q-values")

    counts = np.bincount([policy.choose(no_forward, 1.0, rng) for _ in range(3000)], minlength=3)
    assert np.all(np.abs(counts - 1000) < 150)


def test_a_nan_q_value_gives_a_random_action_not_a_crash() -> None:
    # A diverged network acts before its update reports the NaN: the greedy choice has no
    # maximum then, and must not raise numpy's error in place of dqnlab's divergence message.
    policy = EpsilonGreedy(NATURE, 3)
    rng = np.random.default_rng(0)
    chosen = {policy.choose(np.array([1.0, np.nan, 0.0]), 0.0, rng) for _ in range(60)}
    assert chosen == {0, 1, 2}


class Softmax(Policy):
    """A user's policy: Boltzmann exploration at temperature epsilon."""

    def choose(self, q_values, epsilon, rng) -> int:  # noqa: ANN001
        values = q_values() if callable(q_values) else q_values
        logits = values / max(epsilon, 1e-8)
        probabilities = np.exp(logits - logits.max())
        return int(rng.choice(self.num_actions, p=probabilities / probabilities.sum()))


class Table(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.q = nn.Parameter(torch.tensor([0.0, 10.0]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.q.expand(len(x), 2)


def test_a_users_policy_part_chooses_the_agents_actions(monkeypatch) -> None:
    module = types.ModuleType("user_policies")
    module.Softmax = Softmax  # type: ignore[attr-defined]
    module.NoChoose = object  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "user_policies", module)
    config = dataclasses.replace(NATURE, policy="user_policies:Softmax")
    agent = Agent(Table(), 2, config, torch.device("cpu"), seed=0)
    assert isinstance(agent.policy, Softmax)
    observation = np.zeros((1,), dtype=np.float32)
    # Temperature 0.01: action 1 (Q 10) nearly always; temperature 100: both.
    assert {agent.act(observation, 0.01) for _ in range(50)} == {1}
    assert {agent.act(observation, 100.0) for _ in range(200)} == {0, 1}
    for path, message in [("user_policies:Missing", "cannot be loaded"),
                          ("user_policies:NoChoose", "failed to build")]:  # fmt: skip
        with pytest.raises(ConfigError, match=message) as error:
            build_policy(dataclasses.replace(NATURE, policy=path), 2)
        assert str(error.value).startswith(f"policy = {path!r}") and "\n" not in str(error.value)
