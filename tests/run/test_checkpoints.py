"""Checkpoints: atomic, verified, incremental; damage detected; failed saves leave nothing."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import io
import os
import shutil
import warnings
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from dqnlab.config import Config, config_fingerprint
from dqnlab.errors import DqnlabError, ResourceError
from dqnlab.run import checkpoint_chunks, checkpoint_files, checkpoint_manifest, checkpoints
from dqnlab.run.checkpoints import (
    CheckpointStore,
    CheckpointWarning,
    written_slots,
)
from tests.helpers import RunsCode

CAPACITY = 1000
CHUNK_SLOTS = 64  # 16 chunks per array: 15 of 64 slots and a last one of 40
CHUNKS = 16
ARRAYS = 5
FINGERPRINT = config_fingerprint(Config(env="pong", replay_capacity=CAPACITY))


def replay_arrays(seed: int = 0) -> dict[str, np.ndarray]:
    """Arrays shaped like ReplayMemory's, with 4x4 frames, filled with random contents."""
    rng = np.random.default_rng(seed)
    return {
        "frames": rng.integers(0, 256, (CAPACITY, 4, 4), dtype=np.uint8),
        "actions": rng.integers(0, 18, CAPACITY, dtype=np.int32),
        "rewards": rng.standard_normal(CAPACITY).astype(np.float32),
        "terminals": rng.random(CAPACITY) < 0.1,
        "is_last": rng.random(CAPACITY) < 0.1,
    }


def empty_like(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {name: np.zeros_like(array) for name, array in arrays.items()}


def copy_of(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {name: array.copy() for name, array in arrays.items()}


def write(arrays: dict[str, np.ndarray], start: int, count: int, seed: int) -> tuple[int, int]:
    """Overwrite `count` ring slots from `start` as the replay would; return the range."""
    rng = np.random.default_rng(seed)
    slots = (start + np.arange(count)) % CAPACITY
    arrays["frames"][slots] = rng.integers(0, 256, (count, 4, 4), dtype=np.uint8)
    arrays["actions"][slots] = rng.integers(0, 18, count, dtype=np.int32)
    arrays["rewards"][slots] = rng.standard_normal(count).astype(np.float32)
    arrays["terminals"][slots] = rng.random(count) < 0.5
    arrays["is_last"][slots] = rng.random(count) < 0.5
    written = written_slots(start, count, CAPACITY)
    assert written is not None
    return written


def small_state(step: int) -> dict[str, Any]:
    generator = torch.Generator().manual_seed(step)
    return {
        "online": {"weight": torch.randn(3, 3, generator=generator)},
        "optimizer": {"state": {0: {"square_avg": torch.rand(3, generator=generator)}}},
        "replay_rng": np.random.default_rng(step).bit_generator.state,
        "torch_rng": torch.get_rng_state(),
        "step": step,
        "epsilon": 0.1,
    }


def assert_same_state(loaded: dict[str, Any], expected: dict[str, Any]) -> None:
    assert torch.equal(loaded["online"]["weight"], expected["online"]["weight"])
    assert torch.equal(
        loaded["optimizer"]["state"][0]["square_avg"],
        expected["optimizer"]["state"][0]["square_avg"],
    )
    assert loaded["replay_rng"] == expected["replay_rng"]
    assert torch.equal(loaded["torch_rng"], expected["torch_rng"])
    assert loaded["step"] == expected["step"] and loaded["epsilon"] == expected["epsilon"]


def assert_same_arrays(loaded: dict[str, np.ndarray], expected: dict[str, np.ndarray]) -> None:
    for name, array in expected.items():
        assert loaded[name].dtype == array.dtype
        np.testing.assert_array_equal(loaded[name], array, err_msg=name)


@contextlib.contextmanager
def no_warning() -> Iterator[None]:
    with warnings.catch_warnings():
        warnings.simplefilter("error", CheckpointWarning)
        yield


def store_in(run_dir: Path, keep: int = 2) -> CheckpointStore:
    return CheckpointStore(run_dir, keep=keep, chunk_slots=CHUNK_SLOTS)


def listing(run_dir: Path) -> dict[str, int]:
    """Every file and folder under RUN_DIR/checkpoints, with file sizes."""
    root = run_dir / "checkpoints"
    return {
        str(path.relative_to(root)): path.stat().st_size if path.is_file() else -1
        for path in root.rglob("*")
    }


def chunk_files(run_dir: Path) -> set[str]:
    return {path.name for path in (run_dir / "checkpoints" / "replay").iterdir()}


def manifest_of(run_dir: Path, step: int) -> checkpoint_manifest.Manifest:
    return checkpoint_manifest.read_manifest(run_dir / "checkpoints" / f"step-{step:09d}")


def new_chunks(run_dir: Path, step: int) -> list[str]:
    """The chunk files that the checkpoint of `step` wrote itself."""
    manifest = manifest_of(run_dir, step)
    return [
        chunk.name
        for record in manifest.arrays.values()
        for chunk in record.chunks
        if chunk is not None and chunk.name.endswith(f".g{manifest.generation:09d}.bin")
    ]


def two_checkpoints(run_dir: Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Step 1 full, then step 2 after 100 writes at slots 100..199; both snapshots."""
    store = store_in(run_dir)
    arrays = replay_arrays()
    store.save(1, small_state(1), arrays, None, FINGERPRINT)
    first = copy_of(arrays)
    store.save(2, small_state(2), arrays, write(arrays, 100, 100, seed=1), FINGERPRINT)
    return first, copy_of(arrays)


# Round trip and incremental saves ------------------------------------------------------


def test_round_trip_is_bit_identical(tmp_path: Path) -> None:
    arrays = replay_arrays()
    state = small_state(7)
    directory = store_in(tmp_path).save(7, state, arrays, None, FINGERPRINT)
    assert directory == tmp_path / "checkpoints" / "step-000000007"
    assert sorted(path.name for path in directory.iterdir()) == ["MANIFEST.json", "state.pt"]

    into = empty_like(arrays)
    loaded = store_in(tmp_path).latest(FINGERPRINT, into=into)
    assert loaded is not None and loaded.step == 7 and loaded.arrays_loaded
    assert_same_state(loaded.state, state)
    assert_same_arrays(into, arrays)

    # Without `into`: verified first, then read into place on request.
    loaded = store_in(tmp_path).latest(FINGERPRINT)
    assert loaded is not None and not loaded.arrays_loaded
    later = empty_like(arrays)
    loaded.load_arrays(later)
    assert_same_arrays(later, arrays)


def test_ring_ranges_map_to_the_chunks_holding_them() -> None:
    def chunks(slots: tuple[int, int] | None) -> set[int] | None:
        return checkpoint_chunks.changed_chunks(slots, CAPACITY, CHUNK_SLOTS)

    assert chunks(None) is None
    assert chunks((5, 5)) == set()  # start == stop: nothing written
    assert chunks((0, 64)) == {0}
    assert chunks((63, 65)) == {0, 1}
    assert chunks((100, 200)) == {1, 2, 3}
    assert chunks((950, 30)) == {14, 15, 0}  # wraps around
    assert chunks((990, 0)) == {15}
    with pytest.raises(ValueError):
        chunks((1000, 5))
    assert written_slots(990, 20, CAPACITY) == (990, 10)
    assert written_slots(5, 0, CAPACITY) == (5, 5)
    assert written_slots(5, CAPACITY, CAPACITY) is None  # a whole ring: everything


@pytest.mark.parametrize(
    ("start", "count", "chunks"),
    [(100, 100, {1, 2, 3}), (950, 80, {14, 15, 0})],  # the second wraps around
)
def test_incremental_save_writes_only_the_changed_chunks(
    tmp_path: Path, start: int, count: int, chunks: set[int], monkeypatch: pytest.MonkeyPatch
) -> None:
    store = store_in(tmp_path)
    arrays = replay_arrays()
    store.save(1, small_state(1), arrays, None, FINGERPRINT)
    assert len(chunk_files(tmp_path)) == ARRAYS * CHUNKS
    before = chunk_files(tmp_path)

    written_bytes = []
    original = checkpoint_files.write_buffer

    def counting_write(handle: Any, data: memoryview) -> None:
        written_bytes.append(data.nbytes)
        original(handle, data)

    monkeypatch.setattr(checkpoint_files, "write_buffer", counting_write)
    changed = write(arrays, start, count, seed=1)
    store.save(2, small_state(2), arrays, changed, FINGERPRINT)

    added = chunk_files(tmp_path) - before
    assert sorted(int(name.split(".")[1]) for name in added) == sorted(list(chunks) * ARRAYS)
    chunk_bytes = sum(
        min(CHUNK_SLOTS, CAPACITY - index * CHUNK_SLOTS) * (array.nbytes // CAPACITY)
        for index in chunks
        for array in arrays.values()
    )
    state_bytes = (tmp_path / "checkpoints" / "step-000000002" / "state.pt").stat().st_size
    manifest_bytes = (tmp_path / "checkpoints" / "step-000000002" / "MANIFEST.json").stat()
    assert sum(written_bytes) == chunk_bytes + state_bytes + manifest_bytes.st_size

    into = empty_like(arrays)
    loaded = store_in(tmp_path).latest(FINGERPRINT, into=into)
    assert loaded is not None and loaded.step == 2
    assert_same_arrays(into, arrays)


def test_a_fresh_store_rewrites_everything_on_its_first_save(tmp_path: Path) -> None:
    """It reuses no file of the checkpoints it finds: it does not know what the caller's
    arrays hold relative to them. (Given a range, a fresh store counts it from the arrays'
    creation and leaves out the zeros beyond: tests/run/test_checkpoint_filled.py.)"""
    arrays = replay_arrays()
    store_in(tmp_path).save(1, small_state(1), arrays, None, FINGERPRINT)
    store_in(tmp_path).save(2, small_state(2), arrays, None, FINGERPRINT)
    assert len(new_chunks(tmp_path, 2)) == ARRAYS * CHUNKS


def test_resumed_store_saves_incrementally_from_the_loaded_checkpoint(tmp_path: Path) -> None:
    arrays = replay_arrays()
    store_in(tmp_path).save(1, small_state(1), arrays, None, FINGERPRINT)
    store = store_in(tmp_path)
    arrays = empty_like(arrays)
    assert store.latest(FINGERPRINT, into=arrays) is not None
    store.save(2, small_state(2), arrays, write(arrays, 0, 10, seed=3), FINGERPRINT)
    assert len(new_chunks(tmp_path, 2)) == ARRAYS  # chunk 0 of each array
    into = empty_like(arrays)
    store_in(tmp_path).latest(FINGERPRINT, into=into)
    assert_same_arrays(into, arrays)


def test_older_checkpoints_stay_loadable_after_incremental_saves(tmp_path: Path) -> None:
    store = store_in(tmp_path, keep=3)
    arrays = replay_arrays()
    snapshots = []
    changed = None
    for step, start in [(10, 0), (20, 500), (30, 990)]:
        store.save(step, small_state(step), arrays, changed, FINGERPRINT)
        snapshots.append(copy_of(arrays))
        changed = write(arrays, start, 200, seed=step)
    assert store.steps() == [10, 20, 30]
    for step, snapshot in zip([30, 20, 10], reversed(snapshots), strict=True):
        into = empty_like(arrays)
        with pytest.warns(CheckpointWarning) if step != 30 else no_warning():
            loaded = store_in(tmp_path).latest(FINGERPRINT, into=into)
        assert loaded is not None and loaded.step == step
        assert_same_arrays(into, snapshot)
        (loaded.directory / "MANIFEST.json").unlink()  # hide it: the next one is older


def test_keeps_the_last_n_and_deletes_unreferenced_chunks(tmp_path: Path) -> None:
    store = store_in(tmp_path, keep=2)
    arrays = replay_arrays()
    for step in range(1, 6):
        changed = None if step == 1 else write(arrays, step * 150, 100, seed=step)
        store.save(step, small_state(step), arrays, changed, FINGERPRINT)
    assert store.steps() == [4, 5]
    assert sorted(path.name for path in (tmp_path / "checkpoints").iterdir()) == [
        "replay",
        "step-000000004",
        "step-000000005",
    ]
    referenced = {
        chunk.name
        for step in (4, 5)
        for record in manifest_of(tmp_path, step).arrays.values()
        for chunk in record.chunks
    }
    assert chunk_files(tmp_path) == referenced
    # Chunk 14 (slots 896..959) was never written again: still the first save's file.
    assert "frames.00014.g000000001.bin" in referenced
    into = empty_like(arrays)
    store_in(tmp_path).latest(FINGERPRINT, into=into)
    assert_same_arrays(into, arrays)


def test_saving_a_step_twice_replaces_it(tmp_path: Path) -> None:
    store = store_in(tmp_path)
    arrays = replay_arrays()
    store.save(5, small_state(5), arrays, None, FINGERPRINT)
    changed = write(arrays, 0, 10, seed=1)
    store.save(5, small_state(6), arrays, changed, FINGERPRINT)
    assert store.steps() == [5]
    into = empty_like(arrays)
    loaded = store_in(tmp_path).latest(FINGERPRINT, into=into)
    assert loaded is not None
    assert_same_state(loaded.state, small_state(6))
    assert_same_arrays(into, arrays)
    assert not [p for p in (tmp_path / "checkpoints").iterdir() if p.name.startswith(".")]


def test_state_outside_torchs_weights_only_types_is_refused_before_writing(
    tmp_path: Path,
) -> None:
    state = {"frame_history": np.arange(12, dtype=np.uint8).reshape(3, 4)}
    with pytest.raises(ValueError, match="numpy.* outside torch's weights-only types"):
        store_in(tmp_path).save(1, state, replay_arrays(), None, FINGERPRINT)
    assert store_in(tmp_path).steps() == []


def craft_state(run_dir: Path, step: int, marker: Path) -> bytes:
    """Replace the state of checkpoint `step` by one that runs code when unpickled, with a
    manifest whose size and CRC-32 match it, as someone who can write the run directory
    could; return its bytes."""
    buffer = io.BytesIO()
    torch.save({**small_state(step), "online": RunsCode(marker)}, buffer)
    crafted = buffer.getvalue()
    directory = run_dir / "checkpoints" / f"step-{step:09d}"
    (directory / "state.pt").write_bytes(crafted)
    record = checkpoint_manifest.FileRecord("state.pt", len(crafted), zlib.crc32(crafted))
    manifest = dataclasses.replace(manifest_of(run_dir, step), state=record)
    (directory / "MANIFEST.json").write_bytes(manifest.to_json())
    return crafted


def test_a_crafted_state_file_is_refused_without_running_it(tmp_path: Path) -> None:
    marker = tmp_path / "marker"
    first, _ = two_checkpoints(tmp_path)
    crafted = craft_state(tmp_path, 2, marker)
    torch.load(io.BytesIO(crafted), weights_only=False)  # the attack is real: a full unpickle
    assert marker.exists()  # runs it
    marker.unlink()
    into = empty_like(first)
    with pytest.warns(CheckpointWarning, match="step-000000002") as caught:
        loaded = store_in(tmp_path).latest(FINGERPRINT, into=into)
    assert "state.pt is refused: it holds exec" in str(caught[0].message)
    assert loaded is not None and loaded.step == 1
    assert_same_state(loaded.state, small_state(1))
    assert_same_arrays(into, first)
    craft_state(tmp_path, 1, marker)
    with pytest.warns(CheckpointWarning), pytest.raises(DqnlabError, match="no complete") as error:
        store_in(tmp_path).latest(FINGERPRINT)
    assert str(error.value).count("state.pt is refused") == 2
    assert not marker.exists()


# Damage: detected, and the previous complete checkpoint used ----------------------------


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:-1])


def _flip_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01
    path.write_bytes(bytes(data))


def _damage(run_dir: Path, how: str) -> None:
    step_dir = run_dir / "checkpoints" / "step-000000002"
    chunk = run_dir / "checkpoints" / "replay" / new_chunks(run_dir, 2)[0]
    if how == "truncated state":
        _truncate(step_dir / "state.pt")
    elif how == "truncated chunk":
        _truncate(chunk)
    elif how == "flipped byte in state":
        _flip_byte(step_dir / "state.pt")
    elif how == "flipped byte in chunk":
        _flip_byte(chunk)
    elif how == "missing manifest":
        (step_dir / "MANIFEST.json").unlink()
    elif how == "missing chunk":
        chunk.unlink()
    elif how == "edited manifest":
        text = (step_dir / "MANIFEST.json").read_text()
        (step_dir / "MANIFEST.json").write_text(text.replace('"step": 2', '"step": 3'))
    elif how == "garbage manifest":
        (step_dir / "MANIFEST.json").write_text("{not json")
    else:
        raise AssertionError(how)


DAMAGE = [
    ("truncated state", "state.pt has"),
    ("truncated chunk", "has 1023 bytes"),
    ("flipped byte in state", "state.pt fails its CRC-32"),
    ("flipped byte in chunk", "fails its CRC-32"),
    ("missing manifest", "no MANIFEST.json"),
    ("missing chunk", "is missing"),
    ("edited manifest", "fails its own checksum"),
    ("garbage manifest", "unreadable"),
]


@pytest.mark.parametrize(("how", "reason"), DAMAGE)
def test_damaged_checkpoint_is_skipped_for_the_previous_one(
    tmp_path: Path, how: str, reason: str
) -> None:
    first, _ = two_checkpoints(tmp_path)
    _damage(tmp_path, how)
    into = empty_like(first)
    with pytest.warns(CheckpointWarning, match="step-000000002") as caught:
        loaded = store_in(tmp_path).latest(FINGERPRINT, into=into)
    assert reason in str(caught[0].message) and "falling back" in str(caught[0].message)
    assert loaded is not None and loaded.step == 1
    assert_same_state(loaded.state, small_state(1))
    assert_same_arrays(into, first)


def test_damage_found_after_choosing_is_an_error(tmp_path: Path) -> None:
    _, second = two_checkpoints(tmp_path)
    loaded = store_in(tmp_path).latest(FINGERPRINT)
    assert loaded is not None and loaded.step == 2
    _damage(tmp_path, "flipped byte in chunk")
    with pytest.raises(DqnlabError, match="corrupted"):
        loaded.load_arrays(empty_like(second))


def test_no_complete_checkpoint_at_all_is_an_error(tmp_path: Path) -> None:
    store = store_in(tmp_path)
    arrays = replay_arrays()
    directory = store.save(1, small_state(1), arrays, None, FINGERPRINT)
    _flip_byte(directory / "state.pt")
    with pytest.warns(CheckpointWarning), pytest.raises(DqnlabError, match="no complete"):
        store_in(tmp_path).latest(FINGERPRINT)


def test_no_checkpoint_yet_is_none(tmp_path: Path) -> None:
    assert store_in(tmp_path).latest(FINGERPRINT) is None


def test_resuming_from_an_earlier_checkpoint_removes_the_abandoned_later_ones(
    tmp_path: Path,
) -> None:
    store = store_in(tmp_path, keep=3)
    arrays = replay_arrays()
    changed = None
    for step in (10, 20, 30):
        store.save(step, small_state(step), arrays, changed, FINGERPRINT)
        changed = write(arrays, step, 50, seed=step)
    _flip_byte(tmp_path / "checkpoints" / "step-000000030" / "state.pt")
    resumed = store_in(tmp_path, keep=3)
    arrays = empty_like(arrays)
    with pytest.warns(CheckpointWarning, match="step-000000030"):
        assert resumed.latest(FINGERPRINT, into=arrays) is not None
    changed = write(arrays, 700, 50, seed=99)
    with pytest.warns(CheckpointWarning, match="newer than step 25"):
        resumed.save(25, small_state(25), arrays, changed, FINGERPRINT)
    assert resumed.steps() == [10, 20, 25]
    into = empty_like(arrays)
    loaded = store_in(tmp_path).latest(FINGERPRINT, into=into)
    assert loaded is not None and loaded.step == 25
    assert_same_arrays(into, arrays)


def test_another_config_or_version_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store_in(tmp_path).save(1, small_state(1), replay_arrays(), None, FINGERPRINT)
    other = config_fingerprint(Config(env="breakout", replay_capacity=CAPACITY))
    with pytest.raises(DqnlabError, match="another configuration"):
        store_in(tmp_path).latest(other)
    monkeypatch.setattr(checkpoints, "__version__", "9.9.9")
    with pytest.raises(DqnlabError, match="written by dqnlab 0.1.0 and this is dqnlab 9.9.9"):
        store_in(tmp_path).latest(FINGERPRINT)


# Failed saves: previous checkpoint intact, nothing left behind --------------------------


@pytest.mark.parametrize("failing_file", ["frames.00001", "is_last.00003", "state.pt", "MANIFEST"])
def test_disk_full_midway_leaves_the_previous_checkpoint_and_no_files(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failing_file: str
) -> None:
    store = store_in(tmp_path)
    arrays = replay_arrays()
    store.save(1, small_state(1), arrays, None, FINGERPRINT)
    first = copy_of(arrays)
    before = listing(tmp_path)

    original = checkpoint_files.write_buffer

    def write_until_full(handle: Any, data: memoryview) -> None:
        if Path(handle.name).name.startswith(failing_file):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        original(handle, data)

    monkeypatch.setattr(checkpoint_files, "write_buffer", write_until_full)
    changed = write(arrays, 0, 300, seed=1)
    with pytest.raises(DqnlabError, match="No space left on device") as raised:
        store.save(2, small_state(2), arrays, changed, FINGERPRINT)
    assert "step 2" in str(raised.value) and "intact" in str(raised.value)
    assert listing(tmp_path) == before

    into = empty_like(arrays)
    loaded = store_in(tmp_path).latest(FINGERPRINT, into=into)
    assert loaded is not None and loaded.step == 1
    assert_same_arrays(into, first)

    # The same store saves again once there is room, still incrementally and correctly.
    monkeypatch.setattr(checkpoint_files, "write_buffer", original)
    store.save(2, small_state(2), arrays, changed, FINGERPRINT)
    store_in(tmp_path).latest(FINGERPRINT, into=into)
    assert_same_arrays(into, arrays)


def test_failed_rename_of_a_replaced_step_restores_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = store_in(tmp_path)
    arrays = replay_arrays()
    store.save(1, small_state(1), arrays, None, FINGERPRINT)
    before = listing(tmp_path)
    original = os.replace

    def replace(source: Any, target: Any) -> None:
        if Path(source).name.startswith(".partial-"):
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        original(source, target)

    monkeypatch.setattr(checkpoints.os, "replace", replace)
    with pytest.raises(DqnlabError, match="Input/output error"):
        store.save(1, small_state(2), arrays, (0, 5), FINGERPRINT)
    assert listing(tmp_path) == before


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes to read-only directories anyway")
def test_unwritable_directory_leaves_the_previous_checkpoint(tmp_path: Path) -> None:
    store = store_in(tmp_path)
    arrays = replay_arrays()
    store.save(1, small_state(1), arrays, None, FINGERPRINT)
    before = listing(tmp_path)
    replay_dir = tmp_path / "checkpoints" / "replay"
    replay_dir.chmod(0o500)
    try:
        with pytest.raises(DqnlabError, match="Permission denied"):
            store.save(2, small_state(2), arrays, (0, 5), FINGERPRINT)
    finally:
        replay_dir.chmod(0o700)
    assert listing(tmp_path) == before
    assert store_in(tmp_path).latest(FINGERPRINT) is not None


def test_not_enough_free_space_is_refused_before_writing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = store_in(tmp_path)
    arrays = replay_arrays()
    store.save(1, small_state(1), arrays, None, FINGERPRINT)
    before = listing(tmp_path)
    usage = shutil.disk_usage(tmp_path)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage._replace(free=1000))
    with pytest.raises(ResourceError, match=r"needs \d+\.\d\d GiB but only 0\.00 GiB is free"):
        store.save(2, small_state(2), arrays, None, FINGERPRINT)
    assert listing(tmp_path) == before
