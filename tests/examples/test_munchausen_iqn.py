"""The Munchausen-IQN example (examples/munchausen_iqn.py): its target against the paper's
formula in a plain loop, its settings, and a short training run through the head and loss
parts."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from dqnlab.algorithm.losses import Transitions
from dqnlab.algorithm.quantile import ImplicitQuantileHead
from dqnlab.config import resolve_config
from dqnlab.errors import ConfigError
from dqnlab.run.state import TrainingState
from examples.munchausen_iqn import MunchausenIQNLoss

PART = "examples.munchausen_iqn:MunchausenIQNLoss"
Q = [[0.10, 0.12], [1.0, 1.05]]  # the mean value of each state (row) and action (column)


class KnownHead(ImplicitQuantileHead):
    """Z_tau(s, a) = Q[s][a] + tau - 0.5: the mean over fractions drawn evenly is Q."""

    def __init__(self) -> None:
        super().__init__(1, None, 2, embedding_dim=1, acting_samples=4)

    def quantile_values(self, features: torch.Tensor, fractions: torch.Tensor) -> torch.Tensor:
        means = torch.tensor(Q)[features.long().view(-1)]  # (batch, actions)
        return means.unsqueeze(2) + fractions.unsqueeze(1) - 0.5

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        evenly = torch.tensor([0.125, 0.375, 0.625, 0.875]).expand(features.shape[0], 4)
        return self.quantile_values(features, evenly)


class KnownNetwork(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.torso, self.head = nn.Identity(), KnownHead()


def test_the_target_is_the_papers_formula_at_each_fraction() -> None:
    config = resolve_config("iqn", env="CartPole-v1", loss=PART)
    assert config.parts["loss"] == {
        "kappa": 1.0, "online_samples": 64, "target_samples": 64,
        "tau": 0.03, "alpha": 0.9, "l0": -1.0,
    }  # fmt: skip
    loss = MunchausenIQNLoss(config)
    loss.generator = torch.Generator().manual_seed(0)
    batch = Transitions(
        observations=torch.tensor([0, 0]), actions=torch.tensor([0, 1]),
        rewards=torch.tensor([1.0, 1.0]), terminals=torch.tensor([0.0, 1.0]),
        discounts=torch.tensor([0.99, 0.99]), next_observations=torch.tensor([1, 1]),
    )  # fmt: skip
    network = KnownNetwork()
    targets = loss.target_quantiles(network, network, batch)
    assert targets.shape == (2, 64)
    fractions = torch.Generator().manual_seed(0)  # the loss's draws, drawn again
    drawn = torch.rand((2, 64), generator=fractions)
    tau, alpha = 0.03, 0.9

    def log_pi(q: list[float], a: int) -> float:
        return q[a] / tau - math.log(sum(math.exp(v / tau) for v in q))

    pi_next = [math.exp(log_pi(Q[1], a)) for a in range(2)]
    for i in range(2):
        bonus = alpha * max(-1.0, min(0.0, tau * log_pi(Q[0], int(batch.actions[i]))))
        for j in range(64):
            value = 1.0 + bonus
            if i == 0:  # the second transition is terminal
                z = [Q[1][a] + float(drawn[i, j]) - 0.5 for a in range(2)]
                value += 0.99 * sum(pi_next[a] * (z[a] - tau * log_pi(Q[1], a)) for a in range(2))
            assert float(targets[i, j]) == pytest.approx(value, rel=1e-5, abs=1e-6), (i, j)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"parts.loss.tau": 0.0}, "tau = 0.0 must be > 0"),
        ({"parts.loss.kappa": -1.0}, "kappa = -1.0 must be positive"),
        ({"n_step": 3}, "n_step = 1"),
    ],
)
def test_settings_that_do_not_fit_are_one_line(overrides, message) -> None:
    with pytest.raises(ConfigError, match=message):
        MunchausenIQNLoss(resolve_config("iqn", overrides, env="CartPole-v1", loss=PART))


def test_munchausen_iqn_trains_through_the_head_and_loss_parts() -> None:
    config = resolve_config(
        "iqn", {"parts.loss.online_samples": 8, "parts.loss.target_samples": 8,
                "parts.head.acting_samples": 8},
        env="CartPole-v1", loss=PART, replay_start_steps=100, total_steps=300,
        update_period_steps=2, mlp_hidden_sizes=[32], replay_capacity=1000,
    )  # fmt: skip
    state = TrainingState(config, torch.device("cpu"))
    before = [p.detach().clone() for p in state.agent.online.parameters()]
    for _ in range(300):
        state.advance()
    assert type(state.agent.loss).__name__ == "MunchausenIQNLoss"
    assert state.agent.updates == 100
    loss = state.mean_loss()
    assert loss is not None and math.isfinite(loss)
    after = list(state.agent.online.parameters())
    assert all(not torch.equal(a, b) for a, b in zip(before, after, strict=True))
