"""The files of a training checkpoint: the manifest's records, and reading and writing
files whole, checksummed, fsynced and renamed into place (`checkpoints.CheckpointStore`
decides what to write and what to load)."""

from __future__ import annotations

import contextlib
import errno
import io
import json
import os
import pickle
import re
import shutil
import zlib
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Protocol, runtime_checkable

import numpy as np
import torch

from dqnlab.algorithm.compression import RAW, decode_chunk
from dqnlab.algorithm.streams import WrittenSlots
from dqnlab.errors import DqnlabError

# Format 2 may leave a replay chunk out (null: never written, zeros) or cut a raw one short
# (`slots`); format 1 wrote every chunk whole and is read as it is.
STORE_FORMAT = "dqnlab-training-checkpoint-2"
READ_FORMATS = ("dqnlab-training-checkpoint-1", STORE_FORMAT)
MANIFEST_FILE = "MANIFEST.json"
IO_PIECE_BYTES = 16 * 2**20  # checksum and write in pieces: no copy of a whole chunk
STEP_DIR = re.compile(r"step-(\d{9,})")
_ARRAY_NAME = re.compile(r"[A-Za-z0-9_]+")


class Incomplete(Exception):
    """A checkpoint is incomplete or corrupted; the message is the reason."""


@runtime_checkable
class ChunkedArray(Protocol):
    """An array held chunk by chunk in its own encoding (the compressed replay frames):
    a checkpoint writes each chunk's bytes as they are and hands them back to load."""

    shape: tuple[int, ...]
    dtype: np.dtype
    chunk_slots: int

    def chunk_encoding(self, index: int) -> str: ...

    def chunk_nbytes(self, index: int) -> int: ...

    def chunk_pieces(self, index: int) -> Iterator[memoryview]: ...

    def load_chunk(self, index: int, encoding: str, data: memoryview) -> None: ...

    def clear_chunk(self, index: int) -> None: ...


Arrays = Mapping[str, "np.ndarray | ChunkedArray"]


@dataclass(frozen=True)
class FileRecord:
    name: str
    size: int
    crc32: int
    encoding: str = RAW  # of a replay chunk: raw bytes, or a codec's (`compression`)
    # Of a raw replay chunk cut short: it holds its first `slots` slots, the rest are zeros
    # (never written). None: the whole chunk.
    slots: int | None = None

    def to_json(self) -> dict[str, Any]:
        body: dict[str, Any] = {"file": self.name, "size": self.size, "crc32": f"{self.crc32:08x}"}
        if self.encoding != RAW:
            body["encoding"] = self.encoding
        if self.slots is not None:
            body["slots"] = self.slots
        return body

    @staticmethod
    def from_json(data: Mapping[str, Any]) -> FileRecord:
        return FileRecord(
            str(data["file"]),
            int(data["size"]),
            int(data["crc32"], 16),
            str(data.get("encoding", RAW)),
            None if data.get("slots") is None else int(data["slots"]),
        )


@dataclass(frozen=True)
class ArrayRecord:
    dtype: str  # numpy dtype.str, e.g. "|u1"
    shape: tuple[int, ...]
    chunk_slots: int
    # None: a chunk never written since the replay was made, all zeros: not stored.
    chunks: tuple[FileRecord | None, ...]

    def chunk_span(self, index: int) -> tuple[int, int]:
        start = index * self.chunk_slots
        return start, min(start + self.chunk_slots, self.shape[0])

    def stored_slots(self, index: int) -> int:
        """How many of chunk `index`'s first slots its file holds (the rest are zeros)."""
        chunk = self.chunks[index]
        start, stop = self.chunk_span(index)
        if chunk is None:
            return 0
        return stop - start if chunk.slots is None else chunk.slots


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
                    "chunks": [
                        None if chunk is None else chunk.to_json() for chunk in record.chunks
                    ],
                }
                for name, record in self.arrays.items()
            },
        }
        # The manifest checks itself too: a flipped digit in a step or size is caught.
        body["manifest_crc32"] = f"{zlib.crc32(canonical(body)):08x}"
        return json.dumps(body, indent=1).encode()

    @staticmethod
    def from_json(text: bytes) -> Manifest:
        try:
            body = json.loads(text)
            recorded = int(body.pop("manifest_crc32"), 16)
            if zlib.crc32(canonical(body)) != recorded:
                raise Incomplete(f"{MANIFEST_FILE} fails its own checksum")
            if body["format"] not in READ_FORMATS:
                raise Incomplete(f"{MANIFEST_FILE} has format {body['format']!r}")
            arrays = {
                name: ArrayRecord(
                    dtype=str(record["dtype"]),
                    shape=tuple(int(n) for n in record["shape"]),
                    chunk_slots=int(record["chunk_slots"]),
                    chunks=tuple(
                        None if chunk is None else FileRecord.from_json(chunk)
                        for chunk in record["chunks"]
                    ),
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
            raise Incomplete(f"{MANIFEST_FILE} is unreadable ({error!r})") from None


def canonical(body: Mapping[str, Any]) -> bytes:
    return json.dumps(body, sort_keys=True, separators=(",", ":")).encode()


# Files ---------------------------------------------------------------------------------


def write_buffer(handle: BinaryIO, data: memoryview) -> None:
    """Write `data` to `handle`: the one place checkpoint bytes reach a file."""
    handle.write(data)


def write_file(
    path: Path, pieces: Iterable[memoryview], created: list[Path], encoding: str = RAW
) -> FileRecord:
    """Write to a temporary name, fsync, rename; never over an existing file."""
    temporary = path.with_name(path.name + ".tmp")
    created.append(temporary)
    crc = 0
    size = 0
    with temporary.open("wb") as handle:
        for piece in pieces:
            crc = zlib.crc32(piece, crc)
            write_buffer(handle, piece)
            size += piece.nbytes
        handle.flush()
        os.fsync(handle.fileno())
    if path.exists():
        raise FileExistsError(errno.EEXIST, f"checkpoint file {path} exists already")
    os.replace(temporary, path)
    created.append(path)
    return FileRecord(path.name, size, crc, encoding)


def pieces_of(data: memoryview) -> Iterator[memoryview]:
    """The bytes of `data` (C-contiguous) in pieces of IO_PIECE_BYTES, without copying."""
    view = data.cast("B")
    for offset in range(0, view.nbytes, IO_PIECE_BYTES):
        yield view[offset : offset + IO_PIECE_BYTES]


def read_verified(path: Path, record: FileRecord, target: memoryview | None = None) -> None:
    """Read `path` into `target` (or a scratch buffer) and check its size and CRC-32."""
    scratch = None if target is not None else memoryview(bytearray(IO_PIECE_BYTES))
    crc = 0
    offset = 0
    try:
        with path.open("rb", buffering=0) as handle:
            while True:
                if target is not None:
                    window = target[offset : offset + IO_PIECE_BYTES]
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
                        raise Incomplete(f"{path.name} is longer than recorded")
                    break
    except OSError as error:
        raise Incomplete(f"{path.name} cannot be read ({error.strerror or error})") from None
    if offset != record.size:
        raise Incomplete(f"{path.name} has {offset} bytes, the manifest says {record.size}")
    if crc != record.crc32:
        raise Incomplete(f"{path.name} fails its CRC-32 check")


def read_manifest(directory: Path) -> Manifest:
    path = directory / MANIFEST_FILE
    try:
        text = path.read_bytes()
    except FileNotFoundError:
        raise Incomplete(f"no {MANIFEST_FILE}: the save did not complete") from None
    except OSError as error:
        raise Incomplete(f"{MANIFEST_FILE} cannot be read ({error})") from None
    manifest = Manifest.from_json(text)
    if manifest.step != step_of(directory):
        raise Incomplete(f"{MANIFEST_FILE} is for step {manifest.step}")
    return manifest


def check_sizes(manifest: Manifest, directory: Path, replay_directory: Path) -> None:
    files = [(directory / manifest.state.name, manifest.state)]
    files += [
        (replay_directory / chunk.name, chunk)
        for record in manifest.arrays.values()
        for chunk in record.chunks
        if chunk is not None
    ]
    for path, record in files:
        size = size_of(path)
        if size is None:
            raise Incomplete(f"{path.name} is missing")
        if size != record.size:
            raise Incomplete(f"{path.name} has {size} bytes, the manifest says {record.size}")


def load_state(path: Path, record: FileRecord, map_location: str | torch.device) -> dict:
    data = bytearray(record.size)
    read_verified(path, record, memoryview(data))
    try:
        # Never weights_only=False: a matching CRC-32 says the bytes are whole, not that this
        # store wrote them.
        state = torch.load(io.BytesIO(data), map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as error:
        raise Incomplete(
            f"{path.name} is refused: {_unsafe_reason(error)}; dqnlab writes only tensors and "
            "plain Python values"
        ) from None
    except Exception as error:  # noqa: BLE001 - a file that verifies but will not load
        raise Incomplete(f"{path.name} cannot be loaded ({error})") from None
    if not isinstance(state, dict):
        raise Incomplete(f"{path.name} holds a {type(state).__name__}, not a state dict")
    return state


def check_loadable(state_bytes: memoryview) -> None:
    """Refuse before writing a state that `load_state` would refuse when resuming."""
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


def load_arrays(manifest: Manifest, replay_directory: Path, into: Arrays | None) -> None:
    """Read every chunk, verifying its CRC-32, into `into` (None: verify only). A raw array
    is filled in place (a compressed chunk decompressed into it); a `ChunkedArray` gets
    each chunk's bytes as stored. Slots no file holds (a chunk left out, or past the end of
    one cut short) are set to zeros, as the saved replay held them."""
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
            if isinstance(target, ChunkedArray):
                if target.chunk_slots != record.chunk_slots:
                    raise DqnlabError(
                        f"the checkpoint's {name} is in chunks of {record.chunk_slots} slots, "
                        f"the memory to load it into in chunks of {target.chunk_slots}"
                    )
            elif not target.flags.c_contiguous or not target.flags.writeable:
                raise ValueError(f"{name} must be a writeable C-contiguous array")
        for index, chunk in enumerate(record.chunks):
            _load_chunk(record, index, chunk, replay_directory, target)


def _load_chunk(
    record: ArrayRecord,
    index: int,
    chunk: FileRecord | None,
    replay_directory: Path,
    target: np.ndarray | ChunkedArray | None,
) -> None:
    start, stop = record.chunk_span(index)
    stored = record.stored_slots(index)
    if chunk is not None and (
        not 0 < stored <= stop - start or (chunk.slots is not None and chunk.encoding != RAW)
    ):
        raise Incomplete(f"{chunk.name} is recorded as {stored} slots of a chunk of {stop - start}")
    if chunk is None:
        if isinstance(target, ChunkedArray):
            target.clear_chunk(index)
        elif target is not None:
            zero_unless_zero(target[start:stop])
        return
    path = replay_directory / chunk.name
    if target is None:
        read_verified(path, chunk)
    elif isinstance(target, ChunkedArray) or chunk.encoding != RAW:
        # A chunk cut short is raw: its stored slots, then zeros, make the whole chunk.
        whole = stored == stop - start
        row_bytes = int(np.prod(record.shape[1:], dtype=np.int64)) * np.dtype(record.dtype).itemsize
        data = memoryview(bytearray(chunk.size if whole else (stop - start) * row_bytes))
        read_verified(path, chunk, data if whole else data[: chunk.size])
        try:
            if isinstance(target, ChunkedArray):
                target.load_chunk(index, chunk.encoding, data)
            else:
                decode_chunk(chunk.encoding, data, target[start:stop])
        except ValueError as error:
            raise Incomplete(f"{chunk.name} cannot be decoded ({error})") from None
    else:
        read_verified(path, chunk, target[start : start + stored].data.cast("B"))
        zero_unless_zero(target[start + stored : stop])


def zero_unless_zero(array: np.ndarray) -> None:
    """Set `array` (C-contiguous) to zeros, reading it first: memory never written (a fresh
    replay's) is left unwritten, so it stays unallocated."""
    flat = array.reshape(-1).view(np.uint8)
    whole_words = flat.nbytes // 8 * 8
    if flat[:whole_words].view(np.uint64).any() or flat[whole_words:].any():
        array[...] = 0


def chunk_slots_of(array: np.ndarray | ChunkedArray, default: int) -> int:
    return array.chunk_slots if isinstance(array, ChunkedArray) else default


def chunk_pieces(
    array: np.ndarray | ChunkedArray, index: int, start: int, stop: int
) -> tuple[str, int, Iterator[memoryview]]:
    """Chunk `index` (slots [start, stop)) of `array`: its encoding, size and bytes."""
    if isinstance(array, ChunkedArray):
        return array.chunk_encoding(index), array.chunk_nbytes(index), array.chunk_pieces(index)
    return RAW, array[start:stop].nbytes, pieces_of(array[start:stop].data)


def check_arrays(arrays: Arrays) -> int:
    capacities = {array.shape[0] if len(array.shape) else 0 for array in arrays.values()}
    if len(capacities) > 1 or 0 in capacities:
        raise ValueError(f"replay arrays must share a non-zero first dimension, not {capacities}")
    for name, array in arrays.items():
        if not _ARRAY_NAME.fullmatch(name):
            raise ValueError(f"array name {name!r} must be letters, digits and underscores")
        if not isinstance(array, ChunkedArray) and not array.flags.c_contiguous:
            raise ValueError(f"array {name} must be C-contiguous")
    return capacities.pop() if capacities else 0


def changed_chunks(changed_slots: WrittenSlots, capacity: int, chunk_slots: int) -> set[int] | None:
    """The chunk indices holding the ring range [start, stop); None for every chunk."""
    extents = changed_extents(changed_slots, capacity, chunk_slots)
    return None if extents is None else set(extents)


def changed_extents(
    changed_slots: WrittenSlots, capacity: int, chunk_slots: int
) -> dict[int, int] | None:
    """Per chunk holding a slot of the ring range [start, stop) (or of a list of them, one
    per replay stream): the number of its first slots that reach its last slot in the
    range; None for every chunk, whole."""
    if changed_slots is None:
        return None
    extents: dict[int, int] = {}
    for start, stop in [changed_slots] if isinstance(changed_slots, tuple) else changed_slots:
        if not (0 <= start < capacity and 0 <= stop <= capacity):
            raise ValueError(f"changed slots {start, stop} are outside a capacity of {capacity}")
        spans = [(start, stop)] if start <= stop else [(start, capacity), (0, stop)]
        for low, high in spans:
            first, last = low // chunk_slots, (high - 1) // chunk_slots
            for index in range(first, last + 1) if low < high else ():
                end = min(high, (index + 1) * chunk_slots) - index * chunk_slots
                extents[index] = max(extents.get(index, 0), end)
    return extents


def step_of(directory: Path) -> int:
    match = STEP_DIR.fullmatch(directory.name)
    assert match is not None
    return int(match.group(1))


def size_of(path: Path) -> int | None:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return None


def fsync_directory(directory: Path) -> None:
    """Make renames and deletions in `directory` durable."""
    descriptor = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def remove_quietly(path: Path) -> None:
    # Cleaning up after a failure: the original error is the one to report.
    with contextlib.suppress(OSError):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink(missing_ok=True)
