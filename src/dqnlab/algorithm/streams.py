"""The replay memory's streams: one ring per training environment, in one set of arrays.

With `num_envs` = N environments, the frames of one environment must never meet another's
in a stacked history or an n-step window. The replay's capacity is cut into N equal
segments (slot = stream · segment + local slot), each a ring of its own with its own
position, fill and write count: a window, an n-step sum and the slots a write can make
(in)valid wrap within their segment, never into a neighbour. With N = 1 the one segment is
the whole ring and every formula below is the single ring's, number for number.

A uniform draw picks k in [0, slots stored) and maps it to the k-th stored slot, stream
by stream (`slots_of`), so that with N = 1 it draws the very numbers it always did and for
any N each stored slot is equally likely.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dqnlab.algorithm.nstep import ring_slots

# The ring ranges written since a mark: one (start, stop) ring range, several that do not
# wrap, or None for every slot (`ReplayStreams.written_since`).
WrittenSlots = tuple[int, int] | list[tuple[int, int]] | None


class ReplayStreams:
    """`count` rings of `capacity // count` slots each (the remainder, < count slots, is
    left unused). `positions[k]`: stream k's next local slot to write; `sizes[k]`: its
    slots stored; `writes[k]`: its writes since creation."""

    def __init__(self, capacity: int, count: int, smallest_segment: int) -> None:
        if count < 1:
            raise ValueError(f"a replay needs at least one stream, not {count}")
        segment = capacity // count
        if segment < smallest_segment:
            raise ValueError(
                f"a replay of {capacity} slots cut into {count} streams leaves {segment} "
                f"slots each, fewer than the {smallest_segment} one transition needs"
            )
        self.count = count
        self.segment = segment
        self.capacity = segment * count
        # Python lists: one element is read and written per stored step (cheaper than
        # NumPy scalars); the vectorised checks convert them (N numbers).
        self.positions = [0] * count
        self.sizes = [0] * count
        self.writes = [0] * count

    @property
    def size(self) -> int:
        return sum(self.sizes)

    def advance(self, stream: int) -> int:
        """The slot a write to `stream` goes to; the stream then moves past it."""
        local = self.positions[stream]
        self.positions[stream] = (local + 1) % self.segment
        if self.sizes[stream] < self.segment:
            self.sizes[stream] += 1
        self.writes[stream] += 1
        return stream * self.segment + local

    def wrap(self, starts: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """Slots `offsets` away from each of `starts` ((len(starts), len(offsets))),
        wrapped round the start's own segment."""
        return ring_slots(starts, offsets, self.segment)

    def locate(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(stream, local slot) of each of `slots`."""
        streams, local = np.divmod(slots, self.segment)
        return streams, local

    def ages(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per slot: its age in its ring (0 the oldest, the next overwritten; before the
        ring is full the slots not written yet rank first), its local slot, and whether
        its ring is full."""
        if self.count == 1:
            full = np.full(len(slots), self.sizes[0] == self.segment)
            return (slots - self.positions[0]) % self.segment, slots, full
        streams, local = self.locate(slots)
        positions = np.asarray(self.positions)[streams]
        full = np.asarray(self.sizes)[streams] == self.segment
        return (local - positions) % self.segment, local, full

    def stored(self, slots: np.ndarray) -> np.ndarray:
        """Whether each of `slots` holds a write of its stream (before its ring is full,
        the first `size` local slots)."""
        if self.count == 1:
            return slots < self.sizes[0]
        streams, local = self.locate(slots)
        return local < np.asarray(self.sizes)[streams]

    def slots_of(self, ranks: np.ndarray) -> np.ndarray:
        """The slot of each rank in [0, size): the stored slots of stream 0 first (local
        order), then stream 1's, and so on. With one stream, the rank itself."""
        if self.count == 1:
            return ranks
        ends = np.cumsum(self.sizes)
        streams = np.searchsorted(ends, ranks, side="right")
        return streams * self.segment + ranks - (ends[streams] - np.asarray(self.sizes)[streams])

    def full_rows(self, starts: np.ndarray) -> bool | np.ndarray:
        """Whether the ring of each of `starts` is full (one bool with one stream)."""
        if self.count == 1:
            return self.sizes[0] == self.segment
        return np.asarray(self.sizes)[starts // self.segment] == self.segment

    def bases(self, starts: np.ndarray) -> np.ndarray | None:
        """The first slot of each start's segment (None with one stream: slot 0)."""
        if self.count == 1:
            return None
        return starts - starts % self.segment

    # Checkpoints ----------------------------------------------------------------------

    def mark(self) -> tuple[list[int], list[int]]:
        """Where the rings are now: what `written_since` counts from."""
        return list(self.positions), list(self.writes)

    def written_since(self, mark: tuple[list[int], list[int]]) -> WrittenSlots:
        """The slots written since `mark`: with one stream, its ring range [start, stop)
        (stop < start wraps; None: every slot), as `checkpoints.written_slots`; with
        more, one range per stream (two where it wraps in its segment), None if every
        stream was written all round."""
        positions, writes = mark
        written = [now - then for now, then in zip(self.writes, writes, strict=True)]
        if any(count < 0 for count in written):
            raise ValueError(f"writes went back since the mark: {writes} -> {self.writes}")
        segment = self.segment
        if all(count >= segment for count in written):
            return None
        if self.count == 1:
            return positions[0], (positions[0] + written[0]) % segment
        ranges: list[tuple[int, int]] = []
        for stream, (start, count) in enumerate(zip(positions, written, strict=True)):
            base = stream * segment
            if count >= segment:
                ranges.append((base, base + segment))
            elif start + count <= segment:
                ranges.append((base + start, base + start + count))
            else:
                ranges += [(base + start, base + segment), (base, base + start + count - segment)]
        return ranges

    def state_dict(self) -> dict[str, Any]:
        return {"positions": self.positions, "sizes": self.sizes, "writes": self.writes}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for name in ("positions", "sizes", "writes"):
            values = [int(value) for value in state[name]]
            if len(values) != self.count:
                raise ValueError(f"a state of {len(values)} replay streams, not {self.count}")
            setattr(self, name, values)
