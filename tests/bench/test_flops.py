"""The FLOP count of the networks and of the update against hand computations and against
PyTorch's own count of what `Agent.update` runs; the matrix multiply's figures (not their
speed)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

from dqnlab.algorithm.agent import agent_for_input
from dqnlab.algorithm.networks import MLP, NatureCNN
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.bench.flops import (
    agent_network_flops,
    count_network_flops,
    measure_matmul,
    update_flop_figures,
)
from dqnlab.config import resolve_config

# The Nature CNN on 4 stacked 84x84 frames, 2 x MACs per input, worked out by hand:
NATURE_LAYERS = {
    "features.0": 2 * (32 * 20 * 20) * (4 * 8 * 8),  # 8x8 stride 4: 84 -> 20
    "features.2": 2 * (64 * 9 * 9) * (32 * 4 * 4),  # 4x4 stride 2: 20 -> 9
    "features.4": 2 * (64 * 7 * 7) * (64 * 3 * 3),  # 3x3 stride 1: 9 -> 7
    "head.0": 2 * (64 * 7 * 7) * 512,
    "head.2": 2 * 512 * 4,  # 4 actions (Breakout)
}


def test_the_nature_cnn_counted_layer_by_layer() -> None:
    flops = count_network_flops(NatureCNN((4, 84, 84), 4), (4, 84, 84), torch.uint8)
    assert {layer.name: layer.forward for layer in flops.layers} == NATURE_LAYERS
    assert flops.forward == 18_690_048  # about 18.7 MFLOP per input
    # Every layer learns; the first takes the observations, which need no gradient.
    assert all(layer.weight_gradient for layer in flops.layers)
    assert [layer.input_gradient for layer in flops.layers] == [False, True, True, True, True]
    first = NATURE_LAYERS["features.0"]
    # Per minibatch of 32: target forward + online forward + weight gradients (3 F) and
    # input gradients (F - first); the double target adds an online forward.
    assert flops.update(32, "max") == 32 * (4 * 18_690_048 - first) == 2_182_610_944
    assert flops.update(32, "double") == 32 * (5 * 18_690_048 - first) == 2_780_692_480
    assert flops.not_counted == ()


def test_a_small_mlp_counted_by_hand() -> None:
    network = MLP((2, 3), 2, (8, 8))  # 6 inputs (history 2 x 3) -> 8 -> 8 -> 2 actions
    training = network.training
    network.eval()
    flops = count_network_flops(network, (2, 3), torch.float32)
    assert [layer.forward for layer in flops.layers] == [2 * 6 * 8, 2 * 8 * 8, 2 * 8 * 2]
    assert flops.forward == 256
    assert flops.backward == 2 * 256 - 2 * 6 * 8
    assert flops.update(5) == 5 * (4 * 256 - 96)
    assert not network.training and training  # its mode is put back


@pytest.mark.parametrize(
    "overrides",
    [
        {},  # nature
        {"target": "double"},
        {"target": "double", "dueling": True, "noisy": True},  # Rainbow's head without C51
    ],
)
def test_the_count_is_what_the_update_computes(overrides: dict[str, object]) -> None:
    config = resolve_config("nature", overrides, replay_capacity=200)
    agent = agent_for_input(
        config, (4, 84, 84), np.dtype(np.uint8), ["a", "b", "c", "d"], torch.device("cpu"), 0
    )
    replay = ReplayMemory(200, (84, 84), np.uint8, 4, 32, 0)
    frames = np.random.default_rng(0).integers(0, 256, size=(100, 84, 84), dtype=np.uint8)
    for i, frame in enumerate(frames):
        replay.add(frame, i % 4, 1.0, False)
    with FlopCounterMode(display=False) as counter:
        agent.update(replay.sample())
    counted = agent_network_flops(agent).update(32, config.target)
    assert counted == counter.get_total_flops()


def test_c51_leaves_out_only_its_projection() -> None:
    config = resolve_config("c51", replay_capacity=200)
    agent = agent_for_input(
        config, (4, 84, 84), np.dtype(np.uint8), ["a", "b"], torch.device("cpu"), 0
    )
    replay = ReplayMemory(200, (84, 84), np.uint8, 4, 32, 0)
    for i in range(100):
        replay.add(np.full((84, 84), i, np.uint8), i % 2, 1.0, False)
    with FlopCounterMode(display=False) as counter:
        agent.update(replay.sample())
    counted = agent_network_flops(agent).update(32, config.target)
    # The projection: one (51 x 51) by (51 x 1) product per transition.
    assert counter.get_total_flops() - counted == 32 * 2 * 51 * 51


def test_the_matmul_and_the_update_figures() -> None:
    matmul = measure_matmul(torch.device("cpu"), size=128, repeats=3)
    assert matmul.size == 128 and matmul.threads == torch.get_num_threads()
    assert matmul.best_gflop_per_s >= matmul.median_gflop_per_s > 0
    figures = update_flop_figures("nature_", 2_000_000_000, 20.0, matmul)
    assert figures["nature_update_gflop"] == 2.0
    assert figures["nature_update_gflop_per_s"] == pytest.approx(100.0)
    assert figures["nature_update_fraction_of_matmul"] == pytest.approx(
        100.0 / matmul.median_gflop_per_s
    )
