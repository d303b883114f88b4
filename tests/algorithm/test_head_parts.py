"""Heads as parts (`head = module:factory`): what a factory receives, how the network reads
its outputs and Q-values, the shipped head written through the same interface, a run
trained through a user's head, and one-line errors for heads that do not fit."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from torch import nn

from dqnlab.algorithm.heads import QHead, head_q_values, standard_head
from dqnlab.algorithm.networks import QNetwork, build_q_network
from dqnlab.config import Config, resolve_config
from dqnlab.errors import ConfigError
from dqnlab.run.state import TrainingState

HERE = "tests.algorithm.test_head_parts"
RECEIVED: list[tuple[int, int, int | None]] = []


class QuantileHead(nn.Module):
    """Five outputs per action and no `q_values`: the network's Q-values are their mean."""

    def __init__(self, in_features: int, num_actions: int) -> None:
        super().__init__()
        self.num_actions = num_actions
        self.linear = nn.Linear(in_features, num_actions * 5)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.linear(features).unflatten(1, (self.num_actions, 5))


def quantile_head(
    in_features: int, num_actions: int, config: Config, hidden_width: int | None
) -> nn.Module:
    RECEIVED.append((in_features, num_actions, hidden_width))
    assert isinstance(config, Config)
    return QuantileHead(in_features, num_actions)


class MaxHead(QuantileHead):
    """Its own `q_values`: the largest of the five outputs."""

    def q_values(self, outputs: torch.Tensor) -> torch.Tensor:
        return outputs.amax(dim=2)


def max_head(
    in_features: int, num_actions: int, config: Config, hidden_width: int | None
) -> nn.Module:
    return MaxHead(in_features, num_actions)


def flat_head(
    in_features: int, num_actions: int, config: Config, hidden_width: int | None
) -> nn.Module:
    return nn.Linear(in_features, num_actions)  # (batch, actions): no outputs axis


def failing_head(
    in_features: int, num_actions: int, config: Config, hidden_width: int | None
) -> nn.Module:
    raise RuntimeError("no head today")


def not_a_module(
    in_features: int, num_actions: int, config: Config, hidden_width: int | None
) -> object:
    return object()


def small_torso(input_shape: tuple[int, ...]) -> nn.Module:
    return nn.Sequential(nn.Flatten(), nn.Linear(math.prod(input_shape), 6), nn.ReLU())


def _config(**settings: object) -> Config:
    return resolve_config("classic", env="CartPole-v1", **settings)


def test_the_factory_gets_the_torsos_features_the_actions_and_the_hidden_width() -> None:
    RECEIVED.clear()
    config = _config(head=f"{HERE}:quantile_head", mlp_hidden_sizes=[7, 5])
    network = build_q_network(config, (2, 4), 3, is_image=False)
    # The MLP's torso is its hidden layers but the last (7 features); the last (5) is the
    # hidden width the shipped head would put before its outputs.
    assert RECEIVED[-1] == (7, 3, 5)
    assert isinstance(network, QNetwork) and isinstance(network.head, QuantileHead)
    build_q_network(_config(head=f"{HERE}:quantile_head", torso=f"{HERE}:small_torso"),
                    (2, 4), 3, is_image=False)  # fmt: skip
    assert RECEIVED[-1] == (6, 3, None)  # a user's torso: no hidden width


def test_q_values_are_the_mean_of_the_outputs_or_the_heads_own() -> None:
    torch.manual_seed(0)
    inputs = torch.randn(4, 1, 4)
    mean_net = build_q_network(_config(head=f"{HERE}:quantile_head"), (1, 4), 2, False)
    outputs = mean_net.outputs(inputs)
    assert outputs.shape == (4, 2, 5)
    assert torch.equal(mean_net(inputs), outputs.mean(dim=2))
    max_net = build_q_network(_config(head=f"{HERE}:max_head"), (1, 4), 2, False)
    assert torch.equal(max_net(inputs), max_net.outputs(inputs).amax(dim=2))
    one = torch.randn(4, 2, 1)
    assert torch.equal(head_q_values(nn.Identity(), one), one[:, :, 0])


@pytest.mark.parametrize(
    "settings",
    [{}, {"dueling": True}, {"noisy": True}, {"distributional": "c51", "dueling": True}],
)
def test_the_shipped_head_is_a_factory_like_a_users(settings: dict[str, object]) -> None:
    """`standard_head` has a user factory's signature, and through `head = module:factory`
    it builds bit for bit the network `head = "auto"` builds (the settings it reads are
    given to it through the config, as to any factory)."""
    config = _config(torso=f"{HERE}:small_torso", **settings)
    torch.manual_seed(3)
    shipped = build_q_network(config, (1, 4), 2, is_image=False)
    head = standard_head(6, 2, config, None)
    assert isinstance(head, QHead) and isinstance(shipped.head, type(head))
    torch.manual_seed(3)
    torso = small_torso((1, 4))
    through = QNetwork(torso, standard_head(6, 2, config, None))
    for (name, a), (_, b) in zip(
        shipped.state_dict().items(), through.state_dict().items(), strict=True
    ):
        assert torch.equal(a, b), name
    inputs = torch.randn(3, 1, 4)
    assert torch.equal(shipped.eval()(inputs), through.eval()(inputs))


def test_a_run_trains_through_a_users_head() -> None:
    config = _config(
        head=f"{HERE}:quantile_head", replay_start_steps=100, total_steps=300,
        mlp_hidden_sizes=[16],
    )  # fmt: skip
    state = TrainingState(config, torch.device("cpu"))
    before = [p.detach().clone() for p in state.agent.online.head.parameters()]
    for _ in range(300):
        state.advance()
    assert state.agent.updates == 100  # (300 - 100) / update_period_steps 2
    loss = state.mean_loss()
    assert loss is not None and math.isfinite(loss)
    after = list(state.agent.online.head.parameters())
    assert all(not torch.equal(a, b) for a, b in zip(before, after, strict=True))


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"head": f"{HERE}:flat_head"}, r"gives \(2, 2\) .* expected \(2, 2, outputs per action\)"),
        ({"head": f"{HERE}:failing_head"}, "failed to build: RuntimeError"),
        ({"head": f"{HERE}:not_a_module"}, "built object, not nn.Module"),
        ({"head": f"{HERE}:no_such_head"}, "cannot be loaded"),
    ],
)
def test_a_head_that_does_not_fit_is_one_line_naming_the_setting(settings, message) -> None:
    with pytest.raises(ConfigError, match=message) as error:
        build_q_network(_config(**settings), (1, 4), 2, is_image=False)
    assert "head" in str(error.value) and "\n" not in str(error.value)


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"dueling": True}, "your own head, so dueling cannot be added"),
        ({"distributional": "c51"}, "so distributional cannot be added"),
        ({"noisy": True}, "so noisy cannot be added .* list them in its HEAD_OPTIONS"),
        ({"network": f"{HERE}:small_torso"}, "whole Q-network, so head cannot"),
        ({"head": "just_a_name"}, "head = 'just_a_name' is not one of: auto, or module:Name"),
    ],
)
def test_settings_a_users_head_cannot_take_are_refused(settings, message) -> None:
    with pytest.raises(ConfigError, match=message):
        _config(**{"head": f"{HERE}:quantile_head", **settings})


def test_a_users_head_changes_no_other_network() -> None:
    """`head = "auto"` with every other head setting at its default is still the network
    of the `network` setting (the Nature pin's), not a torso and a head."""
    config = _config()
    assert config.head == "auto"
    network = build_q_network(config, (1, 4), 2, is_image=False)
    assert not isinstance(network, QNetwork)
    custom = build_q_network(
        dataclasses.replace(config, head=f"{HERE}:quantile_head"), (1, 4), 2, False
    )
    assert isinstance(custom, QNetwork)
