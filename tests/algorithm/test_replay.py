"""Replay memory: frames stored once, histories stacked exactly at episode boundaries."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dqnlab.algorithm.replay import FrameHistory, ReplayMemory, replay_bytes
from dqnlab.errors import ResourceError


def frame(value: int) -> np.ndarray:
    """A 2x2 frame whose pixels all equal `value`, so a stacked history reads as numbers."""
    return np.full((2, 2), value, dtype=np.uint8)


def values(stack: np.ndarray) -> list[int]:
    """The frame values of one stacked (history, 2, 2) input."""
    return [int(f[0, 0]) for f in stack]


def memory(capacity: int = 20, history: int = 4, batch: int = 1) -> ReplayMemory:
    return ReplayMemory(capacity, (2, 2), np.uint8, history, batch, seed=0)


def fill_episode(replay: ReplayMemory, first: int, length: int, terminal: bool = True) -> None:
    """Observations first..first+length-1 with actions, then the final observation."""
    for t in range(length):
        replay.add(frame(first + t), action=t % 3, reward=float(first + t), terminal=False)
    # The last transition's flag says whether the final observation is terminal.
    replay.terminals[(replay.position - 1) % replay.capacity] = terminal
    replay.add_last(frame(first + length))


def test_history_has_zeros_before_episode_start_and_never_mixes_episodes() -> None:
    replay = memory()
    fill_episode(replay, first=1, length=3)  # slots 0,1,2 = 1,2,3 and slot 3 = final 4
    fill_episode(replay, first=11, length=5)  # slots 4..8 = 11..15 and slot 9 = final 16
    # Transition from slot 5 (obs 12): history [0, 0, 11, 12], next [0, 11, 12, 13].
    batch = replay.gather(np.array([5]))
    assert values(batch.observations[0]) == [0, 0, 11, 12]
    assert values(batch.next_observations[0]) == [0, 11, 12, 13]
    # First transition of the second episode: only its own first frame.
    batch = replay.gather(np.array([4]))
    assert values(batch.observations[0]) == [0, 0, 0, 11]
    assert values(batch.next_observations[0]) == [0, 0, 11, 12]
    # Slot 0 of a fresh memory: nothing before it.
    batch = replay.gather(np.array([0]))
    assert values(batch.observations[0]) == [0, 0, 0, 1]
    # Deep in an episode: four real frames.
    batch = replay.gather(np.array([8]))
    assert values(batch.observations[0]) == [12, 13, 14, 15]
    assert values(batch.next_observations[0]) == [13, 14, 15, 16]
    assert batch.terminals[0] == 1.0
    assert batch.actions[0] == 4 % 3 and batch.rewards[0] == 15.0


def test_terminal_and_truncated_episode_ends() -> None:
    replay = memory()
    fill_episode(replay, first=1, length=2, terminal=True)
    fill_episode(replay, first=21, length=2, terminal=False)  # truncated: bootstrap
    terminal = replay.gather(np.array([1]))
    assert terminal.terminals[0] == 1.0
    assert values(terminal.next_observations[0]) == [0, 1, 2, 3]
    truncated = replay.gather(np.array([4]))
    assert truncated.terminals[0] == 0.0
    assert values(truncated.next_observations[0]) == [0, 21, 22, 23]


def test_sampling_never_starts_at_a_final_observation_or_the_newest_slot() -> None:
    replay = memory(capacity=50, batch=32)
    fill_episode(replay, first=1, length=5)
    fill_episode(replay, first=101, length=5)
    replay.add(frame(200), action=1, reward=0.0, terminal=False)  # o_{t+1} not stored yet
    starts = set()
    for _ in range(50):
        starts.update(int(i) for i in replay.sample_indices(32))
    assert starts == {0, 1, 2, 3, 4, 6, 7, 8, 9, 10}  # not 5, 11 (final) nor 12 (newest)


def test_sampling_is_uniform_with_replacement() -> None:
    replay = memory(capacity=50, batch=32)
    fill_episode(replay, first=1, length=10)
    counts = np.bincount(
        np.concatenate([replay.sample_indices(32) for _ in range(1000)]), minlength=11
    )
    assert counts[10] == 0  # the final observation
    expected = 32_000 / 10
    assert np.all(np.abs(counts[:10] - expected) < 5 * np.sqrt(expected))  # ~5 sigma
    assert len(np.unique(replay.sample_indices(32))) < 32  # repeats happen with 10 choices


def test_wraparound_overwrites_oldest_and_excludes_histories_into_new_data() -> None:
    replay = memory(capacity=10)
    for value in range(1, 16):  # one long episode: slots hold 11..15, 6..10
        replay.add(frame(value), action=0, reward=0.0, terminal=False)
    assert replay.size == 10 and replay.position == 5
    assert [int(f[0, 0]) for f in replay.frames] == [11, 12, 13, 14, 15, 6, 7, 8, 9, 10]
    valid = replay._valid(np.arange(10))
    # Slot 4 (15) is the newest; slots 5,6,7 (6,7,8) lack their full history; slot 8 (9) has 6,7,8.
    assert valid.tolist() == [True, True, True, True, False, False, False, False, True, True]
    batch = replay.gather(np.array([1]))  # obs 12: history crosses the array end
    assert values(batch.observations[0]) == [9, 10, 11, 12]
    assert values(batch.next_observations[0]) == [10, 11, 12, 13]


def test_episode_boundary_across_the_array_end() -> None:
    replay = memory(capacity=8)
    fill_episode(replay, first=1, length=5)  # slots 0..4, final at 5
    fill_episode(replay, first=31, length=4)  # slots 6,7,0,1 and final 32+... at 2
    batch = replay.gather(np.array([0]))  # obs 33 at slot 0, episode began at slot 6
    assert values(batch.observations[0]) == [0, 31, 32, 33]


def test_vector_observations_and_history_one() -> None:
    replay = ReplayMemory(10, (3,), np.float32, history_length=1, batch_size=2, seed=0)
    for t in range(4):
        replay.add(
            np.array([t, t + 0.5, -t], dtype=np.float32), action=t, reward=1.0, terminal=False
        )
    replay.add_last(np.array([9, 9, 9], dtype=np.float32))
    batch = replay.gather(np.array([1, 3]))
    np.testing.assert_array_equal(batch.observations[:, 0], [[1, 1.5, -1], [3, 3.5, -3]])
    np.testing.assert_array_equal(batch.next_observations[:, 0], [[2, 2.5, -2], [9, 9, 9]])
    assert batch.observations.shape == (2, 1, 3)


def test_memory_budget_for_a_nature_replay() -> None:
    per_transition = replay_bytes(1, (84, 84), np.uint8)
    assert per_transition == 84 * 84 + 10
    assert replay_bytes(1_000_000, (84, 84), np.uint8) / 1e9 == pytest.approx(7.066)
    assert per_transition / (84 * 84) <= 1.03


def test_refuses_a_replay_that_cannot_fit() -> None:
    with pytest.raises(ResourceError, match="GiB"):
        ReplayMemory(10**9, (84, 84), np.uint8, 4, 32, seed=0)  # 7 TB


def test_state_dict_round_trip_continues_identically() -> None:
    a = memory(capacity=30, batch=8)
    fill_episode(a, first=1, length=12)
    b = memory(capacity=30, batch=8)
    for name, array in a.arrays.items():
        b.arrays[name][...] = array
    b.load_state_dict(dict(a.state_dict()))
    assert b.writes == a.writes == 13
    np.testing.assert_array_equal(a.sample_indices(8), b.sample_indices(8))
    np.testing.assert_array_equal(a.sample().observations, b.sample().observations)


def test_frame_history_matches_replay_stacking() -> None:
    replay = memory()
    history = FrameHistory(4, (2, 2), np.dtype(np.uint8))
    history.reset(frame(1))
    stacks = [history.frames.copy()]
    replay.add(frame(1), 0, 0.0, False)
    for value in (2, 3, 4, 5):
        history.push(frame(value))
        stacks.append(history.frames.copy())
        replay.add(frame(value), 0, 0.0, False)
    replay.add_last(frame(6))
    for slot, stack in enumerate(stacks):
        np.testing.assert_array_equal(replay.gather(np.array([slot])).observations[0], stack)
    assert values(stacks[0]) == [0, 0, 0, 1]


def test_sampling_an_empty_or_incomplete_memory_raises() -> None:
    replay = memory(batch=4)
    with pytest.raises(RuntimeError, match="no complete transition"):
        replay.sample()
    replay.add(frame(1), 0, 0.0, False)  # o_{t+1} not stored yet
    with pytest.raises(RuntimeError, match="no complete transition"):
        replay.sample()
    replay.add(frame(2), 0, 0.0, False)
    assert replay.sample_indices(4).tolist() == [0, 0, 0, 0]


@pytest.mark.parametrize("capacity", [40, 1000], ids=["wrapped", "filling"])
def test_frames_kept_on_the_device_sample_the_same_batches(capacity: int) -> None:
    """The device path (here the CPU as the device: the GPU's code, run without one)
    gathers the same transitions as host memory, zeros before episode starts included."""
    rng = np.random.default_rng(7)
    blanked = 0
    host = ReplayMemory(capacity, (3, 2), np.uint8, 4, 16, seed=3)
    device = ReplayMemory(capacity, (3, 2), np.uint8, 4, 16, seed=3, device=torch.device("cpu"))
    for step in range(300):
        observation = rng.integers(0, 256, size=(3, 2), dtype=np.uint8)
        if step % 9 == 8:
            for replay in (host, device):
                replay.add_last(observation)
        else:
            for replay in (host, device):
                replay.add(observation, step % 4, float(step), step % 9 == 7)
        if step > 20 and step % 4 == 0:
            expected, got = host.sample(), device.sample()
            assert isinstance(got.window, torch.Tensor) and isinstance(expected.window, np.ndarray)
            np.testing.assert_array_equal(got.window.numpy(), expected.window)
            np.testing.assert_array_equal(got.observations.numpy(), expected.observations)
            np.testing.assert_array_equal(got.next_observations.numpy(), expected.next_observations)
            np.testing.assert_array_equal(got.actions, expected.actions)
            np.testing.assert_array_equal(got.terminals, expected.terminals)
            blanked += int(np.all(expected.window == 0, axis=(2, 3)).any())
    assert blanked > 0  # windows reaching back across an episode start were compared


def test_upload_copies_frames_loaded_into_the_host_arrays() -> None:
    """A checkpoint loads into the host arrays; upload brings the device copy up to date."""
    source = memory()
    fill_episode(source, 1, 15)
    replay = ReplayMemory(20, (2, 2), np.uint8, 4, 1, seed=0, device=torch.device("cpu"))
    for name, array in replay.arrays.items():
        array[...] = source.arrays[name]
    replay.load_state_dict(source.state_dict())
    replay.upload()
    for _ in range(20):
        expected, got = source.sample(), replay.sample()
        np.testing.assert_array_equal(got.observations.numpy(), expected.observations)
