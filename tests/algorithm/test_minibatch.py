"""The one minibatch type: the replay's draw reaches the loss part whole (its weights and
indices with it), and the tensors a CUDA graph keeps buffers for give the same minibatch
back."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from dqnlab.algorithm.agent import agent_for_input
from dqnlab.algorithm.losses import LossOutput, TDLoss
from dqnlab.algorithm.minibatch import Batch, Minibatch, Transitions
from dqnlab.config import Config, resolve_config


def _transitions(window: bool) -> Transitions:
    frames = torch.arange(2 * 5 * 3, dtype=torch.float32).view(2, 5, 3)
    return Minibatch.from_update_inputs(
        (
            frames if window else frames[:, :4],
            None if window else frames[:, 1:] + 100,
            torch.tensor([0, 1]),
            torch.tensor([1.0, -1.0]),
            torch.tensor([0.0, 1.0]),
            torch.tensor([0.9, 0.81]),
            torch.tensor([0.5, 2.0]),
        ),
        indices=np.array([7, 3]),
    )


def test_a_window_gives_both_states_as_its_views_and_is_the_only_frames_input() -> None:
    batch = _transitions(window=True)
    assert batch.window is not None
    assert torch.equal(batch.observations, batch.window[:, :4])
    assert torch.equal(batch.next_observations, batch.window[:, 1:])
    assert batch.observations.data_ptr() == batch.window.data_ptr()  # views, no copy
    inputs = batch.update_inputs()
    assert inputs[0] is batch.window and inputs[1] is None


def test_update_inputs_and_back_is_the_same_minibatch() -> None:
    for window in (True, False):
        batch = _transitions(window)
        again = Minibatch.from_update_inputs(batch.update_inputs(), batch.indices)
        for name in ("observations", "next_observations", "actions", "rewards", "terminals",
                     "discounts", "weights"):  # fmt: skip
            assert torch.equal(getattr(again, name), getattr(batch, name)), name
        assert again.indices is batch.indices


class _Recording(TDLoss):
    """Nature's loss, keeping the minibatch it was given."""

    def __init__(self, config: Config) -> None:
        super().__init__(config)
        self.seen: list[Transitions] = []

    def __call__(self, online: nn.Module, target: nn.Module, batch: Transitions) -> LossOutput:
        self.seen.append(batch)
        return super().__call__(online, target, batch)


def test_the_loss_part_reads_the_drawn_minibatch_with_its_weights_and_indices() -> None:
    config = resolve_config("prioritized", env="CartPole-v1", network="mlp", batch_size=3)
    agent = agent_for_input(
        config, (1, 4), np.dtype(np.float32), ["left", "right"], torch.device("cpu"), seed=0
    )
    agent.loss = recording = _Recording(config)
    rng = np.random.default_rng(0)
    drawn = Batch(
        observations=rng.random((3, 1, 4), dtype=np.float32),
        actions=np.array([0, 1, 1]),
        rewards=np.array([1.0, 0.0, -1.0], dtype=np.float32),
        terminals=np.array([0.0, 0.0, 1.0], dtype=np.float32),
        discounts=np.full(3, 0.99, dtype=np.float32),
        next_observations=rng.random((3, 1, 4), dtype=np.float32),
        weights=np.array([0.25, 1.0, 0.5], dtype=np.float32),
        indices=np.array([11, 4, 9]),
    )
    agent.update(drawn)
    (seen,) = recording.seen
    assert seen.indices is drawn.indices
    assert seen.weights is not None and np.array_equal(seen.weights.numpy(), drawn.weights)
    assert np.array_equal(seen.discounts.numpy(), drawn.discounts)
    assert np.array_equal(seen.observations.numpy(), drawn.observations)
