"""Compressed replay frames (`replay_compression`): the frames of a replay memory, kept
compressed except for the chunk being written.

The slots are cut into chunks of `chunk_slots` (16,384, the checkpoint's chunk), and each
chunk into blocks of `block_slots` consecutive frames, compressed one block at a time so
that a minibatch decompresses only the blocks its windows touch. A chunk is compressed
once its last slot is written (it cannot change until the ring comes back to it) and
decompressed whole when the ring does: one chunk's worth of work every 16k steps, on the
acting thread, so that the frames and the order of everything stay deterministic.
Consecutive frames of a game differ little, so a block of four compresses far better than
four single frames; a window of history + 1 = 5 slots always touches exactly two blocks.
The codec was chosen by measurement (docs/benchmark.md, "Compressed replay"): LZ4 decompresses a
minibatch's blocks faster than zstd does at compression ratios well past the target.

A chunk's compressed form is what a checkpoint writes and reads back, byte for byte: the
block offsets (int64, one more than there are blocks) followed by the compressed blocks.
"""

from __future__ import annotations

import csv
import functools
import time
from collections.abc import Iterator
from dataclasses import dataclass
from importlib import resources

import lz4.block
import numpy as np
import torch

from dqnlab.config import CHOICES
from dqnlab.errors import ConfigError

CODECS = CHOICES["replay_compression"]
RAW = "raw"  # a chunk's encoding when stored as plain bytes
CHUNK_SLOTS = 16_384
BLOCK_SLOTS = 4
# How much larger than measured (under the random policy) a game's compressed frames may
# turn out in a run before the start-up memory check is wrong: frames of later, trained
# play show more objects on screen. `ReplayMemory` checks the real size as it fills.
MEASURED_SIZE_MARGIN = 2.0
MEASURED_FILE = "replay_compression.csv"


@functools.cache
def measured_frame_bytes() -> dict[str, float]:
    """Compressed bytes per frame of each Atari game, as the compression scan measured them
    (data/replay_compression.csv; `python scripts/compression_scan.py`, once
    `dqnlab bench --compression-scan`)."""
    path = resources.files("dqnlab") / "data" / MEASURED_FILE
    if not path.is_file():
        return {}
    with path.open() as handle:
        rows = [row for row in csv.DictReader(line for line in handle if not line.startswith("#"))]
    return {row["game"]: float(row["lz4_bytes_per_frame"]) for row in rows}


def expected_frame_bytes(codec: str, env: str) -> float | None:
    """The compressed size of one frame of `env` that a memory check may count on: the
    measured one with `MEASURED_SIZE_MARGIN`, or None (unknown: count the raw size)."""
    if codec == "none" or env not in measured_frame_bytes():
        return None
    return MEASURED_SIZE_MARGIN * measured_frame_bytes()[env]


def check_codec(codec: str) -> None:
    if codec not in CODECS or codec == "none":
        raise ConfigError(
            f"replay_compression = {codec!r} is not a codec; accepted: "
            f"{', '.join(c for c in CODECS if c != 'none')}"
        )


@dataclass(frozen=True)
class PackedChunk:
    """A chunk's blocks, compressed: block b is payload[offsets[b]:offsets[b + 1]]."""

    offsets: np.ndarray  # int64, blocks + 1
    payload: memoryview

    @property
    def nbytes(self) -> int:
        return self.offsets.nbytes + self.payload.nbytes

    def pieces(self) -> Iterator[memoryview]:
        """The bytes a checkpoint stores: offsets, then blocks."""
        yield self.offsets.data.cast("B")
        yield self.payload

    @staticmethod
    def from_bytes(data: memoryview, blocks: int) -> PackedChunk:
        """Read back what `pieces` wrote (kept without a copy); checks the offsets."""
        data = data.cast("B")
        header = (blocks + 1) * 8
        if data.nbytes < header:
            raise ValueError(f"{data.nbytes} bytes cannot hold the offsets of {blocks} blocks")
        offsets = np.frombuffer(data[:header], dtype="<i8").astype(np.int64)
        payload = data[header:]
        if offsets[0] != 0 or offsets[-1] != payload.nbytes or np.any(np.diff(offsets) <= 0):
            raise ValueError("its block offsets do not match its payload")
        return PackedChunk(offsets, payload)


def pack(codec: str, frames: np.ndarray, block_slots: int = BLOCK_SLOTS) -> PackedChunk:
    """Compress `frames` (slots first) in blocks of `block_slots` slots."""
    check_codec(codec)
    blocks = [
        lz4.block.compress(frames[begin : begin + block_slots], store_size=False)
        for begin in range(0, len(frames), block_slots)
    ]
    offsets = np.zeros(len(blocks) + 1, dtype=np.int64)
    np.cumsum([len(block) for block in blocks], out=offsets[1:])
    return PackedChunk(offsets, memoryview(b"".join(blocks)))


def unpack_block(codec: str, packed: PackedChunk, block: int, out: np.ndarray) -> None:
    """Decompress block `block` into `out` (C-contiguous, exactly the block's bytes)."""
    data = lz4.block.decompress(
        packed.payload[packed.offsets[block] : packed.offsets[block + 1]],
        uncompressed_size=out.nbytes,
    )
    if len(data) != out.nbytes:
        raise ValueError(f"a compressed block holds {len(data)} bytes, not {out.nbytes}")
    out.reshape(-1)[...] = np.frombuffer(data, dtype=out.dtype)


def unpack(
    codec: str, packed: PackedChunk, out: np.ndarray, block_slots: int = BLOCK_SLOTS
) -> None:
    """Decompress a whole chunk into `out` (its slots first)."""
    for block, begin in enumerate(range(0, len(out), block_slots)):
        unpack_block(codec, packed, block, out[begin : begin + block_slots])


def decode_chunk(encoding: str, data: memoryview, out: np.ndarray) -> None:
    """Decompress a stored chunk into the raw array `out`: a replay without compression
    resuming from a checkpoint that had it."""
    if encoding not in CODECS or encoding == "none":
        raise ValueError(f"unknown chunk encoding {encoding!r}")
    blocks = -(-len(out) // BLOCK_SLOTS)
    unpack(encoding, PackedChunk.from_bytes(data, blocks), out)


class CompressedFrames:
    """`capacity` frames of `frame_shape`, written one slot at a time and read by slot
    numbers; every chunk but the one being written is compressed with `codec`.

    Before anything is written, every chunk holds zeros (one shared compressed chunk), as a
    raw replay's zero-filled array does, so that reads are identical to it everywhere.
    `open_chunks` chunks may be raw at once (a replay of several streams writes one chunk
    per stream); opening one more compresses the one written longest ago.
    """

    def __init__(
        self,
        capacity: int,
        frame_shape: tuple[int, ...],
        dtype: np.dtype | type,
        codec: str = "lz4",
        chunk_slots: int = CHUNK_SLOTS,
        block_slots: int = BLOCK_SLOTS,
        open_chunks: int = 1,
    ) -> None:
        check_codec(codec)
        if chunk_slots % block_slots:
            raise ValueError(f"chunk_slots {chunk_slots} is not a multiple of {block_slots}")
        self.codec = codec
        self.capacity = capacity
        self.frame_shape = tuple(frame_shape)
        self.dtype = np.dtype(dtype)
        self.shape = (capacity, *self.frame_shape)
        self.chunk_slots = chunk_slots
        self.block_slots = block_slots
        self.frame_bytes = int(np.prod(frame_shape)) * self.dtype.itemsize
        self.chunks = -(-capacity // chunk_slots)
        self._packed: list[PackedChunk | None] = [None] * self.chunks
        # The chunks being written, raw, by index, the one written longest ago first; their
        # buffers are reused for the next ones.
        self._open: dict[int, np.ndarray] = {}
        self._free = [
            np.zeros((chunk_slots, *frame_shape), dtype=self.dtype) for _ in range(open_chunks)
        ]
        # Zeros compressed once per chunk length (the last chunk may be shorter), shared.
        self._zeros: dict[int, PackedChunk] = {}
        for index in range(self.chunks):
            start, stop = self.chunk_span(index)
            slots = stop - start
            if slots not in self._zeros:
                self._zeros[slots] = pack(codec, self._free[0][:slots], block_slots)
            self._packed[index] = self._zeros[slots]
        self._scratch = np.empty((0, block_slots, *frame_shape), self.dtype)
        # Time spent compressing full chunks and decompressing reopened ones (the
        # benchmark's cost per step), and what was compressed.
        self.chunk_seconds = 0.0
        self.sealed_slots = 0
        self.sealed_bytes = 0
        self.last_sealed_slots, self.last_sealed_bytes = 0, 0

    # Layout ---------------------------------------------------------------------------

    def chunk_span(self, index: int) -> tuple[int, int]:
        start = index * self.chunk_slots
        return start, min(start + self.chunk_slots, self.capacity)

    def chunk_encoding(self, index: int) -> str:
        return self.codec

    def chunk_pieces(self, index: int) -> Iterator[memoryview]:
        """The compressed bytes of chunk `index`, as held (the chunk being written is
        compressed for the occasion): a checkpoint writes them as they are."""
        if index in self._open:
            start, stop = self.chunk_span(index)
            frames = self._open[index][: stop - start]
            yield from pack(self.codec, frames, self.block_slots).pieces()
        else:
            packed = self._packed[index]
            assert packed is not None
            yield from packed.pieces()

    def chunk_nbytes(self, index: int) -> int:
        """At most the bytes `chunk_pieces` yields, for a free-space check: the chunk being
        written counts above LZ4's worst case (raw + raw/255 + 16 per block) with its
        offsets (8 per block)."""
        if index in self._open:
            start, stop = self.chunk_span(index)
            raw = (stop - start) * self.frame_bytes
            return raw + raw // 128 + 64 * -(-(stop - start) // self.block_slots)
        packed = self._packed[index]
        assert packed is not None
        return packed.nbytes

    @property
    def resident_bytes(self) -> int:
        """Bytes held: the compressed chunks (the shared zero chunk once) and the raw one."""
        seen: set[int] = set()
        total = sum(buffer.nbytes for buffer in (*self._open.values(), *self._free))
        for packed in self._packed:
            if packed is not None and id(packed) not in seen:
                seen.add(id(packed))
                total += packed.nbytes
        return total

    # Writing --------------------------------------------------------------------------

    def write(self, slot: int, frame: np.ndarray) -> np.ndarray:
        """Store `frame` in `slot`; return the stored row (a view, until the next write)."""
        index = slot // self.chunk_slots
        buffer = self._open.get(index)
        if buffer is None:
            buffer = self._reopen(index)
        elif len(self._open) > 1:  # now the one written last
            self._open[index] = self._open.pop(index)
        start, stop = self.chunk_span(index)
        row = buffer[slot - start]
        row[...] = frame
        if slot == stop - 1:  # the chunk is full: it cannot change until the ring returns
            self._seal(index)
        return row

    def _reopen(self, index: int) -> np.ndarray:
        if not self._free:
            self._seal(next(iter(self._open)))  # the one written longest ago
        buffer = self._free.pop()
        packed = self._packed[index]
        assert packed is not None
        start, stop = self.chunk_span(index)
        began = time.perf_counter()
        unpack(self.codec, packed, buffer[: stop - start], self.block_slots)
        self.chunk_seconds += time.perf_counter() - began
        self._packed[index] = None
        self._open[index] = buffer
        return buffer

    def _seal(self, index: int) -> None:
        buffer = self._open.pop(index)
        start, stop = self.chunk_span(index)
        began = time.perf_counter()
        packed = pack(self.codec, buffer[: stop - start], self.block_slots)
        self.chunk_seconds += time.perf_counter() - began
        self.sealed_slots += stop - start
        self.sealed_bytes += packed.nbytes
        self.last_sealed_slots, self.last_sealed_bytes = stop - start, packed.nbytes
        self._packed[index] = packed
        self._free.append(buffer)

    # Reading --------------------------------------------------------------------------

    def gather(self, slots: np.ndarray, out: np.ndarray) -> None:
        """out[i] = frame of slots[i] (int64): each block that the slots touch is
        decompressed once (or copied, in the raw chunk) and the frames picked from them."""
        blocks, inverse = np.unique(slots // self.block_slots, return_inverse=True)
        if len(self._scratch) < len(blocks):  # grows to a minibatch's blocks, then reused
            self._scratch = np.empty((len(blocks), self.block_slots, *self.frame_shape), self.dtype)
        scratch = self._scratch
        scratch_bytes = scratch.data.cast("B")
        block_bytes = self.block_slots * self.frame_bytes
        chunk_of, local_of = np.divmod(blocks, self.chunk_slots // self.block_slots)
        # Only the ring's last block can be short (chunks hold whole blocks).
        first_slot = blocks * self.block_slots
        sizes = np.minimum(first_slot + self.block_slots, self.capacity) - first_slot
        sizes *= self.frame_bytes
        decompress = lz4.block.decompress
        packed_chunks = self._packed
        for k, (index, local, nbytes) in enumerate(
            zip(chunk_of.tolist(), local_of.tolist(), sizes.tolist(), strict=True)
        ):
            at = k * block_bytes
            buffer = self._open.get(index)
            if buffer is not None:
                begin = local * block_bytes
                scratch_bytes[at : at + nbytes] = buffer.data.cast("B")[begin : begin + nbytes]
                continue
            packed = packed_chunks[index]
            assert packed is not None
            offsets = packed.offsets
            data = decompress(
                packed.payload[offsets[local] : offsets[local + 1]], uncompressed_size=nbytes
            )
            if len(data) != nbytes:
                raise ValueError(f"a compressed block holds {len(data)} bytes, not {nbytes}")
            scratch_bytes[at : at + nbytes] = data
        rows = inverse * self.block_slots + slots % self.block_slots
        torch.index_select(
            torch.from_numpy(scratch.reshape(-1, *self.frame_shape)),
            0,
            torch.from_numpy(rows),
            out=torch.from_numpy(out),
        )

    def chunk(self, index: int) -> np.ndarray:
        """Chunk `index`'s frames, raw (a copy): for a device upload or a conversion."""
        start, stop = self.chunk_span(index)
        if index in self._open:
            return self._open[index][: stop - start].copy()
        out = np.empty((stop - start, *self.frame_shape), self.dtype)
        packed = self._packed[index]
        assert packed is not None
        unpack(self.codec, packed, out, self.block_slots)
        return out

    # Checkpoints ----------------------------------------------------------------------

    def load_chunk(self, index: int, encoding: str, data: memoryview) -> None:
        """Replace chunk `index` with the bytes a checkpoint stored for it, kept as they are
        when compressed with this codec; raw bytes (a run saved without compression, or the
        chunk that was being written) are compressed here."""
        start, stop = self.chunk_span(index)
        self._discard(index)
        if encoding == self.codec:
            blocks = -(-(stop - start) // self.block_slots)
            try:
                self._packed[index] = PackedChunk.from_bytes(data, blocks)
            except ValueError as error:
                raise ValueError(f"chunk {index} is not valid {self.codec} data: {error}") from None
        elif encoding == RAW:
            frames = np.frombuffer(data, dtype=self.dtype).reshape(stop - start, *self.frame_shape)
            self._packed[index] = pack(self.codec, frames, self.block_slots)
        else:
            raise ValueError(f"chunk {index} has encoding {encoding!r}, unknown to this replay")

    def clear_chunk(self, index: int) -> None:
        """Set chunk `index` to zeros, as before anything was written: a chunk that a
        checkpoint left out because it was never written."""
        start, stop = self.chunk_span(index)
        self._discard(index)
        self._packed[index] = self._zeros[stop - start]

    def _discard(self, index: int) -> None:
        """Chunk `index` is replaced: its raw frames, if open, are not kept."""
        if index in self._open:
            self._free.append(self._open.pop(index))
