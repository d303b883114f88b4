"""How much memory a replay memory takes (`replay.ReplayMemory`), checked before it is
allocated and again as compressed frames show their real size."""

from __future__ import annotations

import numpy as np
import psutil

from dqnlab.algorithm.compression import CHUNK_SLOTS, CompressedFrames, check_codec
from dqnlab.errors import ResourceError

_SLOT_OVERHEAD_BYTES = 4 + 4 + 1 + 1  # action int32, reward float32, terminal, is_last


def replay_bytes(
    capacity: int,
    frame_shape: tuple[int, ...],
    frame_dtype: np.dtype,
    compressed_frame_bytes: float | None = None,
    streams: int = 1,
) -> int:
    """Host bytes of a replay; `compressed_frame_bytes`: the compressed size of one frame,
    when the frames are compressed (plus the raw chunks being written: one, or one more
    than the `streams`)."""
    frame_bytes = int(np.prod(frame_shape)) * np.dtype(frame_dtype).itemsize
    if compressed_frame_bytes is None:
        return capacity * (frame_bytes + _SLOT_OVERHEAD_BYTES)
    raw_chunk = min(capacity, CHUNK_SLOTS) * frame_bytes * open_chunks(streams)
    return int(capacity * (compressed_frame_bytes + _SLOT_OVERHEAD_BYTES) + raw_chunk)


def open_chunks(streams: int) -> int:
    """Raw chunks compressed frames keep open: each stream writes its own, and a chunk
    that two streams' segments share may be open beside them."""
    return 1 if streams == 1 else streams + 1


def compresses(compression: str, frame_shape: tuple[int, ...]) -> bool:
    """Whether `compression` applies: it is for image observations, not vectors."""
    if compression != "none":
        check_codec(compression)
    return compression != "none" and len(frame_shape) >= 2


def check_memory(required_bytes: int, what: str) -> None:
    available = psutil.virtual_memory().available
    if required_bytes > available:
        raise ResourceError(
            f"{what} needs {required_bytes / 2**30:.2f} GiB but only "
            f"{available / 2**30:.2f} GiB of memory is available; lower replay_capacity"
        )


def check_projection(frames: CompressedFrames, remaining: int, raw_frame_bytes: int) -> None:
    """After a chunk is compressed: stop before memory runs out, not in it.

    The replay grows until it is full; the chunk just compressed tells how large this
    game's frames are when compressed, which the start-up check could only assume. If the
    `remaining` slots still to fill, at this size, need more than the memory available,
    raise now (a ResourceError, with the figures), minutes into a run rather than hours.
    """
    per_slot = frames.last_sealed_bytes / frames.last_sealed_slots
    needed = remaining * per_slot
    available = psutil.virtual_memory().available
    if needed > available:
        raise ResourceError(
            f"this game's frames compress to {per_slot:.0f} bytes each "
            f"({raw_frame_bytes / per_slot:.1f}x): the {remaining:,} replay slots "
            f"still to fill need {needed / 2**30:.2f} GiB but only "
            f"{available / 2**30:.2f} GiB of memory is available; lower replay_capacity"
        )
