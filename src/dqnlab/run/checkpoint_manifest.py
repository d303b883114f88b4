"""What a training checkpoint records: MANIFEST.json, the size and CRC-32 of state.pt and of
every replay chunk file the checkpoint needs, and the step directory it names
(`checkpoints` has the layout; `checkpoint_files` writes and verifies the files)."""

from __future__ import annotations

import json
import re
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dqnlab.algorithm.compression import RAW

# Format 2 may leave a replay chunk out (null: never written, zeros) or cut a raw one short
# (`slots`); format 1 wrote every chunk whole and is read as it is.
STORE_FORMAT = "dqnlab-training-checkpoint-2"
READ_FORMATS = ("dqnlab-training-checkpoint-1", STORE_FORMAT)
MANIFEST_FILE = "MANIFEST.json"
STEP_DIR = re.compile(r"step-(\d{9,})")


class Incomplete(Exception):
    """A checkpoint is incomplete or corrupted; the message is the reason."""


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


def step_of(directory: Path) -> int:
    match = STEP_DIR.fullmatch(directory.name)
    assert match is not None
    return int(match.group(1))
