"""Replay memory: preallocated, each frame stored once, histories stacked when sampled.

Slot i holds the observation o_t, the action a_t taken from it, the reward r_t that
followed and whether that transition ended in a terminal state. The next observation
o_{t+1} is slot i+1. The last observation of every episode gets a slot of its own,
marked `is_last`, from which no transition starts: it is the bootstrap state of a
truncated episode and the (masked) next state of a terminal one. A network input is the
last `history_length` observations of one episode; older slots across an `is_last`
boundary are zeros, as at an episode start while acting (`FrameHistory`; the buffers a
minibatch is gathered into are `minibatch.py`'s).

With `n_step` > 1, a sampled transition sums the rewards of up to n stored steps and
bootstraps from the observation n steps on (`nstep.py`, computed when drawn). How
minibatches are drawn is the replay's sampler's business (`samplers.py`: uniform,
prioritized, or a user's): the replay tells it of every write and hands it `valid`,
`sample_indices` and `gather`.

Memory per transition is one frame plus 10 bytes (action, reward, two flags): a 1M Atari
replay is 7.07 GB, like the Lua code's byte tensor (TransitionTable.lua).

With a `device` (a GPU), the frames are also kept there and minibatches are gathered
there: nothing but the slot numbers crosses to the device per update. The host arrays
stay the reference (checkpoints read and load them; `upload` copies them over after a
load), and the sampled transitions are the same either way.

With `compression` (`replay_compression`, image observations only), the host frames are a
`CompressedFrames`: every 16,384-slot chunk but the one being written is compressed, and a
minibatch decompresses the blocks its windows touch. The batches are the same bytes as
without it; a device copy, when there is one, stays raw.

With `streams` > 1 (`num_envs` environments), each environment's steps go to a ring of
their own (`streams.py`), so that no history or n-step window mixes two environments; with
one stream everything is the single ring's, draw for draw.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from dqnlab.algorithm.compression import CHUNK_SLOTS, CompressedFrames
from dqnlab.algorithm.minibatch import Batch, Layout, MinibatchBuffers
from dqnlab.algorithm.nstep import discount_powers, n_step_targets, window_steps
from dqnlab.algorithm.replay_sizes import (  # noqa: F401 - `replay_bytes`: their home before
    _SLOT_OVERHEAD_BYTES,
    check_memory,
    check_projection,
    compresses,
    open_chunks,
    replay_bytes,
)
from dqnlab.algorithm.samplers import UniformSampler
from dqnlab.algorithm.streams import ReplayStreams, WrittenSlots


class ReplayMemory:
    def __init__(
        self,
        capacity: int,
        frame_shape: tuple[int, ...],
        frame_dtype: np.dtype | type,
        history_length: int,
        batch_size: int,
        seed: int,
        device: torch.device | None = None,
        pin_memory: bool = False,
        compression: str = "none",
        expected_frame_bytes: float | None = None,
        chunk_slots: int = CHUNK_SLOTS,
        n_step: int = 1,
        discount: float = 0.99,
        sampler: Any = None,
        streams: int = 1,
    ) -> None:
        """`device`: also keep the frames there and gather minibatches there (see the
        module's docstring). `pin_memory`: the host minibatch buffer page-locked, for faster
        copies to a GPU. `compression`: a codec for the host frames (not for vectors:
        `compresses`); `expected_frame_bytes`: a compressed frame's measured size, which the
        memory check may count on (else the raw size: `replay_sizes.check_projection`).
        `n_step` and `discount` (γ): the returns a sampled transition sums (`nstep.py`).
        `sampler`: how `sample` draws (`samplers.py`; uniform when None), bound here.
        `streams`: rings of capacity // streams slots, one per environment (`streams.py`)."""
        if n_step < 1:
            raise ValueError(f"n_step = {n_step} must be at least 1")
        frame_dtype = np.dtype(frame_dtype)
        # One stream: the whole ring, whatever its size; more: each holds a transition.
        self.streams = ReplayStreams(
            capacity, streams, 1 if streams == 1 else history_length + n_step + 1
        )
        capacity = self.streams.capacity
        self.compressed = compresses(compression, tuple(frame_shape))
        self.frame_shape = tuple(frame_shape)
        self.raw_frame_bytes = int(np.prod(frame_shape)) * frame_dtype.itemsize
        # What the replay may grow to, as far as is known before it is filled.
        self.expected_bytes = replay_bytes(
            capacity,
            frame_shape,
            frame_dtype,
            expected_frame_bytes if self.compressed else None,
            streams,
        )
        check_memory(self.expected_bytes, "the replay memory")
        self.capacity = capacity
        self.history_length = history_length
        self.batch_size = batch_size
        self.n_step = n_step
        self.discount = discount
        self._powers = discount_powers(discount, n_step)
        self.device = device
        self._allocate_storage(frame_dtype, compression, chunk_slots, streams)
        self.rng = np.random.default_rng(seed)
        self._offsets = np.arange(-history_length + 1, 2, dtype=np.int64)  # a window
        self._history_offsets = self._offsets[:-1]
        self._allocate_minibatches(frame_dtype, pin_memory)
        self.sampler = sampler if sampler is not None else UniformSampler()
        self.sampler.bind(self)

    def _allocate_storage(
        self, frame_dtype: np.dtype, compression: str, chunk_slots: int, streams: int
    ) -> None:
        """The ring's arrays, preallocated: the frames (raw, or compressed chunk by chunk),
        actions, rewards, terminals and episode ends, and the frames' copy on `device`."""
        capacity, frame_shape = self.capacity, self.frame_shape
        self.frames: np.ndarray | CompressedFrames
        if self.compressed:
            self.frames = CompressedFrames(
                capacity, frame_shape, frame_dtype, compression, chunk_slots,
                open_chunks=open_chunks(streams),
            )  # fmt: skip
        else:
            self.frames = np.zeros((capacity, *frame_shape), dtype=frame_dtype)
        self.actions = np.zeros(capacity, dtype=np.int32)
        self.rewards = np.zeros(capacity, dtype=np.float32)
        self.terminals = np.zeros(capacity, dtype=np.bool_)
        self.is_last = np.zeros(capacity, dtype=np.bool_)
        self._frames_view = None if self.compressed else torch.from_numpy(self.frames)
        if self.device is not None:  # a copy of the frames, to gather minibatches there
            torch_dtype = torch.from_numpy(np.zeros(0, dtype=frame_dtype)).dtype
            self._device_frames = torch.zeros(
                (capacity, *frame_shape), dtype=torch_dtype, device=self.device
            )

    def _allocate_minibatches(self, frame_dtype: np.dtype, pin_memory: bool) -> None:
        """Sampling buffers, reused by every call: room for the widest transition, of which
        one-step windows take the first batch_size * (history + 1) frames."""
        history, n_step = self.history_length, self.n_step
        self._buffers = MinibatchBuffers(
            self.frame_shape, frame_dtype, history, self.batch_size,
            history + 1 if n_step == 1 else 2 * history, self.discount, self.device, pin_memory,
        )  # fmt: skip
        self._one_step = self._buffers.layout(history + 1, next_column=1)
        self._n_step = (
            self._one_step
            if n_step == 1
            else self._buffers.layout(2 * history, next_column=history)
        )

    @property
    def position(self) -> int:
        """The next slot to write (of the one stream)."""
        if self.streams.count != 1:
            raise ValueError("a replay of several streams has one position per stream")
        return self.streams.positions[0]

    @property
    def size(self) -> int:
        """Slots stored, all streams together."""
        return self.streams.size

    @property
    def writes(self) -> int:
        """Slots written since creation, all streams together."""
        return sum(self.streams.writes)

    def mark(self) -> tuple[list[int], list[int]]:
        """Where the rings are now, for `written_since`."""
        return self.streams.mark()

    def written_since(self, mark: tuple[list[int], list[int]]) -> WrittenSlots:
        """The slots written since `mark`, as a checkpoint is told (`ReplayStreams`)."""
        return self.streams.written_since(mark)

    @property
    def bytes_per_transition(self) -> float:
        """Host bytes per transition without compression."""
        return self.raw_frame_bytes + _SLOT_OVERHEAD_BYTES

    @property
    def resident_bytes(self) -> int:
        """Host bytes the replay's arrays hold now (compressed frames as they are)."""
        frames = (
            self.frames.resident_bytes
            if isinstance(self.frames, CompressedFrames)
            else self.frames.nbytes
        )
        return frames + self.capacity * _SLOT_OVERHEAD_BYTES

    # Writing --------------------------------------------------------------------------

    def add(
        self,
        observation: np.ndarray,
        action: int,
        reward: float,
        terminal: bool,
        stream: int = 0,
    ) -> None:
        """Store o_t, a_t, r_t and whether o_{t+1} is terminal, in `stream`'s ring."""
        self._write(observation, action, reward, terminal, False, stream)

    def add_last(self, observation: np.ndarray, stream: int = 0) -> None:
        """Store the final observation of an episode (terminal or truncated)."""
        self._write(observation, 0, 0.0, False, True, stream)

    def _write(
        self,
        observation: np.ndarray,
        action: int,
        reward: float,
        terminal: bool,
        is_last: bool,
        stream: int,
    ) -> None:
        slot = self.streams.advance(stream)
        sealed = None
        if isinstance(self.frames, CompressedFrames):
            sealed = self.frames.sealed_slots
            row = torch.from_numpy(self.frames.write(slot, observation))
        else:
            assert self._frames_view is not None
            self.frames[slot] = observation
            row = self._frames_view[slot]
        if self.device is not None:
            self._device_frames[slot] = row
        self.actions[slot] = action
        self.rewards[slot] = reward
        self.terminals[slot] = terminal
        self.is_last[slot] = is_last
        self.sampler.written(slot)
        frames = self.frames
        if isinstance(frames, CompressedFrames) and frames.sealed_slots != sealed:
            check_projection(frames, self.capacity - self.size, self.raw_frame_bytes)

    # Sampling -------------------------------------------------------------------------

    def valid(self, slots: np.ndarray) -> np.ndarray:
        """Which slots can start a sampled transition: not an episode's last observation,
        its next state (slot t + m, `window_steps`) stored already, and, once its ring is
        full, its history not reaching back into overwritten (newest) data."""
        streams = self.streams
        steps = (
            1
            if self.n_step == 1
            else window_steps(self.terminals, self.is_last, slots, self.n_step, streams.segment)
        )
        # Rank in its ring from the oldest slot: 0 the oldest (the next overwritten),
        # segment - 1 the newest. Before a ring is full, its unwritten slots rank first.
        age, _, full = streams.ages(slots)
        valid = ~self.is_last[slots] & (age + steps <= streams.segment - 1)
        # Before a ring is full its local slots 0..size-1 are written, size-1 the newest;
        # after, the oldest slots' histories reach back into overwritten (newest) data.
        return valid & np.where(full, age >= self.history_length - 1, streams.stored(slots))

    def has_transition(self) -> bool:
        """Whether a complete transition (o_t to o_{t+m}) is stored, so sampling can succeed."""
        return bool(self.valid(self.streams.slots_of(np.arange(self.size))).any())

    def sample_indices(self, count: int, rng: np.random.Generator | None = None) -> np.ndarray:
        """Uniform with replacement over valid transitions, by rejection (as the Lua code),
        with the replay's own generator unless `rng` is given."""
        rng = self.rng if rng is None else rng
        indices = np.empty(count, dtype=np.int64)
        filled = 0
        rejected_rounds = 0
        while filled < count:
            ranks = rng.integers(0, max(self.size, 1), size=2 * (count - filled))
            candidates = self.streams.slots_of(ranks)
            accepted = candidates[self.valid(candidates)][: count - filled]
            indices[filled : filled + len(accepted)] = accepted
            filled += len(accepted)
            rejected_rounds = 0 if len(accepted) else rejected_rounds + 1
            if rejected_rounds == 20 and not self.has_transition():
                raise RuntimeError("the replay memory holds no complete transition yet")
        return indices

    def sample(self, step: int = 0) -> Batch:
        """The minibatch of the update at agent step `step`, as the sampler draws it."""
        batch: Batch = self.sampler.sample(step)
        return batch

    @property
    def minibatch(self) -> Batch:
        """The batch `gather` fills and returns, reused by every draw (a sampler may give
        it importance weights)."""
        return self._n_step.batch

    def gather(self, indices: np.ndarray) -> Batch:
        """The transitions starting at `indices` (len == batch_size): with n_step = 1, the
        windows of `gather_windows`; with more, n-step returns (`nstep.n_step_targets`)
        and the histories of o_t and o_{t+m}, gathered side by side (`window` None)."""
        if self.n_step == 1:
            return self.gather_windows(indices)
        layout = self._n_step
        segment = self.streams.segment
        steps = window_steps(self.terminals, self.is_last, indices, self.n_step, segment)
        history = self.history_length
        bases = self.streams.bases(indices)
        starts = indices if bases is None else indices - bases
        raw_slots = np.empty((len(indices), 2 * history), dtype=np.int64)
        raw_slots[:, :history] = starts[:, None] + self._history_offsets
        raw_slots[:, history:] = (starts + steps)[:, None] + self._history_offsets
        self._gather_frames(layout, raw_slots, indices, bases)
        batch = layout.batch
        assert batch.indices is not None and batch.discounts is not None
        batch.indices[:] = indices
        batch.actions[:] = self.actions[indices]
        n_step_targets(
            self.rewards, self.terminals, indices, steps, self._powers,
            batch.rewards, batch.terminals, batch.discounts, segment,
        )  # fmt: skip
        return batch

    def gather_windows(self, indices: np.ndarray) -> Batch:
        """One-step transitions starting at `indices` (len == batch_size), whatever n_step:
        windows of history + 1 slots (s the first `history` frames, s' the last), r_t,
        whether s' is terminal, γ. Nature's Fig. 2 (`heldout.py`) measures these."""
        layout = self._one_step
        bases = self.streams.bases(indices)
        starts = indices if bases is None else indices - bases
        self._gather_frames(layout, starts[:, None] + self._offsets, indices, bases)
        batch = layout.batch
        assert batch.indices is not None
        batch.indices[:] = indices
        batch.actions[:] = self.actions[indices]
        batch.rewards[:] = self.rewards[indices]
        batch.terminals[:] = self.terminals[indices]
        return batch

    def _gather_frames(
        self, layout: Layout, raw_slots: np.ndarray, indices: np.ndarray, bases: np.ndarray | None
    ) -> None:
        source: torch.Tensor | CompressedFrames
        if self.device is not None:
            source = self._device_frames
        elif isinstance(self.frames, CompressedFrames):
            source = self.frames
        else:
            assert self._frames_view is not None
            source = self._frames_view
        streams = self.streams
        full = streams.full_rows(indices)
        self._buffers.gather(layout, raw_slots, source, self.is_last, full, streams.segment, bases)

    def upload(self) -> None:
        """Copy the host frames to the device (after a checkpoint was loaded into them)."""
        if self.device is None:
            return
        if isinstance(self.frames, CompressedFrames):
            for index in range(self.frames.chunks):
                start, stop = self.frames.chunk_span(index)
                self._device_frames[start:stop] = torch.from_numpy(self.frames.chunk(index))
        else:
            assert self._frames_view is not None
            self._device_frames.copy_(self._frames_view)

    # State ----------------------------------------------------------------------------

    @property
    def arrays(self) -> dict[str, np.ndarray | CompressedFrames]:
        """The preallocated arrays, by name: what a checkpoint stores chunk by chunk (the
        compressed frames, chunk by chunk as they are held)."""
        return {
            "frames": self.frames,
            "actions": self.actions,
            "rewards": self.rewards,
            "terminals": self.terminals,
            "is_last": self.is_last,
        }

    def state_dict(self) -> dict[str, Any]:
        """The small state; the arrays are saved separately (`arrays`). With prioritized
        sampling, the sampler's state too (8 bytes a slot), so a resumed run draws the same
        minibatches."""
        state: dict[str, Any] = {"rng": self.rng.bit_generator.state}
        if self.streams.count == 1:
            state.update(position=self.position, size=self.size, writes=self.writes)
        else:
            state["streams"] = self.streams.state_dict()
        sampler_state = self.sampler.state_dict()
        if sampler_state is not None:  # the key of the priorities before samplers were parts
            state["priorities"] = sampler_state
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if "streams" in state:
            self.streams.load_state_dict(state["streams"])
        else:
            self.streams.load_state_dict({name: [state[key]] for name, key in STREAM_KEYS.items()})
        self.rng.bit_generator.state = state["rng"]
        self.sampler.load_state_dict(state.get("priorities"))


STREAM_KEYS = {"positions": "position", "sizes": "size", "writes": "writes"}  # one stream


class FrameHistory:
    """The last `history_length` observations of the current episode, zeros before its start."""

    def __init__(self, history_length: int, frame_shape: tuple[int, ...], dtype: np.dtype) -> None:
        self.frames = np.zeros((history_length, *frame_shape), dtype=dtype)

    def reset(self, observation: np.ndarray) -> None:
        self.frames.fill(0)
        self.frames[-1] = observation

    def push(self, observation: np.ndarray) -> None:
        self.frames[:-1] = self.frames[1:]
        self.frames[-1] = observation

    @property
    def newest(self) -> np.ndarray:
        return self.frames[-1]
