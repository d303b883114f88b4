"""QR-DQN and IQN (`algorithm/quantile.py`), shipped through the head, loss, settings and
generator parts: the quantile Huber loss against a loop written from the papers' formulas,
the heads' fractions, embedding and draws, both losses worked out by hand from the
networks' own outputs, the presets' values against a table, short trainings, and the
Dopamine curves a run of them is compared with."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dqnlab.algorithm.agent import agent_for_input
from dqnlab.algorithm.losses import Transitions
from dqnlab.algorithm.quantile import (
    ImplicitQuantileHead,
    ImplicitQuantileLoss,
    QuantileHead,
    QuantileLoss,
    quantile_huber_losses,
)
from dqnlab.analysis.report.reference import reference_agent
from dqnlab.config import resolve_config
from dqnlab.errors import ConfigError
from dqnlab.run.state import TrainingState

QR = {
    "head": "dqnlab.algorithm.quantile:quantile_head",
    "loss": "dqnlab.algorithm.quantile:QuantileLoss",
}
IQN = {
    "head": "dqnlab.algorithm.quantile:implicit_quantile_head",
    "loss": "dqnlab.algorithm.quantile:ImplicitQuantileLoss",
}


def _rho(u: float, tau: float, kappa: float) -> float:
    """The quantile Huber loss of one error (QR-DQN Eq. 9-10): |tau - 1{u<0}| L_kappa(u) / kappa."""
    huber = 0.5 * u * u if abs(u) <= kappa else kappa * (abs(u) - 0.5 * kappa)
    return abs(tau - (1.0 if u < 0 else 0.0)) * huber / kappa


@pytest.mark.parametrize("kappa", [1.0, 0.5])
def test_the_quantile_huber_loss_sums_over_estimates_and_averages_over_targets(kappa) -> None:
    torch.manual_seed(0)
    errors = torch.randn(3, 4, 5) * 2  # (batch, targets j, estimates i)
    fractions = torch.rand(3, 1, 5)
    losses = quantile_huber_losses(errors, fractions, kappa)
    for b in range(3):
        expected = sum(
            sum(_rho(errors[b, j, i].item(), fractions[b, 0, i].item(), kappa) for j in range(4))
            / 4
            for i in range(5)
        )
        assert losses[b].item() == pytest.approx(expected, rel=1e-5)


def _classic(settings: dict, **overrides) -> object:
    return resolve_config(
        "classic", env="CartPole-v1", mlp_hidden_sizes=[16], **settings, **overrides
    )


def _agent(config, seed: int = 0):
    return agent_for_input(
        config, (1, 4), np.dtype(np.float32), ["l", "r"], torch.device("cpu"), seed
    )


def _batch(seed: int = 0) -> Transitions:
    generator = torch.Generator().manual_seed(seed)
    return Transitions(
        observations=torch.randn(4, 1, 4, generator=generator),
        actions=torch.tensor([0, 1, 1, 0]),
        rewards=torch.tensor([1.0, 0.0, -1.0, 0.5]),
        terminals=torch.tensor([0.0, 0.0, 1.0, 0.0]),
        discounts=torch.full((4,), 0.99),
        next_observations=torch.randn(4, 1, 4, generator=generator),
    )


def test_qr_head_has_n_midpoint_fractions_and_acts_on_their_mean() -> None:
    config = _classic(QR, **{"parts": {"head": {"quantiles": 4}}})
    network = _agent(config).online
    head = network.head
    assert isinstance(head, QuantileHead)
    assert head.fractions.tolist() == [0.125, 0.375, 0.625, 0.875]  # (2i + 1) / 2N
    assert "head.fractions" not in network.state_dict()
    inputs = torch.randn(3, 1, 4)
    assert torch.equal(network(inputs), network.outputs(inputs).mean(dim=2))


@pytest.mark.parametrize("target_rule", ["max", "double"])
def test_qr_loss_by_hand_from_the_networks_quantiles(target_rule) -> None:
    config = _classic(
        QR, target=target_rule, parts={"head": {"quantiles": 3}, "loss": {"kappa": 1.0}}
    )
    agent = _agent(config)
    online, target = agent.online, agent.target
    with torch.no_grad():  # a target unlike the online network
        for parameter in target.parameters():
            parameter.add_(0.3 * torch.randn_like(parameter))
    batch = _batch()
    output = QuantileLoss(config)(online, target, batch)
    taus = [1 / 6, 3 / 6, 5 / 6]
    theta = online.outputs(batch.observations).detach()
    next_theta = target.outputs(batch.next_observations).detach()
    chooser = online if target_rule == "double" else target
    for b in range(4):
        a_star = int(chooser(batch.next_observations[b : b + 1]).argmax())
        bootstrap = 0.99 * (1 - batch.terminals[b].item())
        targets = [
            batch.rewards[b].item() + bootstrap * next_theta[b, a_star, j].item() for j in range(3)
        ]
        estimates = theta[b, batch.actions[b]].tolist()
        expected = sum(
            sum(_rho(t - e, taus[i], 1.0) for t in targets) / 3 for i, e in enumerate(estimates)
        )
        assert output.losses[b].item() == pytest.approx(expected, rel=1e-5)
    assert torch.equal(output.priorities, output.losses.detach())
    output.losses.sum().backward()
    assert all(p.grad is not None for p in online.parameters())


def test_iqn_head_embeds_fractions_by_cosines_and_draws_k_of_them() -> None:
    config = _classic(IQN, parts={"head": {"embedding_dim": 3, "acting_samples": 5}})
    agent = _agent(config)
    head = agent.online.head
    assert isinstance(head, ImplicitQuantileHead) and head.generator is not None
    features = torch.randn(2, 4)  # the MLP torso of one hidden layer: the inputs, flattened
    fractions = torch.tensor([[0.1, 0.7], [0.4, 0.9]])
    values = head.quantile_values(features, fractions)
    assert values.shape == (2, 2, 2)  # (batch, actions, samples)
    for b in range(2):
        for s in range(2):
            cosines = torch.tensor(
                [math.cos(math.pi * i * fractions[b, s].item()) for i in (1, 2, 3)]
            )
            embedded = torch.relu(head.embedding(cosines))
            expected = head.outputs(features[b] * embedded)
            torch.testing.assert_close(values[b, :, s], expected)
    state = head.generator.get_state()
    drawn = head(features)
    assert drawn.shape == (2, 2, 5)
    replay = torch.Generator().set_state(state)
    torch.testing.assert_close(
        drawn, head.quantile_values(features, torch.rand((2, 5), generator=replay))
    )


def test_iqn_loss_by_hand_from_the_draws_of_its_generators() -> None:
    parts = {
        "head": {"embedding_dim": 8, "acting_samples": 4},
        "loss": {"online_samples": 3, "target_samples": 2},
    }
    config = _classic(IQN, parts=parts)
    agent = _agent(config)
    online, target, loss = agent.online, agent.target, agent.loss
    assert isinstance(loss, ImplicitQuantileLoss)
    batch = _batch(1)
    loss_state, head_state = loss.generator.get_state(), target.head.generator.get_state()
    output = loss(online, target, batch)
    # Replay the draws: the loss draws the online fractions (4, 3), the target head its K = 4
    # for a*, then the loss the target fractions (4, 2).
    loss_draws, head_draws = (
        torch.Generator().set_state(loss_state),
        torch.Generator().set_state(head_state),
    )
    taus = torch.rand((4, 3), generator=loss_draws)
    acting = torch.rand((4, 4), generator=head_draws)
    taus_prime = torch.rand((4, 2), generator=loss_draws)
    with torch.no_grad():
        estimates = online.head.quantile_values(online.torso(batch.observations), taus)
        next_features = target.torso(batch.next_observations)
        a_star = target.head.quantile_values(next_features, acting).mean(dim=2).argmax(dim=1)
        next_values = target.head.quantile_values(next_features, taus_prime)
    for b in range(4):
        bootstrap = 0.99 * (1 - batch.terminals[b].item())
        targets = [
            batch.rewards[b].item() + bootstrap * next_values[b, a_star[b], j].item()
            for j in range(2)
        ]
        chosen = estimates[b, batch.actions[b]].tolist()
        expected = sum(
            sum(_rho(t - e, taus[b, i].item(), 1.0) for t in targets) / 2
            for i, e in enumerate(chosen)
        )
        assert output.losses[b].item() == pytest.approx(expected, rel=1e-5)


def test_a_quantile_loss_refuses_a_network_without_its_head() -> None:
    config = _classic({})
    agent = _agent(config)
    with pytest.raises(
        ConfigError, match="needs the head of head = 'dqnlab.algorithm.quantile:quantile_head'"
    ):
        QuantileLoss(config)(agent.online, agent.target, _batch())


def test_quantile_settings_are_checked_in_one_line() -> None:
    with pytest.raises(ConfigError, match="parts.loss.kappa = 0.0 must be positive"):
        TrainingState(_classic(QR, parts={"loss": {"kappa": 0.0}}), torch.device("cpu"))
    with pytest.raises(ConfigError, match="parts.head.quantiles = 0 must be at least 1"):
        TrainingState(_classic(QR, parts={"head": {"quantiles": 0}}), torch.device("cpu"))
    with pytest.raises(ConfigError, match="has no setting 'quantiles'"):
        _classic(IQN, parts={"head": {"quantiles": 8}})
    with pytest.raises(ConfigError, match="dueling cannot be added"):
        _classic(IQN, dueling=True)


# The presets' values, written out here from the papers and the references (qrdqn.toml,
# iqn.toml give the sources); every other setting is the c51 preset's, the Nature regime.
QRDQN_VALUES = {
    **QR,
    "optimizer": "adam",
    "learning_rate": 5e-5,
    "adam_epsilon": 0.01 / 32,
    "loss_reduction": "mean",
    "epsilon_end": 0.01,
    "target": "max",
    "n_step": 1,
    "replay_sampling": "uniform",
    "distributional": "none",
    "target_update_steps": 10_000,
    "replay_start_steps": 50_000,
    "epsilon_decay_steps": 1_000_000,
    "dueling": False,
    "parts": {"head": {"quantiles": 200}, "loss": {"kappa": 1.0}},
}
IQN_VALUES = {
    **QRDQN_VALUES,
    **IQN,
    "parts": {
        "head": {"embedding_dim": 64, "acting_samples": 32},
        "loss": {"kappa": 1.0, "online_samples": 64, "target_samples": 64},
    },
}


@pytest.mark.parametrize(("preset", "values"), [("qrdqn", QRDQN_VALUES), ("iqn", IQN_VALUES)])
def test_the_presets_values(preset, values) -> None:
    config = resolve_config(preset, env="pong")
    for name, value in values.items():
        assert getattr(config, name) == value, name
    c51 = resolve_config("c51", env="pong").to_dict()
    ours = config.to_dict()
    differing = {name for name in ours if ours[name] != c51[name]}
    assert differing <= set(values) | {"distributional", "preset"}


SMALL = {  # fewer quantiles and fractions than the defaults: what is tested is the wiring
    "qrdqn": {**QR, "parts": {"head": {"quantiles": 8}}},
    "iqn": {**IQN, "parts": {"loss": {"online_samples": 8, "target_samples": 8}}},
}


@pytest.mark.parametrize("variant", list(SMALL))
def test_a_short_training_through_the_parts(variant) -> None:
    config = _classic(SMALL[variant], replay_start_steps=100, total_steps=200)
    state = TrainingState(config, torch.device("cpu"))
    before = [p.detach().clone() for p in state.agent.online.parameters()]
    for _ in range(200):
        state.advance()
    assert state.agent.updates == 50
    loss = state.mean_loss()
    assert loss is not None and math.isfinite(loss)
    after = list(state.agent.online.parameters())
    assert all(not torch.equal(a, b) for a, b in zip(before, after, strict=True))


def test_runs_of_the_presets_are_compared_with_dopamines_agents() -> None:
    qr = reference_agent(resolve_config("qrdqn", env="pong"))
    assert qr.agent == "quantile" and "one-step returns and uniform replay" in qr.caveat
    regime = resolve_config("qrdqn", env="pong", n_step=3, replay_sampling="prioritized")
    assert reference_agent(regime).agent == "quantile" and reference_agent(regime).caveat is None
    iqn = reference_agent(resolve_config("iqn", env="pong", n_step=3))
    assert iqn.agent == "iqn" and iqn.caveat is None
    double = reference_agent(resolve_config("iqn", env="pong", target="double"))
    assert double.agent is None and "IQN + double Q-learning" in double.why_none


def test_the_qr_head_composes_with_dueling_and_noisy_layers() -> None:
    """`quantile_head` lists dueling and noisy in its HEAD_OPTIONS and builds them."""
    head = _agent(_classic(QR, dueling=True, noisy=True)).online.head
    assert isinstance(head, QuantileHead) and head.dueling and head.noisy
