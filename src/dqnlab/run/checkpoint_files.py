"""The bytes of a training checkpoint on disk: files written whole (checksummed, fsynced,
renamed into place, never over another), read back with their size and CRC-32 verified,
and state.pt read with torch's weights-only unpickler (`checkpoints` has the layout)."""

from __future__ import annotations

import contextlib
import errno
import io
import os
import pickle
import re
import shutil
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

import torch

from dqnlab.algorithm.compression import RAW
from dqnlab.run.checkpoint_manifest import FileRecord, Incomplete, Manifest

IO_PIECE_BYTES = 16 * 2**20  # checksum and write in pieces: no copy of a whole chunk


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
