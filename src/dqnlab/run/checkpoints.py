"""Training checkpoints: the whole training state of a run, complete and verifiable (the
network files best.pt, last.pt ... are `rundir`'s).

`CheckpointStore` keeps complete, verifiable training checkpoints in RUN_DIR/checkpoints/:

    step-000001234/      one complete checkpoint
        state.pt         torch.save of the caller's small state (networks, optimizer, RNGs...):
                         tensors and plain Python values only, read with weights_only=True
        MANIFEST.json    written last: version, config fingerprint, step, and the size and
                         CRC-32 of state.pt and of every replay chunk file it needs
    replay/              chunk files shared by all checkpoints
        frames.00003.g000000007.bin   raw bytes of `frames` slots [3 * chunk_slots,
                                      4 * chunk_slots), written by save number 7
    .partial-step-.../   a save in progress (never read; removed when it fails)

Each replay array is cut into chunks of `chunk_slots` slots. A save writes only the chunks
holding slots written since the previous save and points the new manifest at the previous
checkpoint's files for the rest, so a checkpoint of a 1M replay writes about a quarter of
its 7 GB after 250k steps instead of all of it. A file that a checkpoint references is never
modified: rewritten chunks get a new generation in their name. A checkpoint is complete
when its manifest is valid and every file it names has the recorded size (checked always)
and CRC-32 (checked when loading); anything else is skipped with a warning.

Checksum: CRC-32 (zlib) is about four times faster than BLAKE2b (the README's figures
give the time to verify a 1M replay). A checksum here detects torn or flipped bytes, not
tampering, so the fast one is enough; chunk files are named by generation, not by content,
so nothing relies on the checksum being collision resistant.

Loading: a run directory may be writable by others (a shared cluster filesystem), and a
CRC-32 is no defence against a crafted file, so state.pt is read with torch's weights-only
unpickler, which builds tensors and plain Python values and calls nothing else. A state it
refuses is skipped as corrupted; `save` refuses to write one.
"""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import pickle
import re
import shutil
import warnings
import zlib
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import torch

from dqnlab import __version__
from dqnlab.errors import DqnlabError, ResourceError
from dqnlab.run.rundir import checkpoints_dir

# Training checkpoints ------------------------------------------------------------------

STORE_FORMAT = "dqnlab-training-checkpoint-1"
MANIFEST_FILE = "MANIFEST.json"
STATE_FILE = "state.pt"
REPLAY_DIR = "replay"
# 16,384 slots is 115 MB of 84x84 frames: a save rewrites at most two partly changed chunks
# per changed range (<= 230 MB wasted), and a 1M replay is 62 files per array.
DEFAULT_CHUNK_SLOTS = 16_384
_IO_PIECE_BYTES = 16 * 2**20  # checksum and write in pieces: no copy of a whole chunk
_MANIFEST_SLACK_BYTES = 2**20
_STEP_DIR = re.compile(r"step-(\d{9,})")
_CHUNK_FILE = re.compile(r"([A-Za-z0-9_]+)\.(\d{5,})\.g(\d{9,})\.bin(\.tmp)?")
_ARRAY_NAME = re.compile(r"[A-Za-z0-9_]+")
_PARTIAL_PREFIX = ".partial-"
_REPLACED_PREFIX = ".replaced-"


class CheckpointWarning(UserWarning):
    """A checkpoint was skipped or removed; the message says which and why."""


class _Incomplete(Exception):
    """A checkpoint is incomplete or corrupted; the message is the reason."""


def written_slots(start_position: int, writes: int, capacity: int) -> tuple[int, int] | None:
    """The ring range [start, stop) of `writes` writes from `start_position`; None: all slots.

    A replay's position and size alone cannot tell zero writes from `capacity` writes once
    it is full, so the caller counts writes since the last save.
    """
    if writes < 0 or not 0 <= start_position < capacity:
        raise ValueError(f"bad ring range: start {start_position}, {writes} writes")
    if writes >= capacity:
        return None
    return start_position, (start_position + writes) % capacity


@dataclass(frozen=True)
class FileRecord:
    name: str
    size: int
    crc32: int

    def to_json(self) -> dict[str, Any]:
        return {"file": self.name, "size": self.size, "crc32": f"{self.crc32:08x}"}

    @staticmethod
    def from_json(data: Mapping[str, Any]) -> FileRecord:
        return FileRecord(str(data["file"]), int(data["size"]), int(data["crc32"], 16))


@dataclass(frozen=True)
class ArrayRecord:
    dtype: str  # numpy dtype.str, e.g. "|u1"
    shape: tuple[int, ...]
    chunk_slots: int
    chunks: tuple[FileRecord, ...]

    def chunk_span(self, index: int) -> tuple[int, int]:
        start = index * self.chunk_slots
        return start, min(start + self.chunk_slots, self.shape[0])


@dataclass(frozen=True)
class Manifest:
    step: int
    generation: int  # save counter of the store: names new chunk files
    dqnlab_version: str
    config_fingerprint: str
    state: FileRecord
    arrays: dict[str, ArrayRecord]

    def to_json(self) -> bytes:
        body = {
            "format": STORE_FORMAT,
            "checksum": "crc32",
            "dqnlab_version": self.dqnlab_version,
            "config_fingerprint": self.config_fingerprint,
            "step": self.step,
            "generation": self.generation,
            "state": self.state.to_json(),
            "arrays": {
                name: {
                    "dtype": record.dtype,
                    "shape": list(record.shape),
                    "chunk_slots": record.chunk_slots,
                    "chunks": [chunk.to_json() for chunk in record.chunks],
                }
                for name, record in self.arrays.items()
            },
        }
        # The manifest checks itself too: a flipped digit in a step or size is caught.
        body["manifest_crc32"] = f"{zlib.crc32(_canonical(body)):08x}"
        return json.dumps(body, indent=1).encode()

    @staticmethod
    def from_json(text: bytes) -> Manifest:
        try:
            body = json.loads(text)
            recorded = int(body.pop("manifest_crc32"), 16)
            if zlib.crc32(_canonical(body)) != recorded:
                raise _Incomplete(f"{MANIFEST_FILE} fails its own checksum")
            if body["format"] != STORE_FORMAT:
                raise _Incomplete(f"{MANIFEST_FILE} has format {body['format']!r}")
            arrays = {
                name: ArrayRecord(
                    dtype=str(record["dtype"]),
                    shape=tuple(int(n) for n in record["shape"]),
                    chunk_slots=int(record["chunk_slots"]),
                    chunks=tuple(FileRecord.from_json(chunk) for chunk in record["chunks"]),
                )
                for name, record in body["arrays"].items()
            }
            return Manifest(
                step=int(body["step"]),
                generation=int(body["generation"]),
                dqnlab_version=str(body["dqnlab_version"]),
                config_fingerprint=str(body["config_fingerprint"]),
                state=FileRecord.from_json(body["state"]),
                arrays=arrays,
            )
        except (ValueError, KeyError, TypeError, AttributeError) as error:
            raise _Incomplete(f"{MANIFEST_FILE} is unreadable ({error!r})") from None


def _canonical(body: Mapping[str, Any]) -> bytes:
    return json.dumps(body, sort_keys=True, separators=(",", ":")).encode()


@dataclass
class LoadedCheckpoint:
    step: int
    state: dict[str, Any]
    directory: Path
    manifest: Manifest
    arrays_loaded: bool  # True when `latest(into=...)` already filled the arrays

    def load_arrays(self, into: Mapping[str, np.ndarray]) -> None:
        """Fill the preallocated arrays in place, verifying every chunk's CRC-32.

        There is no fallback from here: `CheckpointStore.latest(into=...)` loads the arrays
        while choosing the checkpoint, and falls back if one turns out corrupted.
        """
        try:
            _load_arrays(self.manifest, self.directory.parent / REPLAY_DIR, into)
        except _Incomplete as reason:
            raise DqnlabError(f"checkpoint {self.directory} is corrupted: {reason}") from None
        self.arrays_loaded = True


class CheckpointStore:
    """Complete, atomic, incremental training checkpoints in RUN_DIR/checkpoints/.

    One writer at a time. The store remembers the checkpoint it last saved or loaded: the
    next save takes the unchanged replay chunks from it. A fresh store has none, so its
    first save writes every chunk.
    """

    def __init__(
        self, run_dir: Path, keep: int = 2, chunk_slots: int = DEFAULT_CHUNK_SLOTS
    ) -> None:
        if keep < 1:
            raise ValueError(f"keep must be at least 1, not {keep}")
        if chunk_slots < 1:
            raise ValueError(f"chunk_slots must be at least 1, not {chunk_slots}")
        self.directory = checkpoints_dir(Path(run_dir))
        self.replay_directory = self.directory / REPLAY_DIR
        self.keep = keep
        self.chunk_slots = chunk_slots
        self._base: Manifest | None = None

    # Saving ---------------------------------------------------------------------------

    def save(
        self,
        step: int,
        state: dict[str, Any],
        arrays: Mapping[str, np.ndarray],
        changed_slots: tuple[int, int] | None,
        config_fingerprint: str,
    ) -> Path:
        """Write a complete checkpoint of `step`; return its directory.

        `arrays` are the replay arrays (same first dimension, the capacity); `changed_slots`
        is the ring range [start, stop) of slots written since the last save or load of
        this store (stop < start wraps around; start == stop is nothing), None for all.
        A failed save leaves the earlier checkpoints as they were and no files behind.
        """
        capacity = _check_arrays(arrays)
        changed = _changed_chunks(changed_slots, capacity, self.chunk_slots)
        buffer = io.BytesIO()
        torch.save(state, buffer)
        state_bytes = buffer.getbuffer()
        _check_loadable(state_bytes)
        plan = self._plan(arrays, changed)
        needed = len(state_bytes) + _MANIFEST_SLACK_BYTES
        needed += sum(
            arrays[name][start:stop].nbytes
            for name, chunks in plan.items()
            for start, stop, reused in chunks
            if reused is None
        )
        created: list[Path] = []
        staging = self.directory / f"{_PARTIAL_PREFIX}step-{step:09d}"
        final = self.directory / f"step-{step:09d}"
        replaced = self.directory / f"{_REPLACED_PREFIX}step-{step:09d}"
        try:
            self.replay_directory.mkdir(parents=True, exist_ok=True)
            self._check_free_space(step, needed)
            shutil.rmtree(staging, ignore_errors=True)
            generation = self._next_generation()
            records = {
                name: ArrayRecord(
                    dtype=arrays[name].dtype.str,
                    shape=tuple(arrays[name].shape),
                    chunk_slots=self.chunk_slots,
                    chunks=tuple(
                        reused
                        if reused is not None
                        else _write_file(
                            self.replay_directory / f"{name}.{index:05d}.g{generation:09d}.bin",
                            _pieces(arrays[name][start:stop].data),
                            created,
                        )
                        for index, (start, stop, reused) in enumerate(chunks)
                    ),
                )
                for name, chunks in plan.items()
            }
            _fsync_directory(self.replay_directory)
            staging.mkdir()
            created.append(staging)
            manifest = Manifest(
                step=step,
                generation=generation,
                dqnlab_version=__version__,
                config_fingerprint=config_fingerprint,
                state=_write_file(staging / STATE_FILE, _pieces(state_bytes), created),
                arrays=records,
            )
            _write_file(staging / MANIFEST_FILE, [memoryview(manifest.to_json())], created)
            _fsync_directory(staging)
            if final.exists():  # saved twice at one step: replace it
                shutil.rmtree(replaced, ignore_errors=True)
                os.replace(final, replaced)
            os.replace(staging, final)
            created.append(final)
            _fsync_directory(self.directory)
        except BaseException as error:
            for path in reversed(created):
                _remove(path)
            if replaced.exists() and not final.exists():
                with contextlib.suppress(OSError):
                    os.replace(replaced, final)
            if isinstance(error, OSError):
                raise DqnlabError(
                    f"could not write the checkpoint of step {step} in {self.directory}: "
                    f"{os.strerror(error.errno) if error.errno else error}; "
                    "the earlier checkpoints are intact"
                ) from error
            raise
        self._base = manifest
        try:
            self._prune(step)
        except OSError as error:
            warnings.warn(
                f"checkpoint of step {step} is complete, but removing old checkpoints in "
                f"{self.directory} failed: {error}",
                CheckpointWarning,
                stacklevel=2,
            )
        return final

    def _plan(
        self, arrays: Mapping[str, np.ndarray], changed: set[int] | None
    ) -> dict[str, list[tuple[int, int, FileRecord | None]]]:
        """Per array, per chunk: its slot span and the earlier file to reuse, or None."""
        plan: dict[str, list[tuple[int, int, FileRecord | None]]] = {}
        for name, array in arrays.items():
            base = self._base.arrays.get(name) if self._base is not None else None
            if (
                changed is None
                or base is None
                or (base.dtype, base.shape, base.chunk_slots)
                != (
                    array.dtype.str,
                    tuple(array.shape),
                    self.chunk_slots,
                )
            ):
                base = None
            chunks: list[tuple[int, int, FileRecord | None]] = []
            for index, start in enumerate(range(0, array.shape[0], self.chunk_slots)):
                stop = min(start + self.chunk_slots, array.shape[0])
                reused = None
                if base is not None and changed is not None and index not in changed:
                    record = base.chunks[index]
                    # Reuse only a file that is still there, whole: else write it again.
                    if _size_of(self.replay_directory / record.name) == record.size:
                        reused = record
                chunks.append((start, stop, reused))
            plan[name] = chunks
        return plan

    def _check_free_space(self, step: int, needed: int) -> None:
        free = shutil.disk_usage(self.directory).free
        if needed > free:
            raise ResourceError(
                f"the checkpoint of step {step} needs {needed / 2**30:.2f} GiB but only "
                f"{free / 2**30:.2f} GiB is free in {self.directory}; free some disk space"
            )

    def _next_generation(self) -> int:
        """One more than any generation in use, so a new chunk file never overwrites one."""
        latest = self._base.generation if self._base is not None else 0
        for directory in self._step_directories():
            with contextlib.suppress(_Incomplete):
                latest = max(latest, _read_manifest(directory).generation)
        for path in self.replay_directory.iterdir():
            match = _CHUNK_FILE.fullmatch(path.name)
            if match:
                latest = max(latest, int(match.group(3)))
        return latest + 1

    def _prune(self, saved_step: int) -> None:
        """Keep the newest `keep` complete checkpoints up to `saved_step`; delete the rest.

        Checkpoints after `saved_step` belong to a run that was resumed from an earlier
        one (the later ones were corrupted, or the user went back) and are removed too.
        Then every chunk file that no kept checkpoint references is deleted.
        """
        complete: list[tuple[int, Path, Manifest]] = []
        for directory in self._step_directories():
            step = _step_of(directory)
            try:
                manifest = _read_manifest(directory)
                _check_sizes(manifest, directory, self.replay_directory)
            except _Incomplete as reason:
                _warn(f"removing incomplete checkpoint {directory} ({reason})")
                shutil.rmtree(directory)
                continue
            if step > saved_step:
                _warn(
                    f"removing checkpoint {directory}: it is newer than step {saved_step}, "
                    "saved by a run that was resumed from an earlier checkpoint"
                )
                shutil.rmtree(directory)
                continue
            complete.append((step, directory, manifest))
        complete.sort(key=lambda entry: entry[0])
        for _, directory, _ in complete[: -self.keep]:
            shutil.rmtree(directory)
        for path in self.directory.iterdir():
            if path.name.startswith((_PARTIAL_PREFIX, _REPLACED_PREFIX)):
                shutil.rmtree(path)
        referenced = {
            chunk.name
            for _, _, manifest in complete[-self.keep :]
            for record in manifest.arrays.values()
            for chunk in record.chunks
        }
        for path in self.replay_directory.iterdir():
            if path.name not in referenced:
                path.unlink()
        _fsync_directory(self.replay_directory)
        _fsync_directory(self.directory)

    # Loading --------------------------------------------------------------------------

    def steps(self) -> list[int]:
        """The steps of the checkpoints whose manifest and file sizes are right, oldest first."""
        steps = []
        for directory in self._step_directories():
            try:
                _check_sizes(_read_manifest(directory), directory, self.replay_directory)
            except _Incomplete:
                continue
            steps.append(_step_of(directory))
        return sorted(steps)

    def latest(
        self,
        config_fingerprint: str,
        into: Mapping[str, np.ndarray] | None = None,
        map_location: str | torch.device = "cpu",
    ) -> LoadedCheckpoint | None:
        """The newest complete checkpoint, checksums verified; None when there is none.

        With `into` (the preallocated replay arrays), the replay is read into them in
        place while it is verified: one pass over the files, no second copy. Without it the
        chunks are verified by reading, and `load_arrays` reads them again. A corrupted or
        incomplete checkpoint is skipped with a warning saying why; when every one is, the
        contents of `into` are undefined and DqnlabError says why each was skipped.
        Another dqnlab version or config fingerprint raises DqnlabError.
        """
        if not self.directory.is_dir():
            return None
        for path in self.directory.iterdir():
            if path.name.startswith(_PARTIAL_PREFIX):
                _warn(f"ignoring {path}: a save that was interrupted before it completed")
        reasons = []
        for directory in sorted(self._step_directories(), key=_step_of, reverse=True):
            try:
                manifest = _read_manifest(directory)
                self._check_compatible(manifest, directory, config_fingerprint)
                _check_sizes(manifest, directory, self.replay_directory)
                state = _load_state(directory / STATE_FILE, manifest.state, map_location)
                _load_arrays(manifest, self.replay_directory, into)
            except _Incomplete as reason:
                reasons.append(f"{directory.name}: {reason}")
                _warn(
                    f"skipping checkpoint {directory}: incomplete or corrupted ({reason}); "
                    "falling back to the previous one"
                )
                continue
            self._base = manifest
            return LoadedCheckpoint(
                step=manifest.step,
                state=state,
                directory=directory,
                manifest=manifest,
                arrays_loaded=into is not None,
            )
        if reasons:
            raise DqnlabError(f"no complete checkpoint in {self.directory}: " + "; ".join(reasons))
        return None

    @staticmethod
    def _check_compatible(manifest: Manifest, directory: Path, fingerprint: str) -> None:
        if manifest.dqnlab_version != __version__:
            raise DqnlabError(
                f"checkpoint {directory} was written by dqnlab {manifest.dqnlab_version} and "
                f"this is dqnlab {__version__}: resume it with dqnlab "
                f"{manifest.dqnlab_version}, or start a new run"
            )
        if manifest.config_fingerprint != fingerprint:
            raise DqnlabError(
                f"checkpoint {directory} was written with another configuration (fingerprint "
                f"{manifest.config_fingerprint[:12]}, this one {fingerprint[:12]}): resume "
                "with the run's own config.toml, or start a new run"
            )

    def _step_directories(self) -> list[Path]:
        if not self.directory.is_dir():
            return []
        return [
            path
            for path in self.directory.iterdir()
            if _STEP_DIR.fullmatch(path.name) and path.is_dir()
        ]


# Files ---------------------------------------------------------------------------------


def _write_buffer(handle: BinaryIO, data: memoryview) -> None:
    """Write `data` to `handle`: the one place checkpoint bytes reach a file."""
    handle.write(data)


def _write_file(path: Path, pieces: Iterable[memoryview], created: list[Path]) -> FileRecord:
    """Write to a temporary name, fsync, rename; never over an existing file."""
    temporary = path.with_name(path.name + ".tmp")
    created.append(temporary)
    crc = 0
    size = 0
    with temporary.open("wb") as handle:
        for piece in pieces:
            crc = zlib.crc32(piece, crc)
            _write_buffer(handle, piece)
            size += piece.nbytes
        handle.flush()
        os.fsync(handle.fileno())
    if path.exists():
        raise FileExistsError(errno.EEXIST, f"checkpoint file {path} exists already")
    os.replace(temporary, path)
    created.append(path)
    return FileRecord(path.name, size, crc)


def _pieces(data: memoryview) -> Iterator[memoryview]:
    """The bytes of `data` (C-contiguous) in pieces of _IO_PIECE_BYTES, without copying."""
    view = data.cast("B")
    for offset in range(0, view.nbytes, _IO_PIECE_BYTES):
        yield view[offset : offset + _IO_PIECE_BYTES]


def _read_verified(path: Path, record: FileRecord, target: memoryview | None = None) -> None:
    """Read `path` into `target` (or a scratch buffer) and check its size and CRC-32."""
    scratch = None if target is not None else memoryview(bytearray(_IO_PIECE_BYTES))
    crc = 0
    offset = 0
    try:
        with path.open("rb", buffering=0) as handle:
            while True:
                if target is not None:
                    window = target[offset : offset + _IO_PIECE_BYTES]
                else:
                    assert scratch is not None
                    window = scratch
                read = handle.readinto(window) if window.nbytes else 0
                if not read:
                    break
                crc = zlib.crc32(window[:read], crc)
                offset += read
                if target is not None and offset == target.nbytes:
                    if handle.read(1):
                        raise _Incomplete(f"{path.name} is longer than recorded")
                    break
    except OSError as error:
        raise _Incomplete(f"{path.name} cannot be read ({error.strerror or error})") from None
    if offset != record.size:
        raise _Incomplete(f"{path.name} has {offset} bytes, the manifest says {record.size}")
    if crc != record.crc32:
        raise _Incomplete(f"{path.name} fails its CRC-32 check")


def _read_manifest(directory: Path) -> Manifest:
    path = directory / MANIFEST_FILE
    try:
        text = path.read_bytes()
    except FileNotFoundError:
        raise _Incomplete(f"no {MANIFEST_FILE}: the save did not complete") from None
    except OSError as error:
        raise _Incomplete(f"{MANIFEST_FILE} cannot be read ({error})") from None
    manifest = Manifest.from_json(text)
    if manifest.step != _step_of(directory):
        raise _Incomplete(f"{MANIFEST_FILE} is for step {manifest.step}")
    return manifest


def _check_sizes(manifest: Manifest, directory: Path, replay_directory: Path) -> None:
    files = [(directory / manifest.state.name, manifest.state)]
    files += [
        (replay_directory / chunk.name, chunk)
        for record in manifest.arrays.values()
        for chunk in record.chunks
    ]
    for path, record in files:
        size = _size_of(path)
        if size is None:
            raise _Incomplete(f"{path.name} is missing")
        if size != record.size:
            raise _Incomplete(f"{path.name} has {size} bytes, the manifest says {record.size}")


def _load_state(path: Path, record: FileRecord, map_location: str | torch.device) -> dict:
    data = bytearray(record.size)
    _read_verified(path, record, memoryview(data))
    try:
        # Never weights_only=False: a matching CRC-32 says the bytes are whole, not that this
        # store wrote them.
        state = torch.load(io.BytesIO(data), map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as error:
        raise _Incomplete(
            f"{path.name} is refused: {_unsafe_reason(error)}; dqnlab writes only tensors and "
            "plain Python values"
        ) from None
    except Exception as error:  # noqa: BLE001 - a file that verifies but will not load
        raise _Incomplete(f"{path.name} cannot be loaded ({error})") from None
    if not isinstance(state, dict):
        raise _Incomplete(f"{path.name} holds a {type(state).__name__}, not a state dict")
    return state


def _check_loadable(state_bytes: memoryview) -> None:
    """Refuse before writing a state that `_load_state` would refuse when resuming."""
    try:
        torch.load(io.BytesIO(state_bytes), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as error:
        raise ValueError(
            f"the checkpoint state cannot be saved: {_unsafe_reason(error)}; store arrays as "
            "tensors and numbers as Python numbers"
        ) from None


def _unsafe_reason(error: pickle.UnpicklingError) -> str:
    """The part of torch's weights-only error that names what was refused."""
    message = str(error)
    refused = re.search(r"Unsupported global: GLOBAL (\S+)", message)
    if refused:
        return f"it holds {refused.group(1)}, outside torch's weights-only types"
    detail = re.search(r"WeightsUnpickler error: ([^\n]+)", message)
    return f"torch's weights-only unpickler refuses it ({detail.group(1) if detail else message})"


def _load_arrays(
    manifest: Manifest, replay_directory: Path, into: Mapping[str, np.ndarray] | None
) -> None:
    if into is not None:
        expected = set(manifest.arrays)
        if set(into) != expected:
            raise DqnlabError(
                f"the checkpoint holds the arrays {sorted(expected)}, not {sorted(into)}"
            )
    for name, record in manifest.arrays.items():
        target = None
        if into is not None:
            target = into[name]
            if target.dtype.str != record.dtype or tuple(target.shape) != record.shape:
                raise DqnlabError(
                    f"the checkpoint's {name} is {record.dtype} {record.shape}, "
                    f"the memory to load it into is {target.dtype.str} {tuple(target.shape)}"
                )
            if not target.flags.c_contiguous or not target.flags.writeable:
                raise ValueError(f"{name} must be a writeable C-contiguous array")
        for index, chunk in enumerate(record.chunks):
            start, stop = record.chunk_span(index)
            view = target[start:stop].data.cast("B") if target is not None else None
            _read_verified(replay_directory / chunk.name, chunk, view)


def _check_arrays(arrays: Mapping[str, np.ndarray]) -> int:
    capacities = {array.shape[0] if array.ndim else 0 for array in arrays.values()}
    if len(capacities) > 1 or 0 in capacities:
        raise ValueError(f"replay arrays must share a non-zero first dimension, not {capacities}")
    for name, array in arrays.items():
        if not _ARRAY_NAME.fullmatch(name):
            raise ValueError(f"array name {name!r} must be letters, digits and underscores")
        if not array.flags.c_contiguous:
            raise ValueError(f"array {name} must be C-contiguous")
    return capacities.pop() if capacities else 0


def _changed_chunks(
    changed_slots: tuple[int, int] | None, capacity: int, chunk_slots: int
) -> set[int] | None:
    """The chunk indices holding the ring range [start, stop); None for every chunk."""
    if changed_slots is None:
        return None
    start, stop = changed_slots
    if not (0 <= start < capacity and 0 <= stop <= capacity):
        raise ValueError(f"changed_slots {changed_slots} is outside a capacity of {capacity}")
    spans = [(start, stop)] if start <= stop else [(start, capacity), (0, stop)]
    chunks: set[int] = set()
    for low, high in spans:
        if low < high:
            chunks.update(range(low // chunk_slots, (high - 1) // chunk_slots + 1))
    return chunks


def _step_of(directory: Path) -> int:
    match = _STEP_DIR.fullmatch(directory.name)
    assert match is not None
    return int(match.group(1))


def _size_of(path: Path) -> int | None:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return None


def _fsync_directory(directory: Path) -> None:
    """Make renames and deletions in `directory` durable."""
    descriptor = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def _remove(path: Path) -> None:
    # Cleaning up after a failure: the original error is the one to report.
    with contextlib.suppress(OSError):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)


def _warn(message: str) -> None:
    warnings.warn(message, CheckpointWarning, stacklevel=3)
