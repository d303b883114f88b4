"""The compressed replay returns the raw replay's batches, byte for byte, and round-trips
through checkpoints (in either direction: compressed to raw and raw to compressed)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dqnlab.algorithm import compression
from dqnlab.algorithm.compression import CompressedFrames, PackedChunk, pack, unpack
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.config import resolve_config
from dqnlab.errors import ConfigError, ResourceError
from dqnlab.run.checkpoints import CheckpointStore

SHAPE = (12, 10)


def game_like_frames(count: int, seed: int = 0) -> np.ndarray:
    """Frames that compress as a game's do: a flat background, a few moving blocks."""
    rng = np.random.default_rng(seed)
    frames = np.full((count, *SHAPE), 40, dtype=np.uint8)
    for i in range(count):
        row, column = rng.integers(0, SHAPE[0] - 3), (i * 3) % (SHAPE[1] - 2)
        frames[i, row : row + 3, column : column + 2] = rng.integers(0, 256, (3, 2))
    return frames


def twin_replays(
    capacity: int, chunk_slots: int, seed: int = 1
) -> tuple[ReplayMemory, ReplayMemory]:
    raw = ReplayMemory(capacity, SHAPE, np.uint8, 4, 32, seed)
    packed = ReplayMemory(
        capacity, SHAPE, np.uint8, 4, 32, seed, compression="lz4", chunk_slots=chunk_slots
    )
    return raw, packed


def add_to_both(replays, frames: np.ndarray, rng: np.random.Generator) -> None:
    for i, frame in enumerate(frames):
        if rng.random() < 0.03:  # an episode ends: its last observation, then a new one
            for replay in replays:
                replay.add_last(frame)
        else:
            terminal = bool(rng.random() < 0.02)
            for replay in replays:
                replay.add(frame, i % 3, float(i % 5), terminal)


def assert_same_batch(a, b) -> None:
    assert a.window.tobytes() == b.window.tobytes()
    for name in ("actions", "rewards", "terminals"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_batches_are_bit_identical_to_the_raw_replay_through_wraparound() -> None:
    # 250 slots in chunks of 64 (the last one short, 58 slots, its last block 2 slots);
    # 2,000 writes go round the ring eight times; thousands of sampled transitions.
    raw, packed = twin_replays(250, chunk_slots=64)
    rng = np.random.default_rng(0)
    frames = game_like_frames(2000)
    samples = 0
    for begin in range(0, 2000, 50):
        add_to_both((raw, packed), frames[begin : begin + 50], rng)
        for _ in range(3):
            assert_same_batch(raw.sample(), packed.sample())
            samples += 32
        # Every slot of the ring, including the ones whose histories cross the ring's end,
        # chunk boundaries and episode starts.
        valid = np.flatnonzero(raw.valid(np.arange(raw.size)))
        for begin_index in range(0, len(valid) - 32, 32):
            indices = valid[begin_index : begin_index + 32]
            assert_same_batch(raw.gather(indices), packed.gather(indices))
            samples += 32
    assert samples > 10_000
    assert packed.frames.sealed_slots > 7 * 250  # chunks were compressed and reopened
    assert packed.resident_bytes < raw.resident_bytes


def test_the_sampled_indices_and_random_stream_are_the_raw_replays() -> None:
    raw, packed = twin_replays(300, chunk_slots=32)
    add_to_both((raw, packed), game_like_frames(400), np.random.default_rng(3))
    for _ in range(20):
        assert np.array_equal(raw.sample_indices(32), packed.sample_indices(32))
    assert raw.state_dict() == packed.state_dict()


def test_a_chunk_is_stored_once_full_and_the_written_one_stays_raw() -> None:
    frames = CompressedFrames(100, SHAPE, np.uint8, "lz4", chunk_slots=40)
    data = game_like_frames(100)
    for slot in range(39):
        frames.write(slot, data[slot])
    assert frames.sealed_slots == 0
    frames.write(39, data[39])
    assert frames.sealed_slots == 40  # chunk 0, compressed when its last slot was written
    out = np.empty((3, *SHAPE), np.uint8)
    frames.gather(np.array([0, 39, 41], dtype=np.int64), out)
    assert np.array_equal(out[:2], data[[0, 39]]) and not out[2].any()  # 41: never written
    assert np.array_equal(frames.chunk(0), data[:40])


def test_pack_and_unpack_round_trip_and_the_offsets_are_checked() -> None:
    data = game_like_frames(10)
    packed = pack("lz4", data)
    out = np.empty_like(data)
    unpack("lz4", packed, out)
    assert np.array_equal(out, data)
    stored = memoryview(b"".join(bytes(piece) for piece in packed.pieces()))
    assert PackedChunk.from_bytes(stored, 3).payload.tobytes() == packed.payload.tobytes()
    with pytest.raises(ValueError, match="offsets"):
        PackedChunk.from_bytes(stored, 2)  # the wrong number of blocks


def test_checkpoint_round_trip_writes_compressed_chunks_and_resumes_exactly(
    tmp_path: Path,
) -> None:
    raw, packed = twin_replays(300, chunk_slots=64)
    rng = np.random.default_rng(5)
    add_to_both((raw, packed), game_like_frames(420), rng)
    store = CheckpointStore(tmp_path / "lz4")
    store.save(7, {"replay": packed.state_dict()}, packed.arrays, None, "f")
    raw_store = CheckpointStore(tmp_path / "raw", chunk_slots=64)
    raw_store.save(7, {"replay": raw.state_dict()}, raw.arrays, None, "f")

    def frame_bytes(run: Path) -> int:
        return sum(path.stat().st_size for path in (run / "checkpoints/replay").glob("frames.*"))

    assert frame_bytes(tmp_path / "lz4") * 3 < frame_bytes(tmp_path / "raw")

    # Compressed into compressed, compressed into raw, raw into compressed: the same frames.
    for source in ("lz4", "raw"):
        for into in ("lz4", "raw"):
            fresh_raw, fresh_packed = twin_replays(300, chunk_slots=64, seed=9)
            target = fresh_packed if into == "lz4" else fresh_raw
            loaded = CheckpointStore(tmp_path / source).latest("f", into=target.arrays)
            assert loaded is not None and loaded.step == 7
            target.load_state_dict(loaded.state["replay"])
            # The run left alone: the raw replay as it was saved.
            reference, _ = twin_replays(300, chunk_slots=64)
            for name, array in raw.arrays.items():
                reference.arrays[name][:] = array
            reference.load_state_dict(loaded.state["replay"])
            for _ in range(20):
                assert_same_batch(reference.sample(), target.sample())
            # Writing goes on where it stopped (reopening the chunk that was being written).
            more = game_like_frames(90, seed=11)
            add_to_both((target,), more, np.random.default_rng(12))
            add_to_both((reference,), more, np.random.default_rng(12))
            for _ in range(10):
                assert_same_batch(reference.sample(), target.sample())


def test_incremental_saves_rewrite_a_chunk_that_was_compressed_since(tmp_path: Path) -> None:
    _, packed = twin_replays(256, chunk_slots=64)
    add_to_both((packed,), game_like_frames(30), np.random.default_rng(0))
    store = CheckpointStore(tmp_path, chunk_slots=64)
    first = store.save(1, {}, packed.arrays, None, "f")
    position, writes = packed.position, packed.writes
    add_to_both((packed,), game_like_frames(60, seed=2), np.random.default_rng(1))
    second = store.save(2, {}, packed.arrays, (position, packed.position), "f")

    def names(step_dir: Path) -> set[str]:
        manifest = json.loads((step_dir / "MANIFEST.json").read_text())
        return {chunk["file"] for chunk in manifest["arrays"]["frames"]["chunks"]}

    assert packed.writes - writes == 60
    assert len(names(second) - names(first)) == 2  # chunks 0 and 1 changed; 2 and 3 reused
    manifest = (second / "MANIFEST.json").read_text()
    assert '"encoding": "lz4"' in manifest


def test_the_memory_check_counts_the_raw_size_until_a_games_size_is_measured(
    monkeypatch,
) -> None:
    import psutil

    class Memory:
        available = 8 * 2**30

    monkeypatch.setattr(psutil, "virtual_memory", lambda: Memory)
    # 2M raw Pong frames are 13.16 GiB, more than 8 GiB, and an unmeasured game
    # may not count on compression.
    monkeypatch.setattr(compression, "measured_frame_bytes", lambda: {})
    assert compression.expected_frame_bytes("lz4", "pong") is None
    with pytest.raises(ResourceError, match="the replay memory needs 13.16 GiB"):
        ReplayMemory(2_000_000, (84, 84), np.uint8, 4, 32, 0, compression="lz4")
    monkeypatch.setattr(compression, "measured_frame_bytes", lambda: {"pong": 150.0})
    expected = compression.expected_frame_bytes("lz4", "pong")
    assert expected == 2 * 150.0  # with its margin
    ReplayMemory(
        2_000_000, (84, 84), np.uint8, 4, 32, 0, compression="lz4", expected_frame_bytes=expected
    )


def test_a_game_that_compresses_badly_stops_before_memory_runs_out(monkeypatch) -> None:
    import psutil

    class Memory:
        available = 10**5  # bytes: less than 1,900 frames of noise

    replay = ReplayMemory(2000, SHAPE, np.uint8, 4, 32, 0, compression="lz4", chunk_slots=100)
    noise = np.random.default_rng(0).integers(0, 256, (150, *SHAPE), dtype=np.uint8)
    for frame in noise[:99]:
        replay.add(frame, 0, 0.0, False)
    monkeypatch.setattr(psutil, "virtual_memory", lambda: Memory)
    with pytest.raises(ResourceError, match=r"compress to \d+ bytes each .*1,900 replay slots"):
        replay.add(noise[99], 0, 0.0, False)  # chunk 0 full: noise barely compresses


def test_bad_codec_and_vector_observations(capsys) -> None:
    with pytest.raises(ConfigError, match="replay_compression = 'zip' is not one of: none, lz4"):
        resolve_config("nature", env="pong", replay_compression="zip")
    with pytest.raises(ConfigError, match="accepted: lz4"):
        CompressedFrames(10, SHAPE, np.uint8, "zip")
    vectors = ReplayMemory(100, (4,), np.float32, 4, 32, 0, compression="lz4")
    assert not vectors.compressed and isinstance(vectors.frames, np.ndarray)


def test_a_cartpole_run_with_compression_says_it_is_ignored(capsys) -> None:
    import torch

    from dqnlab.run.state import TrainingState

    config = resolve_config(
        "classic", env="CartPole-v1", replay_compression="lz4", replay_capacity=100
    )
    state = TrainingState(config, torch.device("cpu"))
    state.close()
    assert "replay_compression = lz4 is for image observations" in capsys.readouterr().err


def test_with_a_device_copy_the_batches_come_from_it_and_upload_restores_it(
    tmp_path: Path,
) -> None:
    import torch

    device = torch.device("cpu")  # the device code path, where there is no GPU
    raw = ReplayMemory(200, SHAPE, np.uint8, 4, 32, 4, device=device)
    packed = ReplayMemory(
        200, SHAPE, np.uint8, 4, 32, 4, device=device, compression="lz4", chunk_slots=48
    )
    add_to_both((raw, packed), game_like_frames(330), np.random.default_rng(8))
    for _ in range(30):
        a, b = raw.sample(), packed.sample()
        assert torch.equal(a.window, b.window)
    CheckpointStore(tmp_path).save(1, {"replay": packed.state_dict()}, packed.arrays, None, "f")
    resumed = ReplayMemory(
        200, SHAPE, np.uint8, 4, 32, 0, device=device, compression="lz4", chunk_slots=48
    )
    loaded = CheckpointStore(tmp_path).latest("f", into=resumed.arrays)
    resumed.load_state_dict(loaded.state["replay"])
    resumed.upload()
    assert torch.equal(resumed._device_frames, raw._device_frames)
    for _ in range(10):
        assert torch.equal(raw.sample().window, resumed.sample().window)
