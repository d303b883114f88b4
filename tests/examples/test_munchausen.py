"""The example variant (examples/munchausen.py): its target against the paper's formula
worked out by hand, and a short training run through the loss part interface."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from torch import nn

from dqnlab.algorithm.losses import Transitions
from dqnlab.config import resolve_config
from dqnlab.errors import ConfigError
from dqnlab.run.state import TrainingState
from examples.munchausen import MunchausenLoss

PART = "examples.munchausen:MunchausenLoss"


class TableQ(nn.Module):
    def __init__(self, table: list[list[float]]) -> None:
        super().__init__()
        self.table = nn.Parameter(torch.tensor(table))

    def forward(self, states: torch.Tensor) -> torch.Tensor:
        return self.table[states.long().view(-1)]


@pytest.mark.parametrize(
    ("overrides", "tau", "alpha", "l0"),
    [({}, 0.03, 0.9, -1.0), ({"parts.loss.tau": 0.1, "parts.loss.l0": -0.5}, 0.1, 0.9, -0.5)],
)
def test_munchausen_target_by_hand(overrides, tau, alpha, l0) -> None:
    config = resolve_config("classic", overrides, env="CartPole-v1", loss=PART)
    assert config.parts == {"loss": {"tau": tau, "alpha": alpha, "l0": l0}}
    target = TableQ([[0.10, 0.12], [1.0, 1.05]])
    batch = Transitions(
        observations=torch.tensor([0, 0]), actions=torch.tensor([0, 1]),
        rewards=torch.tensor([1.0, 1.0]), terminals=torch.tensor([0.0, 1.0]),
        discounts=torch.tensor([0.99, 0.99]), next_observations=torch.tensor([1, 1]),
    )  # fmt: skip
    y = MunchausenLoss(config).targets(target, target, batch)

    def log_pi(q: list[float], a: int) -> float:  # log softmax(q / tau)[a]
        return q[a] / tau - math.log(sum(math.exp(v / tau) for v in q))

    q_next = [1.0, 1.05]
    pi_next = [math.exp(log_pi(q_next, a)) for a in range(2)]
    soft = sum(pi_next[a] * (q_next[a] - tau * log_pi(q_next, a)) for a in range(2))
    bonus = [alpha * max(l0, min(0.0, tau * log_pi([0.10, 0.12], a))) for a in (0, 1)]
    assert y.tolist() == pytest.approx([1.0 + bonus[0] + 0.99 * soft, 1.0 + bonus[1]], rel=1e-5)
    # The clip: a very unlikely action's bonus stops at alpha * l0.
    far = TableQ([[0.0, 5.0], [0.0, 0.0]])
    y_far = MunchausenLoss(config).targets(
        far, far, dataclasses.replace(batch, terminals=torch.ones(2))
    )
    assert y_far[0].item() == pytest.approx(1.0 + alpha * l0)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"parts.loss.temperature": 0.1}, "has no setting 'temperature' .*tau, alpha, l0"),
        ({"parts.loss.tau": "hot"}, "parts.loss.tau = 'hot' is not a valid float"),
        ({"parts.loss.tau": -1.0}, "tau = -1.0 must be > 0"),
    ],
)
def test_munchausen_settings_that_do_not_fit_are_one_line(overrides, message) -> None:
    with pytest.raises(ConfigError, match=message):
        config = resolve_config("classic", overrides, env="CartPole-v1", loss=PART)
        MunchausenLoss(config)


def test_munchausen_refuses_settings_it_is_not_written_for() -> None:
    with pytest.raises(ConfigError, match="n_step = 1"):
        MunchausenLoss(resolve_config("classic", env="CartPole-v1", n_step=3))


def test_munchausen_trains_through_the_loss_part_setting() -> None:
    config = resolve_config(
        "classic", env="CartPole-v1", loss=PART, replay_start_steps=100, total_steps=400,
        mlp_hidden_sizes=[32],
    )  # fmt: skip
    state = TrainingState(config, torch.device("cpu"))
    before = [p.detach().clone() for p in state.agent.online.parameters()]
    for _ in range(400):
        state.advance()
    assert type(state.agent.loss).__name__ == "MunchausenLoss"
    assert state.agent.updates == 150  # (400 - 100) / update_period_steps 2
    loss = state.mean_loss()
    assert loss is not None and math.isfinite(loss)
    changed = [
        not torch.equal(a, b) for a, b in zip(before, state.agent.online.parameters(), strict=True)
    ]
    assert all(changed)
