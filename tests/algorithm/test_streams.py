"""A replay of several streams (`num_envs` > 1) is N single rings side by side: every
transition it returns is the one a replay holding that environment's steps alone returns,
so no history or n-step window mixes two environments."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.algorithm.samplers import PrioritizedSampler
from dqnlab.algorithm.streams import ReplayStreams
from dqnlab.run.checkpoints import CheckpointStore

SHAPE = (6, 5)
STREAMS = 3


def planted(stream: int, step: int) -> np.ndarray:
    """A frame that names its environment (all pixels) and its step (one pixel)."""
    frame = np.full(SHAPE, 10 * (stream + 1), dtype=np.uint8)
    frame[0, 0] = step % 256
    return frame


def fill(replays: list[ReplayMemory], streamed: ReplayMemory, steps: int, seed: int) -> None:
    """The same random episodes into `streamed` (stream k) and into `replays[k]` alone,
    the streams' steps interleaved as a vector step writes them."""
    rng = np.random.default_rng(seed)
    for step in range(steps):
        for stream, alone in enumerate(replays):
            frame = planted(stream, step)
            if rng.random() < 0.05:
                alone.add_last(frame)
                streamed.add_last(frame, stream)
            else:
                action, reward = int(rng.integers(3)), float(rng.integers(-1, 2))
                terminal = bool(rng.random() < 0.05)
                alone.add(frame, action, reward, terminal)
                streamed.add(frame, action, reward, terminal, stream)


def make(capacity: int, seed: int, streams: int = 1, **options) -> ReplayMemory:
    if options.pop("prioritized", False):  # a sampler of its own for each replay
        options["sampler"] = PrioritizedSampler(importance_exponent=0.4)
    return ReplayMemory(capacity, SHAPE, np.uint8, 4, 16, seed, streams=streams, **options)


OPTIONS = [
    {},
    {"n_step": 3},
    {"compression": "lz4", "chunk_slots": 8},
    {"n_step": 3, "prioritized": True, "compression": "lz4", "chunk_slots": 8},
]


@pytest.mark.parametrize("options", OPTIONS)
@pytest.mark.parametrize("steps", [20, 170])  # filling, and round the rings several times
def test_each_transition_is_the_one_its_environment_alone_would_give(options, steps) -> None:
    segment = 50
    streamed = make(STREAMS * segment + 2, 1, STREAMS, **options)  # 2 slots left unused
    alone = [make(segment, 1, **options) for _ in range(STREAMS)]
    fill(alone, streamed, steps, seed=steps)
    assert streamed.capacity == STREAMS * segment and streamed.size == sum(a.size for a in alone)
    slots = np.arange(streamed.capacity)
    valid = streamed.valid(slots)
    for stream, single in enumerate(alone):
        local = slots[stream * segment : (stream + 1) * segment] - stream * segment
        assert np.array_equal(valid[stream * segment : (stream + 1) * segment], single.valid(local))
    if options.get("prioritized"):  # the non-zero leaves are exactly the valid slots
        assert np.array_equal(streamed.sampler.priorities.tree.leaves > 0, valid)
    for _ in range(5):
        batch = streamed.sample()
        assert batch.indices is not None
        indices = batch.indices.copy()
        observations = np.asarray(batch.observations).copy()
        nexts = np.asarray(batch.next_observations).copy()
        scalars = [getattr(batch, name).copy() for name in ("actions", "rewards", "terminals")]
        discounts = batch.discounts.copy()
        for row, index in enumerate(indices):
            stream, local = divmod(int(index), segment)
            # Only this environment's frames, or the zeros before an episode's start.
            seen = {int(v) for v in np.concatenate([observations[row], nexts[row]])[:, 1, 1]}
            assert seen <= {0, 10 * (stream + 1)}, (index, seen)
            single = alone[stream].gather(np.full(16, local))
            assert np.array_equal(np.asarray(single.observations)[0], observations[row])
            assert np.array_equal(np.asarray(single.next_observations)[0], nexts[row])
            for name, values in zip(("actions", "rewards", "terminals"), scalars, strict=True):
                assert getattr(single, name)[0] == values[row], name
            assert single.discounts[0] == discounts[row]


def test_uniform_draws_cover_every_stream_in_proportion_to_its_stored_slots() -> None:
    streamed = make(3 * 40, 2, STREAMS)
    fill([make(40, 0) for _ in range(STREAMS)], streamed, 30, seed=3)
    drawn = np.concatenate([streamed.sample_indices(64) for _ in range(200)])
    counts = np.bincount(drawn // 40, minlength=3)
    assert counts.min() > 0.25 * len(drawn)


def test_one_stream_draws_the_single_rings_numbers() -> None:
    streams = ReplayStreams(100, 1, 1)
    for _ in range(130):
        streams.advance(0)
    ranks = np.arange(100)
    assert np.array_equal(streams.slots_of(ranks), ranks)
    assert streams.written_since(([30], [0])) is None
    assert streams.written_since(([30], [100])) == (30, 60)


def test_written_ranges_are_one_or_two_per_stream() -> None:
    streams = ReplayStreams(30, 3, 1)  # segments of 10
    for _ in range(8):
        for stream in range(3):
            streams.advance(stream)
    mark = streams.mark()
    for _ in range(4):  # each stream wraps: slots 8, 9, 0, 1 of its segment
        for stream in range(3):
            streams.advance(stream)
    streams.advance(1)  # one more in stream 1
    assert streams.written_since(mark) == [(8, 10), (0, 2), (18, 20), (10, 13), (28, 30), (20, 22)]
    for _ in range(10):
        streams.advance(0)
    assert streams.written_since(mark)[0] == (0, 10)  # stream 0 written all round


def test_bad_stream_counts_are_refused() -> None:
    with pytest.raises(ValueError, match="at least one stream"):
        ReplayStreams(10, 0, 1)
    with pytest.raises(ValueError, match="fewer than the 9"):
        make(3 * 8, 0, STREAMS, n_step=4)  # 8 slots each; a transition needs 4 + 4 + 1


def test_checkpoints_store_each_streams_written_slots_and_resume_exactly(tmp_path: Path) -> None:
    options = {"n_step": 2, "prioritized": True, "compression": "lz4", "chunk_slots": 8}
    original = make(3 * 30, 5, STREAMS, **options)
    singles = [make(30, 0, **options) for _ in range(STREAMS)]
    fill(singles, original, 12, seed=7)
    store = CheckpointStore(tmp_path, chunk_slots=8)
    since_creation = original.written_since(([0] * 3, [0] * 3))
    store.save(1, {"replay": original.state_dict()}, original.arrays, since_creation, "f")
    mark = original.mark()
    fill(singles, original, 25, seed=8)  # wraps every stream
    changed = original.written_since(mark)
    store.save(2, {"replay": original.state_dict()}, original.arrays, changed, "f")
    resumed = make(3 * 30, 99, STREAMS, **options)
    loaded = CheckpointStore(tmp_path, chunk_slots=8).latest("f", into=resumed.arrays)
    assert loaded is not None
    resumed.load_state_dict(loaded.state["replay"])
    for name, array in original.arrays.items():
        mine = resumed.arrays[name]
        if name == "frames":
            array, mine = (
                np.concatenate([a.chunk(i) for i in range(a.chunks)])  # type: ignore[union-attr]
                for a in (array, mine)
            )
        assert np.array_equal(np.asarray(array), np.asarray(mine)), name
    for _ in range(3):
        a, b = original.sample(), resumed.sample()
        assert np.array_equal(a.indices, b.indices)
        assert np.array_equal(np.asarray(a.observations), np.asarray(b.observations))
