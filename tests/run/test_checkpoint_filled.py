"""A checkpoint stores the filled part of the replay: chunks never written are left out, a
raw chunk is cut after its last written slot, and loading restores the zeros beyond."""

from __future__ import annotations

import functools
import json
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

from dqnlab.algorithm.compression import CompressedFrames
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.config import config_fingerprint, resolve_config
from dqnlab.run import checkpoint_manifest
from dqnlab.run import train as train_module
from dqnlab.run.checkpoints import CheckpointStore, written_slots
from dqnlab.run.rundir import prepare_run_dir
from dqnlab.run.state import TrainingState
from dqnlab.run.train import train
from tests.run.test_resume import assert_identical, final_state

CAPACITY = 2000
CHUNK_SLOTS = 100  # 20 chunks per array
SHAPE = (8, 8)
FINGERPRINT = "filled"


def replay(compression: str = "none", seed: int = 0) -> ReplayMemory:
    return ReplayMemory(
        CAPACITY, SHAPE, np.uint8, 4, 8, seed, compression=compression, chunk_slots=CHUNK_SLOTS
    )


def fill(memory: ReplayMemory, count: int, seed: int) -> tuple[int, int] | None:
    """`count` writes of random frames (an episode's end now and then); the ring range."""
    rng = np.random.default_rng(seed)
    start = memory.position
    for step in range(count):
        frame = rng.integers(1, 256, SHAPE, dtype=np.uint8)  # never all zeros
        if step % 37 == 36:
            memory.add_last(frame)
        else:
            memory.add(frame, int(rng.integers(4)), float(rng.standard_normal()), step % 11 == 0)
    return written_slots(start, count, CAPACITY)


def dirty(compression: str) -> ReplayMemory:
    """A replay whose every slot holds something: loading must leave nothing of it."""
    memory = replay(compression, seed=1)
    fill(memory, CAPACITY + 3, seed=99)
    return memory


def frames_of(memory: ReplayMemory) -> np.ndarray:
    if isinstance(memory.frames, CompressedFrames):
        return np.concatenate([memory.frames.chunk(i) for i in range(memory.frames.chunks)])
    return memory.frames


def assert_same_replay(loaded: ReplayMemory, expected: ReplayMemory) -> None:
    np.testing.assert_array_equal(frames_of(loaded), frames_of(expected))
    for name in ("actions", "rewards", "terminals", "is_last"):
        np.testing.assert_array_equal(loaded.arrays[name], expected.arrays[name], err_msg=name)


def save(store: CheckpointStore, step: int, memory: ReplayMemory, changed) -> Path:
    return store.save(step, {"replay": memory.state_dict()}, memory.arrays, changed, FINGERPRINT)


def load(run_dir: Path, into: ReplayMemory) -> CheckpointStore:
    store = CheckpointStore(run_dir, chunk_slots=CHUNK_SLOTS)
    loaded = store.latest(FINGERPRINT, into=into.arrays)
    assert loaded is not None
    into.load_state_dict(loaded.state["replay"])
    return store


def replay_bytes_on_disk(run_dir: Path) -> int:
    return sum(path.stat().st_size for path in (run_dir / "checkpoints" / "replay").iterdir())


def manifest(run_dir: Path, step: int) -> checkpoint_manifest.Manifest:
    return checkpoint_manifest.read_manifest(run_dir / "checkpoints" / f"step-{step:09d}")


def test_a_partly_filled_raw_replay_stores_its_filled_slots_only(tmp_path: Path) -> None:
    memory = replay()
    changed = fill(memory, 450, seed=0)
    assert changed == (0, 450)
    save(CheckpointStore(tmp_path, chunk_slots=CHUNK_SLOTS), 1, memory, changed)
    # 450 slots: chunks 0-3 whole, chunk 4 cut to 50 slots, chunks 5-19 left out.
    for record in manifest(tmp_path, 1).arrays.values():
        assert [chunk is not None for chunk in record.chunks] == [True] * 5 + [False] * 15
        assert [chunk.slots for chunk in record.chunks[:5]] == [None] * 4 + [50]
    per_slot = 8 * 8 + 4 + 4 + 1 + 1
    assert replay_bytes_on_disk(tmp_path) == 450 * per_slot
    # Into a compressed replay too: the cut chunk is padded with zeros and compressed.
    for into in (replay(seed=5), dirty("none"), dirty("lz4")):
        load(tmp_path, into)
        assert_same_replay(into, memory)
        assert (into.position, into.size, into.writes) == (450, 450, 450)


def test_a_partly_filled_compressed_replay_stores_its_written_chunks_whole(
    tmp_path: Path,
) -> None:
    memory = replay("lz4")
    changed = fill(memory, 450, seed=0)
    save(CheckpointStore(tmp_path, chunk_slots=CHUNK_SLOTS), 1, memory, changed)
    frames = manifest(tmp_path, 1).arrays["frames"]
    assert sum(chunk is not None for chunk in frames.chunks) == 5
    assert all(chunk.slots is None for chunk in frames.chunks[:5])
    for into in (replay("lz4", seed=5), dirty("lz4"), dirty("none")):
        load(tmp_path, into)
        assert_same_replay(into, memory)


def test_later_saves_rewrite_the_changed_chunks_and_leave_out_the_unwritten(
    tmp_path: Path,
) -> None:
    memory = replay()
    store = CheckpointStore(tmp_path, chunk_slots=CHUNK_SLOTS)
    save(store, 1, memory, fill(memory, 450, seed=0))
    first = manifest(tmp_path, 1)
    save(store, 2, memory, fill(memory, 300, seed=1))  # slots 450-749: chunks 4-7
    second = manifest(tmp_path, 2)
    for name, record in second.arrays.items():
        reused = [a == b for a, b in zip(first.arrays[name].chunks, record.chunks, strict=True)]
        assert reused[:4] == [True] * 4 and reused[4:8] == [False] * 4, name
        assert all(chunk is None for chunk in record.chunks[8:]), name
        assert record.chunks[7] is not None and record.chunks[7].slots == 50
    save(store, 3, memory, fill(memory, 0, seed=2))  # nothing written: every file reused
    assert manifest(tmp_path, 3).arrays == second.arrays
    into = dirty("none")
    store = load(tmp_path, into)
    assert_same_replay(into, memory)
    # A store that resumed saves incrementally from what it loaded, still leaving out zeros.
    save(store, 4, memory, fill(memory, 100, seed=3))  # slots 750-849: chunks 7-8
    fourth = manifest(tmp_path, 4).arrays["frames"].chunks
    assert fourth[:7] == second.arrays["frames"].chunks[:7]
    assert fourth[8] is not None and fourth[8].slots == 50 and fourth[9] is None
    into = replay()
    load(tmp_path, into)
    assert_same_replay(into, memory)


@pytest.mark.parametrize("compression", ["none", "lz4"])
def test_a_full_ring_stores_every_chunk_whole(tmp_path: Path, compression: str) -> None:
    memory = replay(compression)
    store = CheckpointStore(tmp_path, chunk_slots=CHUNK_SLOTS)
    save(store, 1, memory, fill(memory, 1234, seed=0))
    save(store, 2, memory, fill(memory, 900, seed=1))  # wraps around: every slot written
    save(store, 3, memory, fill(memory, 2500, seed=2))  # more than the ring: None, all
    for step in (2, 3):
        for name, record in manifest(tmp_path, step).arrays.items():
            assert all(chunk is not None and chunk.slots is None for chunk in record.chunks), name
    into = dirty(compression)
    load(tmp_path, into)
    assert_same_replay(into, memory)


def as_format_1(run_dir: Path, step: int) -> None:
    """Rewrite a checkpoint's manifest as dqnlab wrote it before chunks could be left out
    (format 1: the same records, every chunk present and whole)."""
    path = run_dir / "checkpoints" / f"step-{step:09d}" / checkpoint_manifest.MANIFEST_FILE
    body = json.loads(path.read_bytes())
    body.pop("manifest_crc32")
    for record in body["arrays"].values():
        assert all(chunk is not None and "slots" not in chunk for chunk in record["chunks"])
    body["format"] = "dqnlab-training-checkpoint-1"
    body["manifest_crc32"] = f"{zlib.crc32(checkpoint_manifest.canonical(body)):08x}"
    path.write_bytes(json.dumps(body, indent=1).encode())


def test_a_checkpoint_of_the_earlier_format_loads_and_saves_on(tmp_path: Path) -> None:
    memory = replay()
    fill(memory, 450, seed=0)
    # The earlier store wrote every chunk whole, as a save without a changed range does.
    save(CheckpointStore(tmp_path, chunk_slots=CHUNK_SLOTS), 1, memory, None)
    as_format_1(tmp_path, 1)
    into = dirty("none")
    store = load(tmp_path, into)
    assert_same_replay(into, memory)
    save(store, 2, into, fill(into, 100, seed=1))  # chunks 4-5 rewritten, the rest reused
    fill(memory, 100, seed=1)
    assert sum(chunk.name.endswith("g000000002.bin") for chunk in
               manifest(tmp_path, 2).arrays["frames"].chunks) == 2  # fmt: skip
    into = replay()
    load(tmp_path, into)
    assert_same_replay(into, memory)


def test_a_resumed_run_with_filled_part_checkpoints_is_bit_identical(
    tmp_path: Path, monkeypatch
) -> None:
    """CartPole with a 2,000-slot replay in chunks of 100: checkpoints every 50 steps hold
    the filled slots only; a run stopped after step 137 and resumed from 100 ends as one
    that ran through."""
    monkeypatch.setattr(
        train_module, "CheckpointStore", functools.partial(CheckpointStore, chunk_slots=100)
    )
    config = resolve_config(
        "classic", env="CartPole-v1", total_steps=200, replay_start_steps=50,
        eval_period_steps=100, eval_steps=50, checkpoint_period_steps=50, replay_capacity=2000,
        seed=4,
    )  # fmt: skip
    device = torch.device("cpu")
    reference = tmp_path / "reference"
    prepare_run_dir(reference, force=False)
    train(config, reference, device, progress=False, tensorboard=False)

    resumed = tmp_path / "resumed"
    prepare_run_dir(resumed, force=False)
    original = TrainingState.advance

    def crash(self):
        if self.steps == 137:
            raise RuntimeError("the machine went down")
        return original(self)

    monkeypatch.setattr(TrainingState, "advance", crash)
    with pytest.raises(RuntimeError, match="went down"):
        train(config, resumed, device, progress=False, tensorboard=False)
    frames = manifest(resumed, 100).arrays["frames"]
    stored = sum(frames.stored_slots(index) for index in range(len(frames.chunks)))
    assert 100 <= stored < 200 and frames.chunks[-1] is None
    monkeypatch.setattr(TrainingState, "advance", original)
    train(config, resumed, device, progress=False, tensorboard=False, resume=True)

    state_a, replay_a = final_state(reference)
    state_b, replay_b = final_state(resumed)
    assert_identical(state_a["learner"], state_b["learner"], "learner")
    assert_identical(state_a["run"], state_b["run"], "run")
    assert_identical(replay_a, replay_b, "replay")
    assert config_fingerprint(config)  # the same config both times
