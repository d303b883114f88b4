"""Replay memory: frames stored once, histories stacked exactly at episode boundaries."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dqnlab.algorithm.replay import FrameHistory, ReplayMemory, replay_bytes
from dqnlab.algorithm.samplers import PrioritizedSampler
from dqnlab.config import resolve_config
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
    valid = replay.valid(np.arange(10))
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


# n-step returns --------------------------------------------------------------------------


def n_step_memory(
    capacity: int = 40, n_step: int = 3, batch: int = 1, discount: float = 0.5, **options
) -> ReplayMemory:
    return ReplayMemory(
        capacity, (2, 2), np.uint8, 4, batch, seed=0, n_step=n_step, discount=discount, **options
    )


def walked_transition(replay: ReplayMemory, start: int) -> tuple[float, bool, int, int]:
    """(return, terminal, m, next slot) of the transition at `start`, by walking the
    stored steps one at a time."""
    total, k = 0.0, 0
    while True:
        slot = (start + k) % replay.capacity
        total += replay.discount**k * float(replay.rewards[slot])
        k += 1
        next_slot = (start + k) % replay.capacity
        if replay.terminals[slot]:
            return total, True, k, next_slot
        if replay.is_last[next_slot] or k == replay.n_step:
            return total, False, k, next_slot


def walked_history(replay: ReplayMemory, slot: int) -> list[int]:
    """The frame values of the history ending at `slot`, zeros before its episode."""
    frames = [int(replay.frames[slot][0, 0])]
    for _ in range(replay.history_length - 1):
        before = slot - 1
        if (before < 0 and replay.size < replay.capacity) or replay.is_last[before]:
            break
        slot = before % replay.capacity
        frames.insert(0, int(replay.frames[slot][0, 0]))
    return [0] * (replay.history_length - len(frames)) + frames


def assert_walked(replay: ReplayMemory, indices: np.ndarray) -> None:
    """gather(indices) equals the plain walk over the stored steps, transition by transition."""
    batch = replay.gather(indices)
    assert batch.indices is not None and batch.discounts is not None
    assert batch.indices.tolist() == indices.tolist()
    for row, start in enumerate(indices.tolist()):
        total, terminal, steps, next_slot = walked_transition(replay, start)
        assert batch.rewards[row] == pytest.approx(total, rel=1e-6, abs=1e-6)
        assert batch.terminals[row] == float(terminal)
        assert batch.discounts[row] == np.float32(replay.discount**steps)
        assert batch.actions[row] == replay.actions[start]
        assert values(batch.observations[row]) == walked_history(replay, start)
        assert values(batch.next_observations[row]) == walked_history(replay, next_slot)


def test_n_step_windows_by_hand() -> None:
    replay = n_step_memory()
    fill_episode(replay, first=1, length=6, terminal=True)  # slots 0..5 = 1..6, final 7 at 6
    fill_episode(replay, first=11, length=4, terminal=False)  # 7..10 = 11..14, final at 11
    # A life lost (stored as terminal) at 22: the window stops there; the game goes on at 31.
    fill_episode(replay, first=21, length=2, terminal=True)  # 12, 13 = 21, 22, final 23 at 14
    fill_episode(replay, first=31, length=5, terminal=False)  # 15..19 = 31..35, final at 20
    batch = replay.gather(np.array([0]))  # mid-episode: 1 + 2/2 + 3/4, bootstrap from 4
    assert (batch.rewards[0], batch.terminals[0], batch.discounts[0]) == (2.75, 0.0, 0.125)
    assert values(batch.observations[0]) == [0, 0, 0, 1]
    assert values(batch.next_observations[0]) == [1, 2, 3, 4]
    assert batch.window is None
    batch = replay.gather(np.array([4]))  # 5 + 6/2, then the terminal state 7: no bootstrap
    assert (batch.rewards[0], batch.terminals[0], batch.discounts[0]) == (8.0, 1.0, 0.25)
    assert values(batch.next_observations[0]) == [4, 5, 6, 7]
    batch = replay.gather(np.array([9]))  # truncated: 13 + 14/2, bootstrap from 15 with γ^2
    assert (batch.rewards[0], batch.terminals[0], batch.discounts[0]) == (20.0, 0.0, 0.25)
    assert values(batch.next_observations[0]) == [12, 13, 14, 15]
    batch = replay.gather(np.array([12]))  # the life lost at 22 cuts the window: 21 + 22/2
    assert (batch.rewards[0], batch.terminals[0], batch.discounts[0]) == (32.0, 1.0, 0.25)
    batch = replay.gather(np.array([15]))  # the next life starts afresh: 31 + 16 + 8.25
    assert (batch.rewards[0], batch.terminals[0]) == (55.25, 0.0)
    assert values(batch.observations[0]) == [0, 0, 0, 31]
    assert values(batch.next_observations[0]) == [31, 32, 33, 34]
    for start in np.flatnonzero(replay.valid(np.arange(replay.capacity))):
        assert_walked(replay, np.array([start]))


def test_n_step_windows_near_the_write_head_wait_for_their_last_slot() -> None:
    replay = n_step_memory(batch=32)
    for value in range(1, 11):  # one episode going on: slots 0..9
        replay.add(frame(value), action=0, reward=1.0, terminal=False)
    assert np.flatnonzero(replay.valid(np.arange(40))).tolist() == list(range(7))
    assert max(np.concatenate([replay.sample_indices(32) for _ in range(30)])) == 6
    replay.add_last(frame(11))  # truncated at slot 10: the windows ending there are complete
    assert np.flatnonzero(replay.valid(np.arange(40))).tolist() == list(range(10))
    assert replay.gather(np.arange(32) % 10).discounts[7:10].tolist() == [0.125, 0.25, 0.5]


def test_n_step_windows_across_the_ring_end() -> None:
    replay = n_step_memory(capacity=10)
    for value in range(1, 16):  # one long episode: slots hold 11..15, 6..10; newest slot 4
        replay.add(frame(value), action=value % 3, reward=float(value), terminal=False)
    # Full histories (age >= 3) and windows ending at or before the newest slot.
    assert np.flatnonzero(replay.valid(np.arange(10))).tolist() == [0, 1, 8, 9]
    batch = replay.gather(np.array([9]))  # 10 + 11/2 + 12/4, next state 13 at slot 2
    assert batch.rewards[0] == 18.5 and batch.discounts[0] == 0.125
    assert values(batch.observations[0]) == [7, 8, 9, 10]
    assert values(batch.next_observations[0]) == [10, 11, 12, 13]


@pytest.mark.parametrize("n_step", [2, 3, 5])
def test_n_step_batches_equal_a_walk_over_the_stored_steps(n_step: int) -> None:
    """Random episodes (terminal, truncated, long and short) round a 29-slot ring five
    times: every valid transition equals the plain walk."""
    replay = n_step_memory(capacity=29, n_step=n_step, batch=8, discount=0.9)
    rng = np.random.default_rng(n_step)
    for step in range(150):
        if rng.random() < 0.12:
            if rng.random() < 0.5:
                replay.terminals[(replay.position - 1) % 29] = True
            replay.add_last(frame(step % 250 + 1))
        else:
            reward = float(np.float32(rng.uniform(-1, 1)))
            replay.add(frame(step % 250 + 1), int(rng.integers(4)), reward, False)
        valid = np.flatnonzero(replay.valid(np.arange(29)))
        for begin in range(0, len(valid), 8):
            assert_walked(replay, np.resize(valid[begin : begin + 8], 8))


def test_one_step_is_todays_replay_whatever_the_new_arguments() -> None:
    """n_step = 1: the same random draws, windows and bytes as a replay built without the
    new arguments; γ in `discounts`, no importance weights."""
    today = memory(capacity=30, batch=8)
    explicit = ReplayMemory(30, (2, 2), np.uint8, 4, 8, seed=0, n_step=1, discount=0.9)
    for replay in (today, explicit):
        fill_episode(replay, first=1, length=12)
        fill_episode(replay, first=40, length=25, terminal=False)
    for _ in range(20):
        a, b = today.sample(), explicit.sample()
        assert a.window is not None and b.window is not None
        assert a.window.tobytes() == b.window.tobytes()
        assert np.array_equal(a.indices, b.indices)
        for name in ("actions", "rewards", "terminals"):
            assert np.array_equal(getattr(a, name), getattr(b, name))
        assert b.discounts.tolist() == [np.float32(0.9)] * 8 and b.weights is None


# The validity invariant ---------------------------------------------------------------


def written_valid(replay: ReplayMemory, written_at: list[int]) -> np.ndarray:
    """Which slots can start a transition, from when each slot was written (-1: never):
    its history's slots still hold the writes just before its own (before the ring is
    full, a history reaching back before the first write is zeros), and its n-step window
    is stored (each next slot written right after the one before)."""
    capacity, valid = replay.capacity, np.zeros(replay.capacity, dtype=bool)
    filling = replay.size < capacity
    for slot in range(capacity):
        time = written_at[slot]
        if time < 0 or replay.is_last[slot]:
            continue
        history = [((slot - k) % capacity, time - k) for k in range(1, replay.history_length)]
        if any(written_at[s] != t and not (t < 0 and filling) for s, t in history):
            continue  # overwritten by newer data
        for k in range(replay.n_step):
            next_slot = (slot + k + 1) % capacity
            if written_at[next_slot] != time + k + 1:
                break  # not stored yet
            if replay.terminals[(slot + k) % capacity] or replay.is_last[next_slot]:
                valid[slot] = True
                break
        else:
            valid[slot] = True
    return valid


@pytest.mark.parametrize("n_step", [1, 3])
@pytest.mark.parametrize("sampling", ["uniform", "prioritized"])
@pytest.mark.parametrize("storage", ["host", "lz4", "device"])
def test_valid_slots_and_nonzero_priorities_are_the_same_after_every_write(
    n_step: int, sampling: str, storage: str
) -> None:
    """Random episodes round a 23-slot ring thirteen times; after every write the valid
    slots equal those worked out from the write times and, with priorities, are exactly
    the non-zero leaves; draws come from them alone."""
    options = {
        "host": {},
        "lz4": {"compression": "lz4", "chunk_slots": 8},
        "device": {"device": torch.device("cpu")},
    }[storage]
    replay = ReplayMemory(
        23,
        (2, 2),
        np.uint8,
        4,
        8,
        seed=0,
        n_step=n_step,
        **options,
        sampler=PrioritizedSampler(importance_exponent=0.5) if sampling == "prioritized" else None,
    )
    rng = np.random.default_rng(5)
    written_at = [-1] * 23
    for step in range(300):
        written_at[replay.position] = step
        if rng.random() < 0.15:
            replay.add_last(frame(step % 250))
        else:
            replay.add(frame(step % 250), 0, float(rng.random()), bool(rng.random() < 0.1))
        expected = written_valid(replay, written_at)
        assert replay.valid(np.arange(23)).tolist() == expected.tolist(), step
        if sampling == "prioritized":
            leaves = replay.sampler.priorities.tree.leaves
            assert (leaves > 0).tolist() == expected.tolist(), step
        if step % 7 == 0 and expected.any():
            batch = replay.sample()
            assert batch.indices is not None and expected[batch.indices].all()
            replay.sampler.tell(batch, rng.exponential(size=8))


# Prioritized sampling -----------------------------------------------------------------


def prioritized_sampler(beta: float = 0.5) -> PrioritizedSampler:
    return PrioritizedSampler(
        priority_exponent=0.5, priority_epsilon=0.25, importance_exponent=beta
    )


def prioritized_memory(n_step: int = 1, beta: float = 0.5, **options) -> ReplayMemory:
    replay = ReplayMemory(
        50, (2, 2), np.uint8, 4, 32, seed=1, n_step=n_step, discount=0.9,
        sampler=prioritized_sampler(beta), **options,
    )  # fmt: skip
    rng = np.random.default_rng(2)
    for step in range(80):  # round the ring once and a half, episodes of 9
        if step % 9 == 8:
            replay.add_last(frame(step))
        else:
            replay.add(frame(step), step % 3, float(rng.uniform(-1, 1)), step % 9 == 7)
    return replay


def test_new_transitions_enter_at_the_largest_priority_seen() -> None:
    replay = prioritized_memory()
    assert replay.sampler.priorities is not None
    leaves = replay.sampler.priorities.tree.leaves
    valid = replay.valid(np.arange(50))
    assert leaves[valid].tolist() == [1.0] * int(valid.sum())  # p_1 = 1, before any update
    batch = replay.sample()
    assert batch.indices is not None
    indices = batch.indices.copy()
    errors = np.full(32, 0.5)
    errors[-1] = 8.75
    replay.sampler.update(indices, errors)
    assert leaves[indices[-1]] == 3.0  # (8.75 + 0.25)^0.5
    others = indices[indices != indices[-1]]
    assert np.all(leaves[others] == np.sqrt(0.75))
    assert replay.sampler.priorities.max_priority == 9.0
    replay.add(frame(200), 0, 0.0, False)
    replay.add(frame(201), 0, 0.0, False)  # completes the window of the slot before
    assert leaves[(replay.position - 2) % 50] == 3.0  # 9^0.5


def test_priority_updates_skip_stale_and_invalid_slots_and_take_tensors() -> None:
    replay = prioritized_memory()
    assert replay.sampler.priorities is not None
    leaves = replay.sampler.priorities.tree.leaves
    batch = replay.sample()
    assert batch.indices is not None
    indices = batch.indices.copy()
    final = int(np.flatnonzero(replay.is_last)[0])  # never valid: a priority must not stick
    replay.sampler.update(np.array([final]), np.array([3.0]))
    assert leaves[final] == 0.0
    # 30 slots written since the draw: some of the drawn ones now hold new transitions,
    # valid again at the largest priority, which the errors of the old ones must not touch.
    written = {(replay.position + k) % 50 for k in range(30)}
    for value in range(30):
        replay.add(frame(value), 0, 0.0, False)
    before = leaves.copy()
    assert any(before[i] > 0 for i in indices if i in written)
    replay.sampler.update(indices, torch.full((32,), 1.75))  # a tensor, as a loss gives
    changed = np.flatnonzero(leaves != before)
    expected = {int(i) for i in indices if i not in written and before[i] > 0.0}
    assert expected and set(changed.tolist()) == expected
    assert np.all(leaves[changed] == np.sqrt(2.0))
    with pytest.raises(ValueError, match="3 errors for 2 indices"):
        replay.sampler.update(np.array([0, 1]), np.ones(3))


def test_weights_are_the_batch_normalised_importance_weights_of_the_drawn_slots() -> None:
    replay = prioritized_memory(beta=0.4)
    assert replay.sampler.priorities is not None
    rng = np.random.default_rng(3)
    for _ in range(5):
        batch = replay.sample()
        assert batch.indices is not None
        replay.sampler.update(batch.indices, rng.exponential(size=32))
    batch = replay.sample()
    assert batch.indices is not None and batch.weights is not None
    tree = replay.sampler.priorities.tree
    probabilities = tree.leaves[batch.indices] / tree.total
    weights = (replay.size * probabilities) ** -0.4
    np.testing.assert_allclose(batch.weights, weights / weights.max(), rtol=1e-6)
    assert batch.weights.dtype == np.float32 and batch.weights.max() == 1.0


def test_beta_follows_the_runs_schedule_by_the_step_the_sampler_is_asked_at() -> None:
    config = resolve_config(
        "prioritized", env="pong", importance_exponent_start=0.4, replay_start_steps=100,
        total_steps=300, priority_exponent=0.5, priority_epsilon=0.25,
    )  # fmt: skip
    replay = prioritized_memory()
    replay.sampler = PrioritizedSampler(config)  # the same tree, the run's schedule of beta
    replay.sampler.bind(replay)
    for index in range(50):
        replay.sampler.written(index)
    tree = replay.sampler.priorities.tree
    for step, beta in ((100, 0.4), (200, 0.7), (300, 1.0), (900, 1.0)):
        batch = replay.sample(step)
        assert batch.indices is not None and batch.weights is not None
        weights = (replay.size * tree.leaves[batch.indices] / tree.total) ** -beta
        np.testing.assert_allclose(batch.weights, weights / weights.max(), rtol=1e-6)


def test_prioritized_draws_follow_the_priorities_of_valid_slots_chi_square() -> None:
    from scipy.stats import chisquare

    replay = prioritized_memory(n_step=3)
    assert replay.sampler.priorities is not None
    rng = np.random.default_rng(4)
    valid = replay.valid(np.arange(50))
    replay.sampler.update(np.flatnonzero(valid), rng.exponential(size=int(valid.sum())))
    counts = np.zeros(50, dtype=np.int64)
    for _ in range(2000):
        batch = replay.sample()
        assert batch.indices is not None
        counts += np.bincount(batch.indices, minlength=50)
    assert counts[~valid].sum() == 0
    tree = replay.sampler.priorities.tree
    expected = tree.leaves / tree.total * counts.sum()
    assert chisquare(counts[valid], expected[valid]).pvalue > 1e-3


def test_uniform_sampling_has_no_weights_and_ignores_errors() -> None:
    replay = memory(batch=4)
    fill_episode(replay, first=1, length=10)
    batch = replay.sample()
    assert batch.weights is None and not hasattr(replay.sampler, "priorities")
    replay.sampler.tell(batch, np.ones(4))  # nothing to do


@pytest.mark.parametrize("sampling", ["uniform", "prioritized"])
def test_n_step_batches_are_the_same_from_compressed_frames_and_a_device_copy(
    sampling: str,
) -> None:
    host, packed, device = (
        prioritized_memory(n_step=3, **options)
        if sampling == "prioritized"
        else n_step_memory(capacity=50, batch=32, **options)
        for options in (
            {},
            {"compression": "lz4", "chunk_slots": 12},
            {"device": torch.device("cpu")},
        )
    )
    if sampling == "uniform":
        for replay in (host, packed, device):
            for episode in range(9):
                fill_episode(replay, first=10 * episode + 1, length=8, terminal=episode % 2 == 0)
    for _ in range(10):
        expected, *others = (r.sample() for r in (host, packed, device))
        for batch in others:
            assert batch.window is None and expected.window is None
            for name in ("observations", "next_observations"):
                assert np.array_equal(np.asarray(getattr(batch, name)), getattr(expected, name))
            for name in ("indices", "actions", "rewards", "terminals", "discounts", "weights"):
                assert np.array_equal(getattr(batch, name), getattr(expected, name)), name
        for replay in (host, packed, device):
            replay.sampler.tell(expected, np.arange(32) / 8.0)  # uniform: nothing
    assert_walked(host, host.sample().indices.copy())


def test_prioritized_n_step_state_round_trip_through_a_checkpoint(tmp_path) -> None:
    """Saved and loaded by the checkpoint store as a run does (the arrays chunk by chunk,
    the state with torch's weights-only loader): the same next ten minibatches."""
    from dqnlab.run.checkpoints import CheckpointStore

    replay = prioritized_memory(n_step=3)
    rng = np.random.default_rng(7)
    for _ in range(5):
        batch = replay.sample()
        replay.sampler.update(batch.indices, rng.exponential(size=32))
    CheckpointStore(tmp_path).save(1, {"replay": replay.state_dict()}, replay.arrays, None, "f")
    resumed = ReplayMemory(
        50, (2, 2), np.uint8, 4, 32, seed=99, n_step=3, discount=0.9,
        sampler=prioritized_sampler(),
    )  # fmt: skip
    loaded = CheckpointStore(tmp_path).latest("f", into=resumed.arrays)
    assert loaded is not None
    resumed.load_state_dict(loaded.state["replay"])
    assert resumed.sampler.priorities is not None and replay.sampler.priorities is not None
    assert resumed.sampler.priorities.max_priority == replay.sampler.priorities.max_priority
    for step in range(10):
        a, b = replay.sample(), resumed.sample()
        for name in ("indices", "weights", "rewards", "discounts", "observations"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        errors = rng.exponential(size=32)
        for r in (replay, resumed):
            r.sampler.update(a.indices, errors)
            r.add(frame(step), 0, 1.0, False)


def test_a_state_without_priorities_gives_every_valid_slot_the_largest() -> None:
    uniform = memory(capacity=50, batch=32)
    fill_episode(uniform, first=1, length=30)
    replay = ReplayMemory(50, (2, 2), np.uint8, 4, 32, seed=0, sampler=PrioritizedSampler())
    for name, array in uniform.arrays.items():
        replay.arrays[name][...] = array
    replay.load_state_dict(uniform.state_dict())
    assert replay.sampler.priorities is not None
    valid = replay.valid(np.arange(50))
    assert (replay.sampler.priorities.tree.leaves > 0).tolist() == valid.tolist()
