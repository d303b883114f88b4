"""The replay arrays in a checkpoint, as chunks: which slots changed since the last save,
which chunks to write and which earlier files to reuse (`plan`), writing them (`write`) and
reading them back verified into the preallocated arrays (`load_arrays`). Slots never written
are zeros and are not stored."""

from __future__ import annotations

import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol, TypeAlias, runtime_checkable

import numpy as np

from dqnlab.algorithm.compression import RAW, decode_chunk
from dqnlab.algorithm.streams import WrittenSlots
from dqnlab.errors import DqnlabError
from dqnlab.run.checkpoint_files import (
    fsync_directory,
    pieces_of,
    read_verified,
    size_of,
    write_file,
)
from dqnlab.run.checkpoint_manifest import ArrayRecord, FileRecord, Incomplete, Manifest

_ARRAY_NAME = re.compile(r"[A-Za-z0-9_]+")
CHUNK_FILE = re.compile(r"([A-Za-z0-9_]+)\.(\d{5,})\.g(\d{9,})\.bin(\.tmp)?")


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
class PlannedChunk:
    """Slots [start, stop) of a replay array: store its first `slots` (0: none, zeros), in
    the earlier file `reused` or in a new one (None)."""

    start: int
    stop: int
    slots: int
    reused: FileRecord | None


Plan: TypeAlias = "dict[str, list[PlannedChunk]]"  # per replay array, per chunk


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


def plan(
    arrays: Arrays,
    changed_slots: WrittenSlots,
    base: Manifest | None,
    replay_directory: Path,
    chunk_slots: int,
) -> Plan:
    """Per array, per chunk: the slots to store and the file of `base` (the checkpoint last
    saved or loaded; None: none) to reuse.

    Only slots that may hold something other than zeros are stored: those the earlier
    checkpoint stored and those written since. With no earlier checkpoint, the save
    stores the slots written since the replay was made (zeros) and leaves the rest out: a
    run's first checkpoint holds the filled part. A raw chunk is cut after its last such
    slot; a `ChunkedArray`'s is stored whole (its zeros compress to nearly nothing). A file
    is reused when no slot of its chunk changed and it has the chunk's current encoding (a
    chunk compressed since is written again, compressed)."""
    capacity = check_arrays(arrays)
    return {
        name: _plan_array(
            array,
            changed_extents(changed_slots, capacity, chunk_slots_of(array, chunk_slots)),
            base,
            base.arrays.get(name) if base is not None else None,
            replay_directory,
            chunk_slots_of(array, chunk_slots),
        )
        for name, array in arrays.items()
    }


def _plan_array(
    array: np.ndarray | ChunkedArray,
    extents: dict[int, int] | None,
    base: Manifest | None,
    record: ArrayRecord | None,
    replay_directory: Path,
    chunk_slots: int,
) -> list[PlannedChunk]:
    layout = (array.dtype.str, tuple(array.shape), chunk_slots)
    if record is not None and (record.dtype, record.shape, record.chunk_slots) != layout:
        record = None
    # Every chunk whole: all slots changed, or the earlier checkpoint has no record of this
    # array to tell which slots are zeros.
    whole = extents is None or (base is not None and record is None)
    chunks: list[PlannedChunk] = []
    for index, start in enumerate(range(0, array.shape[0], chunk_slots)):
        stop = min(start + chunk_slots, array.shape[0])
        if whole or extents is None:
            chunks.append(PlannedChunk(start, stop, stop - start, None))
            continue
        stored = record.stored_slots(index) if record is not None else 0
        slots = max(stored, extents.get(index, 0))
        if slots and isinstance(array, ChunkedArray):
            slots = stop - start
        reused = None
        earlier = record.chunks[index] if record is not None else None
        if slots and earlier is not None and index not in extents:
            encoding = chunk_pieces(array, index, start, stop)[0]
            # Reuse only a file that is still there, whole: else write it again.
            if (
                earlier.encoding == encoding
                and stored == slots
                and size_of(replay_directory / earlier.name) == earlier.size
            ):
                reused = earlier
        chunks.append(PlannedChunk(start, stop, slots, reused))
    return chunks


def bytes_to_write(arrays: Arrays, planned: Plan) -> int:
    """The size of the chunk files a save of `planned` writes (those it does not reuse)."""
    return sum(
        chunk_pieces(arrays[name], index, chunk.start, chunk.start + chunk.slots)[1]
        for name, chunks in planned.items()
        for index, chunk in enumerate(chunks)
        if chunk.slots and chunk.reused is None
    )


def write(
    arrays: Arrays,
    planned: Plan,
    generation: int,
    replay_directory: Path,
    created: list[Path],
    chunk_slots: int,
) -> dict[str, ArrayRecord]:
    """Write the planned chunks not reused, as files of save number `generation`; append
    every path made to `created`; return each array's record."""
    records = {
        name: ArrayRecord(
            dtype=arrays[name].dtype.str,
            shape=tuple(arrays[name].shape),
            chunk_slots=chunk_slots_of(arrays[name], chunk_slots),
            chunks=tuple(
                _write_chunk(
                    arrays[name], name, index, chunk, generation, replay_directory, created
                )
                for index, chunk in enumerate(chunks)
            ),
        )
        for name, chunks in planned.items()
    }
    fsync_directory(replay_directory)
    return records


def _write_chunk(
    array: np.ndarray | ChunkedArray,
    name: str,
    index: int,
    chunk: PlannedChunk,
    generation: int,
    replay_directory: Path,
    created: list[Path],
) -> FileRecord | None:
    """The record of a planned chunk: none (zeros), the earlier file, or a new one."""
    if not chunk.slots or chunk.reused is not None:
        return chunk.reused if chunk.slots else None
    encoding, _, pieces = chunk_pieces(array, index, chunk.start, chunk.start + chunk.slots)
    path = replay_directory / f"{name}.{index:05d}.g{generation:09d}.bin"
    record = write_file(path, pieces, created, encoding)
    if chunk.slots < chunk.stop - chunk.start:
        record = replace(record, slots=chunk.slots)
    return record


def generation_of(path: Path) -> int | None:
    """The save number in a chunk file's name; None for another file."""
    match = CHUNK_FILE.fullmatch(path.name)
    return int(match.group(3)) if match else None


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
