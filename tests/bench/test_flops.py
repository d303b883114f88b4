"""The update's FLOPs as `FlopCounterMode` counts them (`flops.update_flops`) against hand
computations (the formula of `flops.py`'s docstring); the matrix multiply's figures (not
their speed)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

from dqnlab.algorithm.agent import Agent, agent_for_input
from dqnlab.algorithm.networks import MLP, NatureCNN
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.bench.flops import measure_matmul, update_flop_figures, update_flops
from dqnlab.config import resolve_config

# The Nature CNN on 4 stacked 84x84 frames, 2 x MACs per input, worked out by hand:
NATURE_LAYERS = {
    "features.0": 2 * (32 * 20 * 20) * (4 * 8 * 8),  # 8x8 stride 4: 84 -> 20
    "features.2": 2 * (64 * 9 * 9) * (32 * 4 * 4),  # 4x4 stride 2: 20 -> 9
    "features.4": 2 * (64 * 7 * 7) * (64 * 3 * 3),  # 3x3 stride 1: 9 -> 7
    "head.0": 2 * (64 * 7 * 7) * 512,
    "head.2": 2 * 512 * 4,  # 4 actions (Breakout)
}
NATURE_FORWARD = 18_690_048  # their sum: about 18.7 MFLOP per input


def _forward_flops(network: torch.nn.Module, inputs: torch.Tensor) -> FlopCounterMode:
    with FlopCounterMode(display=False) as counter:
        network(inputs)
    return counter


def _agent(preset: str, overrides: dict[str, object], actions: int) -> Agent:
    config = resolve_config(preset, overrides, replay_capacity=200)
    names = [str(action) for action in range(actions)]
    return agent_for_input(
        config, (4, 84, 84), np.dtype(np.uint8), names, torch.device("cpu"), 0
    )  # fmt: skip


def _replay() -> ReplayMemory:
    replay = ReplayMemory(200, (84, 84), np.uint8, 4, 32, 0)
    frames = np.random.default_rng(0).integers(0, 256, size=(100, 84, 84), dtype=np.uint8)
    for i, frame in enumerate(frames):
        replay.add(frame, i % 4, 1.0, False)
    return replay


def test_the_nature_cnn_counted_layer_by_layer() -> None:
    counter = _forward_flops(
        NatureCNN((4, 84, 84), 4), torch.zeros((1, 4, 84, 84), dtype=torch.uint8)
    )
    counts = counter.get_flop_counts()
    assert {name: sum(counts[f"NatureCNN.{name}"].values()) for name in NATURE_LAYERS} == (
        NATURE_LAYERS
    )
    assert counter.get_total_flops() == NATURE_FORWARD


def test_a_small_mlp_counted_by_hand() -> None:
    network = MLP((2, 3), 2, (8, 8))  # 6 inputs (history 2 x 3) -> 8 -> 8 -> 2 actions
    counter = _forward_flops(network, torch.zeros((5, 2, 3)))
    assert counter.get_total_flops() == 5 * (2 * 6 * 8 + 2 * 8 * 8 + 2 * 8 * 2)


@pytest.mark.parametrize(
    ("target", "forwards"),
    [("max", 2), ("double", 3)],  # the double target's online forward on the next states
)
def test_the_nature_update_is_the_formulas(target: str, forwards: int) -> None:
    """Per minibatch of 32: the forwards, weight gradients (F) and input gradients (F less
    the first layer's, whose input needs none): 2.18 GFLOP, 2.78 with the double target."""
    agent = _agent("nature", {"target": target}, 4)
    first = NATURE_LAYERS["features.0"]
    expected = 32 * ((forwards + 2) * NATURE_FORWARD - first)
    assert update_flops(agent, _replay().sample()) == expected
    assert expected == {"max": 2_182_610_944, "double": 2_780_692_480}[target]


def test_dueling_and_noisy_heads_keep_the_formula() -> None:
    """Rainbow's head without C51: the same passes, the network's own F."""
    agent = _agent("nature", {"target": "double", "dueling": True, "noisy": True}, 4)
    agent.online.train()
    forward = _forward_flops(agent.online, torch.zeros((1, 4, 84, 84), dtype=torch.uint8))
    first = NATURE_LAYERS["features.0"]
    expected = 32 * (5 * forward.get_total_flops() - first)
    assert update_flops(agent, _replay().sample()) == expected


def test_c51_adds_its_projection() -> None:
    agent = _agent("c51", {}, 4)
    agent.online.train()
    forward = _forward_flops(agent.online, torch.zeros((1, 4, 84, 84), dtype=torch.uint8))
    first = NATURE_LAYERS["features.0"]
    networks = 32 * (4 * forward.get_total_flops() - first)
    # The projection: one (51 x 51) by (51 x 1) product per transition.
    assert update_flops(agent, _replay().sample()) - networks == 32 * 2 * 51 * 51


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


def test_a_target_copied_after_every_update_is_counted_as_training_sees_it() -> None:
    """drq_epsilon's schedule (the target copied after every update): the online network
    stands in for the copy, so the double target costs no more than the max target."""
    agent = _agent("nature", {"target": "double", "target_update_steps": 1}, 4)
    assert update_flops(agent, _replay().sample()) == 2_182_610_944  # B (4 F - F_first)
