"""Held-out transitions (Nature Fig. 2): drawn once, kept whole, measured as the Lua code does."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from torch import nn

from dqnlab.algorithm.heldout import HeldOutSet
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.run.state import TrainingState


def filled_replay(batch_size: int = 8, n_step: int = 1) -> ReplayMemory:
    """Vector observations (3 numbers) in episodes of 7 steps, rewards in {-1, 0, 1}."""
    replay = ReplayMemory(100, (3,), np.float32, 2, batch_size, seed=1, n_step=n_step)
    rng = np.random.default_rng(0)
    for step in range(90):
        replay.add(
            rng.normal(size=3).astype(np.float32),
            int(rng.integers(2)),
            float(rng.integers(-1, 2)),
            terminal=step % 7 == 6,
        )
        if step % 7 == 6:
            replay.add_last(rng.normal(size=3).astype(np.float32))
    return replay


class Linear(nn.Module):
    """Q(s) = W · flatten(s) + b: two actions from a (2, 3) stacked observation."""

    def __init__(self, seed: int) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.layer = nn.Linear(6, 2)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.layer(observations.flatten(1))


def test_the_set_holds_the_replays_transitions_and_leaves_its_minibatches_alone() -> None:
    replay, twin = filled_replay(), filled_replay()
    heldout = HeldOutSet.draw(replay, 21, np.random.default_rng(5))  # 21: not a multiple of 8
    assert heldout is not None and len(heldout) == 21
    indices = twin.sample_indices(21, np.random.default_rng(5))  # the same draw
    assert len(set(indices.tolist())) > 10
    for start in range(0, 21, 8):
        part = indices[start : start + 8]
        batch = twin.gather(np.resize(part, 8))
        count = len(part)
        assert np.array_equal(heldout.windows[start : start + count].numpy(), batch.window[:count])
        assert heldout.actions[start : start + count].tolist() == batch.actions[:count].tolist()
        assert heldout.rewards[start : start + count].tolist() == batch.rewards[:count].tolist()
        terminals = batch.terminals[:count].tolist()
        assert heldout.terminals[start : start + count].tolist() == terminals
    # Drawing with its own generator: the run's next minibatch is the one it would be.
    assert np.array_equal(replay.sample_indices(8), twin.sample_indices(8))


def test_the_set_is_one_step_whatever_the_replays_n_step() -> None:
    """The Lua code's figure is a one-step TD error: with n_step = 3 the set holds the
    one-step windows, rewards and terminals of the transitions drawn."""
    one_step, three_step = filled_replay(), filled_replay(n_step=3)
    heldout = HeldOutSet.draw(three_step, 21, np.random.default_rng(5))
    assert heldout is not None
    indices = three_step.sample_indices(21, np.random.default_rng(5))  # the same draw
    for start in range(0, 21, 8):
        part = indices[start : start + 8]
        batch = one_step.gather(np.resize(part, 8))
        count = len(part)
        assert np.array_equal(heldout.windows[start : start + count].numpy(), batch.window[:count])
        assert heldout.rewards[start : start + count].tolist() == batch.rewards[:count].tolist()
        terminals = batch.terminals[:count].tolist()
        assert heldout.terminals[start : start + count].tolist() == terminals
    assert heldout.rewards.tolist() == three_step.rewards[indices].tolist()


def test_statistics_equal_a_direct_forward_pass_on_the_stored_set() -> None:
    heldout = HeldOutSet.draw(filled_replay(), 50, np.random.default_rng(2))
    assert heldout is not None
    online, target = Linear(0), Linear(1)
    weights = {
        name: (m.layer.weight.detach().numpy(), m.layer.bias.detach().numpy())
        for name, m in (("online", online), ("target", target))
    }

    def q(name: str, observation: np.ndarray) -> np.ndarray:
        weight, bias = weights[name]
        return weight @ observation.reshape(-1) + bias

    max_q, errors, unclipped = [], [], []
    for i in range(len(heldout)):
        window = heldout.windows[i].numpy()
        next_max = q("target", window[1:]).max()
        taken = q("online", window[:2])[int(heldout.actions[i])]
        error = float(heldout.rewards[i]) + 0.9 * (1 - float(heldout.terminals[i])) * next_max
        error -= taken
        max_q.append(next_max)
        errors.append(abs(max(-0.5, min(0.5, error))))
        unclipped.append(abs(error))
    device = torch.device("cpu")
    clipped = heldout.statistics(online, target, 0.9, 0.5, device, batch_size=16)
    assert np.isclose(clipped.max_q, np.mean(max_q), rtol=1e-5)
    assert np.isclose(clipped.td_error, np.mean(errors), rtol=1e-5)
    plain = heldout.statistics(online, target, 0.9, 0.0, device)
    assert np.isclose(plain.td_error, np.mean(unclipped), rtol=1e-5)
    assert plain.td_error > clipped.td_error  # some errors exceed 0.5: the clip matters
    restored = HeldOutSet.from_state_dict(heldout.state_dict())
    assert restored.statistics(online, target, 0.9, 0.5, device, batch_size=16) == clipped


def test_drawn_at_the_first_step_past_replay_start_and_training_unchanged(cartpole) -> None:
    config = dataclasses.replace(
        cartpole, replay_start_steps=60, replay_capacity=500, heldout_transitions=40
    )
    state = TrainingState(config, torch.device("cpu"))
    without = TrainingState(dataclasses.replace(config, heldout_transitions=0), torch.device("cpu"))
    for step in range(1, 121):
        state.advance()
        without.advance()
        assert (state.heldout is not None) == (step > 60)
    assert state.heldout is not None and len(state.heldout) == 40
    assert without.heldout is None and without.heldout_statistics() is None
    for a, b in zip(
        state.agent.online.parameters(), without.agent.online.parameters(), strict=True
    ):
        assert torch.equal(a, b)  # the same minibatches and updates with or without the set
    statistics = state.heldout_statistics()
    assert statistics is not None and np.isfinite(statistics.max_q)
    # Saved with the training state and restored exactly.
    twin = TrainingState(config, torch.device("cpu"))
    twin.load_state_dict(state.state_dict())
    assert twin.heldout is not None and torch.equal(twin.heldout.windows, state.heldout.windows)
    assert twin.heldout_statistics() == statistics
    state.close(), without.close(), twin.close()
