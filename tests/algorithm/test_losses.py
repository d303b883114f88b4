"""The loss parts: TD targets by max and by double, n-step discounts, C51's projection and
cross-entropy, the agent's weighting, reduction and clipping, and a user's own part."""

from __future__ import annotations

import dataclasses
import sys
import types

import numpy as np
import pytest
import torch
from torch import nn

from dqnlab.algorithm.agent import Agent
from dqnlab.algorithm.losses import (
    CategoricalLoss,
    LossOutput,
    TDLoss,
    Transitions,
    build_loss,
    categorical_projection,
    importance_exponent_at,
    project_onto_support,
)
from dqnlab.algorithm.replay import Batch
from dqnlab.config import Config, resolve_config
from dqnlab.errors import ConfigError

NATURE = resolve_config("nature", env="pong")


class TableQ(nn.Module):
    """Q(s, .) = the row of a table for an integer state s: targets worked out by hand."""

    def __init__(self, table: list[list[float]]) -> None:
        super().__init__()
        self.table = nn.Parameter(torch.tensor(table))

    def forward(self, states: torch.Tensor) -> torch.Tensor:
        return self.table[states.long().view(-1)]


def _batch(**values: list) -> Transitions:
    fields = {
        "observations": [0], "actions": [0], "rewards": [0.0], "terminals": [0.0],
        "discounts": [0.9], "next_observations": [1],
    }  # fmt: skip
    fields.update(values)
    return Transitions(
        **{
            k: torch.tensor(v, dtype=torch.int64 if k == "actions" else None)
            for k, v in fields.items()
        }
    )


def test_max_target_takes_the_target_networks_best_value() -> None:
    online = TableQ([[0.0, 0.0], [5.0, 1.0]])
    target = TableQ([[0.0, 0.0], [2.0, 3.0]])
    y = TDLoss(NATURE).targets(online, target, _batch(rewards=[1.0]))
    assert y.tolist() == pytest.approx([1.0 + 0.9 * 3.0])


def test_double_target_values_the_online_networks_choice_with_the_target_network() -> None:
    # The online network prefers action 0 in s' (5 > 1), the target network action 1:
    # y = r + discount Q_target(s', argmax_a Q_online(s', a)) = 1 + 0.9 * 2.
    online = TableQ([[0.0, 0.0], [5.0, 1.0]])
    target = TableQ([[0.0, 0.0], [2.0, 3.0]])
    double = dataclasses.replace(NATURE, target="double")
    y = TDLoss(double).targets(online, target, _batch(rewards=[1.0]))
    assert y.tolist() == pytest.approx([1.0 + 0.9 * 2.0])
    output = TDLoss(double)(online, target, _batch(rewards=[1.0]))
    output.losses.sum().backward()
    # Only Q(s, a) gets a gradient: the row of s = 0, action 0; neither s' row.
    assert online.table.grad[1].abs().sum() == 0 and online.table.grad[0, 0] != 0
    assert target.table.grad is None


def test_n_step_discounts_and_terminals_mask_the_bootstrap() -> None:
    online = target = TableQ([[0.0, 0.0], [2.0, 4.0]])
    batch = _batch(
        observations=[0, 0, 0], actions=[0, 0, 0], rewards=[1.5, 1.5, 1.5],
        terminals=[0.0, 1.0, 0.0], discounts=[0.9**3, 0.9**3, 0.9**2],
        next_observations=[1, 1, 1],
    )  # fmt: skip
    y = TDLoss(NATURE).targets(online, target, batch)
    assert y.tolist() == pytest.approx([1.5 + 0.729 * 4.0, 1.5, 1.5 + 0.81 * 4.0])


# Prioritized replay, and a user's sampler, which may read them whether it asks or not.
@pytest.mark.parametrize("sampling", ["prioritized", "user_samplers:Mine"])
def test_td_priorities_are_the_unclipped_absolute_errors(sampling: str) -> None:
    online = TableQ([[0.5, 0.0], [0.0, 0.0]])
    target = TableQ([[0.0, 0.0], [3.0, 0.0]])
    config = dataclasses.replace(NATURE, replay_sampling=sampling)
    output = TDLoss(config)(online, target, _batch(rewards=[1.0]))
    # TD error = 1 + 0.9 * 3 - 0.5 = 3.2: the Huber loss is clipped, the priority not.
    assert output.priorities is not None
    assert output.priorities.tolist() == pytest.approx([3.2])
    assert output.losses.tolist() == pytest.approx([3.2 - 0.5])


def test_td_loss_gives_no_priorities_to_uniform_replay() -> None:
    """The shipped uniform sampler asks for none: the loss does not compute them."""
    online = TableQ([[0.5, 0.0], [0.0, 0.0]])
    target = TableQ([[0.0, 0.0], [3.0, 0.0]])
    output = TDLoss(NATURE)(online, target, _batch(rewards=[1.0]))
    assert NATURE.replay_sampling == "uniform" and output.priorities is None
    assert output.losses.tolist() == pytest.approx([3.2 - 0.5])


def test_projection_of_dopamines_worked_example() -> None:
    # Dopamine, tf/agents/rainbow/rainbow_agent.py, project_distribution's docstring.
    atoms = torch.tensor([[0.0, 2, 4, 6, 8], [1, 3, 4, 5, 6]])
    weights = torch.tensor([[0.1, 0.6, 0.1, 0.1, 0.1], [0.1, 0.2, 0.5, 0.1, 0.1]])
    projected = project_onto_support(atoms, weights, torch.tensor([4.0, 5, 6, 7, 8]))
    expected = torch.tensor([[0.8, 0.0, 0.1, 0.0, 0.1], [0.8, 0.1, 0.1, 0.0, 0.0]])
    torch.testing.assert_close(projected, expected)


def _algorithm_1(support: np.ndarray, p: np.ndarray, reward: float, bootstrap: float):
    """C51's Algorithm 1 written as a loop, with the fix for an atom landing exactly on a
    support point (l == u: all its mass to that point)."""
    v_min, v_max, n = support[0], support[-1], len(support)
    gap = (v_max - v_min) / (n - 1)
    m = np.zeros(n)
    for j in range(n):
        tz = min(max(reward + bootstrap * support[j], v_min), v_max)
        b = (tz - v_min) / gap
        lower, upper = int(np.floor(b)), int(np.ceil(b))
        lower, upper = min(max(lower, 0), n - 1), min(max(upper, 0), n - 1)
        if lower == upper:
            m[lower] += p[j]
        else:
            m[lower] += p[j] * (upper - b)
            m[upper] += p[j] * (b - lower)
    return m


@pytest.mark.parametrize(
    ("reward", "bootstrap"),
    [
        (0.0, 0.0),
        (0.0, 0.99),
        (1.0, 0.99),
        (0.4, 0.99**3),
        (25.0, 0.99),
        (-30.0, 0.5),
        (0.4, 1.0),
        (-0.4, 0.0),
        (10.0, 0.0),
    ],  # fmt: skip
)
def test_projection_equals_algorithm_1_and_keeps_all_mass(reward, bootstrap) -> None:
    support = torch.linspace(-10.0, 10.0, 51, dtype=torch.float64)
    rng = np.random.default_rng(int(abs(reward) * 10 + bootstrap * 100))
    p = rng.dirichlet(np.ones(51))
    projected = categorical_projection(
        support,
        torch.from_numpy(p)[None],
        torch.tensor([reward], dtype=torch.float64),
        torch.tensor([bootstrap], dtype=torch.float64),
    )[0].numpy()
    np.testing.assert_allclose(projected, _algorithm_1(support.numpy(), p, reward, bootstrap),
                               atol=1e-12)  # fmt: skip
    assert projected.sum() == pytest.approx(1.0, abs=1e-12)
    assert (projected >= 0).all()


class TableDistribution(nn.Module):
    """A distributional network from a table of logits per state: (states, actions, atoms)."""

    def __init__(self, logits: torch.Tensor, support: torch.Tensor) -> None:
        super().__init__()
        self.logits = nn.Parameter(logits)
        self.register_buffer("support", support)

    def log_probabilities(self, states: torch.Tensor) -> torch.Tensor:
        return torch.log_softmax(self.logits[states.long().view(-1)], dim=2)

    def forward(self, states: torch.Tensor) -> torch.Tensor:
        return (self.log_probabilities(states).exp() * self.support).sum(dim=2)


@pytest.mark.parametrize("target_rule", ["max", "double"])
def test_categorical_loss_is_the_cross_entropy_to_the_projected_target(target_rule) -> None:
    torch.manual_seed(0)
    support = torch.linspace(-2.0, 2.0, 5)
    online = TableDistribution(torch.randn(2, 3, 5), support)
    target = TableDistribution(torch.randn(2, 3, 5), support)
    config = dataclasses.replace(
        NATURE, distributional="c51", distributional_atoms=5, distributional_v_min=-2.0,
        distributional_v_max=2.0, target=target_rule,
    )  # fmt: skip
    batch = _batch(actions=[2], rewards=[0.5], discounts=[0.9])
    output = CategoricalLoss(config)(online, target, batch)
    # By hand: the bootstrap action by target (max) or online (double) Q-values in s' = 1.
    chooser = target if target_rule == "max" else online
    action = int(chooser(torch.tensor([1])).argmax())
    p_next = target.log_probabilities(torch.tensor([1]))[0, action].exp().detach().numpy()
    m = _algorithm_1(support.numpy(), p_next, 0.5, 0.9)
    log_p = online.log_probabilities(torch.tensor([0]))[0, 2].detach().numpy()
    assert output.losses.item() == pytest.approx(-(m * log_p).sum(), rel=1e-5)
    assert output.priorities.item() == pytest.approx(output.losses.item())
    if target_rule == "double":
        assert int(online(torch.tensor([1])).argmax()) != int(target(torch.tensor([1])).argmax())


def test_the_categorical_loss_refuses_a_network_without_a_distribution() -> None:
    config = dataclasses.replace(NATURE, distributional="c51")
    net = TableQ([[0.0, 0.0], [0.0, 0.0]])
    with pytest.raises(ConfigError, match="distributional network"):
        CategoricalLoss(config)(net, net, _batch())


def test_importance_exponent_anneals_from_its_start_at_learning_to_one_at_the_end() -> None:
    config = dataclasses.replace(NATURE, replay_start_steps=100, total_steps=1100)
    assert importance_exponent_at(100, config) == pytest.approx(0.4)
    assert importance_exponent_at(600, config) == pytest.approx(0.7)
    assert importance_exponent_at(1100, config) == pytest.approx(1.0)


class Linear1(nn.Module):
    def __init__(self, weights: list[float]) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.tensor(weights))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.reshape(-1, 1).float() * self.w


def _vector_batch(weights: np.ndarray | None = None) -> Batch:
    return Batch(
        observations=np.array([[1.0], [2.0], [1.0]], dtype=np.float32),
        actions=np.array([0, 1, 1]),
        rewards=np.array([0.5, 1.0, -1.0], dtype=np.float32),
        terminals=np.array([0.0, 0.0, 1.0], dtype=np.float32),
        discounts=np.full(3, 0.99, dtype=np.float32),
        next_observations=np.array([[1.0], [2.0], [1.0]], dtype=np.float32),
        weights=weights,
    )


def test_importance_weights_scale_each_transitions_loss_in_the_gradient() -> None:
    config = dataclasses.replace(NATURE, history_length=1, optimizer="adam", td_error_clip=0.0)
    gradients = []
    for weights in (None, np.array([1.0, 0.5, 0.0], dtype=np.float32)):
        agent = Agent(Linear1([1.0, 2.0]), 2, config, torch.device("cpu"), seed=0)
        loss, priorities = agent.update(_vector_batch(weights))
        gradients.append(agent.online.w.grad.clone())
    # Unweighted: w_0 gets -(y0 - q0) s0, w_1 -(y1 - q1) s1 - (y2 - q2) s2. Weighted: the
    # second transition's half, the third's nothing.
    q = np.array([1.0, 4.0, 2.0])
    y = np.array([0.5 + 0.99 * 2.0, 1.0 + 0.99 * 4.0, -1.0])
    errors, states = y - q, np.array([1.0, 2.0, 1.0])
    assert gradients[0].tolist() == pytest.approx(
        [-errors[0] * states[0], -errors[1] * states[1] - errors[2] * states[2]], rel=1e-5
    )
    assert gradients[1].tolist() == pytest.approx(
        [-errors[0] * states[0], -0.5 * errors[1] * states[1]], rel=1e-5
    )


def test_max_gradient_norm_rescales_the_gradient_to_that_norm() -> None:
    config = dataclasses.replace(
        NATURE, history_length=1, optimizer="adam", td_error_clip=0.0, max_gradient_norm=0.5
    )
    agent = Agent(Linear1([1.0, 2.0]), 2, config, torch.device("cpu"), seed=0)
    agent.update(_vector_batch())
    assert agent.online.w.grad.norm().item() == pytest.approx(0.5, rel=1e-5)


class NotCallable:
    def __init__(self, config) -> None:  # noqa: ANN001
        self.config = config


class HalfLoss(TDLoss):
    """A user's part: the TD loss halved, without priorities."""

    def __call__(self, online, target, batch) -> LossOutput:  # noqa: ANN001
        return LossOutput(super().__call__(online, target, batch).losses / 2, None)


def test_a_users_loss_part_is_built_from_its_import_path(monkeypatch) -> None:
    module = types.ModuleType("user_parts")
    module.HalfLoss = HalfLoss  # type: ignore[attr-defined]
    module.NotCallable = NotCallable  # type: ignore[attr-defined]
    module.Broken = int  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "user_parts", module)
    config = dataclasses.replace(NATURE, loss="user_parts:HalfLoss", history_length=1)
    assert isinstance(build_loss(config), HalfLoss)
    agent = Agent(Linear1([1.0, 2.0]), 2, config, torch.device("cpu"), seed=0)
    loss, priorities = agent.update(_vector_batch())
    assert priorities is None and loss.item() > 0
    for path, message in [("user_parts:Missing", "cannot be loaded"),
                          ("no_such_module_x:Loss", "cannot be loaded"),
                          ("user_parts:NotCallable", "not callable"),
                          ("user_parts:Broken", "failed to build")]:  # fmt: skip
        with pytest.raises(ConfigError, match=message) as error:
            build_loss(dataclasses.replace(NATURE, loss=path))
        assert "\n" not in str(error.value) and path in str(error.value)


@pytest.fixture
def prioritized_half_loss(monkeypatch: pytest.MonkeyPatch) -> Config:
    """Prioritized replay with a user's loss part that gives no priorities."""
    module = types.ModuleType("user_parts_2")
    module.HalfLoss = HalfLoss  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "user_parts_2", module)
    return dataclasses.replace(
        NATURE, loss="user_parts_2:HalfLoss", replay_sampling="prioritized", history_length=1
    )


def test_prioritized_replay_refuses_a_loss_part_without_priorities_before_the_run(
    prioritized_half_loss: Config,
) -> None:
    with pytest.raises(ConfigError, match="gives no priorities, which replay_sampling"):
        Agent(Linear1([1.0, 2.0]), 2, prioritized_half_loss, torch.device("cpu"), seed=0,
              input_shape=(1, 1), observation_dtype=np.dtype(np.float32))  # fmt: skip


def test_an_agent_built_without_its_input_shape_refuses_at_the_first_update(
    prioritized_half_loss: Config,
) -> None:
    agent = Agent(Linear1([1.0, 2.0]), 2, prioritized_half_loss, torch.device("cpu"), seed=0)
    with pytest.raises(ConfigError, match="gives no priorities, which replay_sampling") as error:
        agent.update(_vector_batch())
    assert "\n" not in str(error.value)
