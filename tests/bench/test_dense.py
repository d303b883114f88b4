"""The dense operations of an update (`bench/dense.py`): the calls recorded on a small
network are exactly its layers' calls, they replay alone, and the hooks go afterwards (not
the speed)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from dqnlab.algorithm.agent import Agent
from dqnlab.algorithm.heads import NoisyLinear
from dqnlab.algorithm.minibatch import Batch
from dqnlab.bench.dense import dense_calls, dense_figures, median_dense_ms
from dqnlab.config import resolve_config


class SmallNetwork(nn.Module):
    """A channels-last convolution, a linear layer and a noisy one on 4 stacked 12x12
    frames: the kinds of layer the Atari networks have."""

    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Conv2d(4, 8, kernel_size=4, stride=2, padding=1)  # 12x12 -> 6x6
        self.conv.to(memory_format=torch.channels_last)
        self.hidden = nn.Linear(8 * 6 * 6, 16)
        self.out = NoisyLinear(16, 3, sigma0=0.5)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        planes = observations.float().div(255.0).contiguous(memory_format=torch.channels_last)
        features = torch.relu(self.conv(planes)).flatten(1)
        return self.out(torch.relu(self.hidden(features)))


def _agent(target: str) -> Agent:
    torch.manual_seed(0)
    config = resolve_config("nature", env="pong", target=target)
    return Agent(SmallNetwork(), 3, config, torch.device("cpu"), seed=0)


def _batch() -> Batch:
    rng = np.random.default_rng(0)
    window = rng.integers(0, 256, size=(8, 5, 12, 12), dtype=np.uint8)
    return Batch(
        observations=window[:, :4],
        actions=rng.integers(0, 3, size=8).astype(np.int64),
        rewards=np.ones(8, np.float32),
        terminals=np.zeros(8, np.float32),
        discounts=np.full(8, 0.99, np.float32),
        next_observations=window[:, 1:],
    )


LAYERS = ("conv", "hidden", "out")


@pytest.mark.parametrize(
    ("target", "passes"),
    [
        ("max", ("online", "target")),  # online on s, target on s'
        ("double", ("online", "target", "online")),  # and the online choice on s'
    ],
)
def test_the_calls_of_an_update_are_its_layers_forwards_and_one_backward(
    target: str, passes: tuple[str, ...]
) -> None:
    agent = _agent(target)
    calls = dense_calls(agent, _batch())
    assert [call.layer for call in calls] == [f"{n}.{layer}" for n in passes for layer in LAYERS]
    # The backward: the online pass on s alone, every layer's input gradient but the first's.
    assert [call.in_backward for call in calls] == [True] * 3 + [False] * 3 * (len(passes) - 1)
    assert [(call.input_grad, call.weight_grad) for call in calls[:3]] == [
        (False, True),
        (True, True),
        (True, True),
    ]
    conv, hidden, out = calls[:3]
    assert conv.kind == "conv2d" and conv.input_shape == (8, 4, 12, 12)
    assert conv.weight_shape == (8, 4, 4, 4) and conv.bias
    assert (conv.stride, conv.padding, conv.dilation, conv.groups) == ((2, 2), (1, 1), (1, 1), 1)
    assert conv.input_channels_last and conv.weight_channels_last
    assert hidden.kind == "linear" and hidden.input_shape == (8, 288)
    assert hidden.weight_shape == (16, 288) and not hidden.input_channels_last
    # The noisy layer: the linear of its composed weight, of mu's shape.
    assert out.kind == "linear" and out.input_shape == (8, 16) and out.weight_shape == (3, 16)
    assert all(call.dtype == torch.float32 for call in calls)
    for network in (agent.online, agent.target):
        assert all(not module._forward_hooks for module in network.modules())


def test_the_calls_replay_alone_and_give_the_figures() -> None:
    agent = _agent("double")
    batch = _batch()
    dense_ms = median_dense_ms(dense_calls(agent, batch), torch.device("cpu"), repeats=3)
    assert math.isfinite(dense_ms) and dense_ms > 0
    figures = dense_figures("small_", agent, batch, update_ms=2.0, repeats=2)
    assert set(figures) == {"small_dense_ms", "small_update_over_dense"}
    assert figures["small_update_over_dense"] == pytest.approx(2.0 / figures["small_dense_ms"])
