"""Replay memory: preallocated, each frame stored once, histories stacked when sampled.

Slot i holds the observation o_t, the action a_t taken from it, the reward r_t that
followed and whether that transition ended in a terminal state. The next observation
o_{t+1} is slot i+1. The last observation of every episode gets a slot of its own,
marked `is_last`, from which no transition starts: it is the bootstrap state of a
truncated episode and the (masked) next state of a terminal one. A network input is the
last `history_length` observations of one episode; older slots across an `is_last`
boundary are zeros, as at an episode start while acting (`FrameHistory`).

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
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import psutil
import torch

from dqnlab.algorithm.compression import CHUNK_SLOTS, CompressedFrames, check_codec
from dqnlab.errors import ResourceError

_SLOT_OVERHEAD_BYTES = 4 + 4 + 1 + 1  # action int32, reward float32, terminal, is_last


def replay_bytes(
    capacity: int,
    frame_shape: tuple[int, ...],
    frame_dtype: np.dtype,
    compressed_frame_bytes: float | None = None,
) -> int:
    """Host bytes of a replay; `compressed_frame_bytes`: the compressed size of one frame,
    when the frames are compressed (plus the raw chunk being written)."""
    frame_bytes = int(np.prod(frame_shape)) * np.dtype(frame_dtype).itemsize
    if compressed_frame_bytes is None:
        return capacity * (frame_bytes + _SLOT_OVERHEAD_BYTES)
    raw_chunk = min(capacity, CHUNK_SLOTS) * frame_bytes
    return int(capacity * (compressed_frame_bytes + _SLOT_OVERHEAD_BYTES) + raw_chunk)


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


@dataclass
class Batch:
    """Views into the memory's reusable sampling buffers: valid until the next sample.

    The frames are NumPy arrays, or tensors already on the device when the memory keeps
    its frames there."""

    observations: np.ndarray | torch.Tensor  # (batch, history, *frame_shape)
    actions: np.ndarray  # (batch,) int64
    rewards: np.ndarray  # (batch,) float32
    terminals: np.ndarray  # (batch,) float32, 1.0 where the next state is terminal
    next_observations: np.ndarray | torch.Tensor  # (batch, history, *frame_shape)
    # (batch, history + 1, *frame_shape) when both are views of it (observations the first
    # `history` frames, next_observations the last): a device copies it once, not twice.
    window: np.ndarray | torch.Tensor | None = None
    indices: np.ndarray | None = None  # (batch,) int64: the sampled slots
    discounts: np.ndarray | None = None  # (batch,) float32: the bootstrap's discount
    weights: np.ndarray | None = None  # (batch,) float32: importance weights (prioritized)


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
    ) -> None:
        """`device`: also keep the frames there and gather minibatches there (see the
        module's docstring). `pin_memory`: the host minibatch buffer in page-locked memory,
        for faster copies to a GPU (needs CUDA). `compression`: a codec for the host frames
        (ignored for vector observations: `compresses`); `expected_frame_bytes`: the
        measured compressed size of one of this game's frames, which the memory check may
        count on (without it, the check asks for the raw size: see `_check_projection`)."""
        frame_dtype = np.dtype(frame_dtype)
        self.compressed = compresses(compression, tuple(frame_shape))
        self.frame_shape = tuple(frame_shape)
        self.raw_frame_bytes = int(np.prod(frame_shape)) * frame_dtype.itemsize
        # What the replay may grow to, as far as is known before it is filled.
        self.expected_bytes = replay_bytes(
            capacity, frame_shape, frame_dtype, expected_frame_bytes if self.compressed else None
        )
        check_memory(self.expected_bytes, "the replay memory")
        self.capacity = capacity
        self.history_length = history_length
        self.batch_size = batch_size
        self.frames: np.ndarray | CompressedFrames
        if self.compressed:
            self.frames = CompressedFrames(
                capacity, self.frame_shape, frame_dtype, compression, chunk_slots
            )
        else:
            self.frames = np.zeros((capacity, *frame_shape), dtype=frame_dtype)
        self.actions = np.zeros(capacity, dtype=np.int32)
        self.rewards = np.zeros(capacity, dtype=np.float32)
        self.terminals = np.zeros(capacity, dtype=np.bool_)
        self.is_last = np.zeros(capacity, dtype=np.bool_)
        self.position = 0  # next slot to write
        self.size = 0
        self.writes = 0  # slots written since creation: tells a checkpoint what changed
        self.rng = np.random.default_rng(seed)
        # Sampling buffers, reused by every call: a window of history + 1 slots per sample.
        window = history_length + 1
        self._offsets = np.arange(-history_length + 1, 2, dtype=np.int64)
        self._window = np.zeros((batch_size, window, *frame_shape), dtype=frame_dtype)
        if pin_memory:
            pinned = torch.from_numpy(self._window).pin_memory()
            self._window = pinned.numpy()
        self._slots = np.zeros((batch_size, window), dtype=np.int64)
        self._mask = np.ones((batch_size, window), dtype=np.bool_)
        # torch views of the same memory: index_select copies the windows on every core,
        # twice as fast as np.take on 2 cores (np.take with `out` and mode "raise" even
        # buffers the whole copy).
        self._frames_view = None if self.compressed else torch.from_numpy(self.frames)
        self._window_view = torch.from_numpy(self._window).view(-1, *frame_shape)
        self._window_frames = self._window.reshape(-1, *frame_shape)  # a view
        self._slots_view = torch.from_numpy(self._slots).view(-1)
        self._batch = Batch(
            observations=self._window[:, :history_length],
            actions=np.zeros(batch_size, dtype=np.int64),
            rewards=np.zeros(batch_size, dtype=np.float32),
            terminals=np.zeros(batch_size, dtype=np.float32),
            next_observations=self._window[:, 1:],
            window=self._window,
        )
        self.device = device
        if device is not None:  # the same buffers, on the device
            torch_dtype = torch.from_numpy(self._window[:0]).dtype
            self._device_frames = torch.zeros(
                (capacity, *frame_shape), dtype=torch_dtype, device=device
            )
            self._device_window = torch.zeros(self._window.shape, dtype=torch_dtype, device=device)
            self._device_slots = torch.zeros(self._slots.size, dtype=torch.int64, device=device)
            # Kept frames of each window, shaped to broadcast over a frame.
            self._device_mask = torch.zeros(
                (batch_size, window, *[1] * len(frame_shape)), dtype=torch.uint8, device=device
            )
            self._batch = dataclasses.replace(
                self._batch,
                observations=self._device_window[:, :history_length],
                next_observations=self._device_window[:, 1:],
                window=self._device_window,
            )

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

    def add(self, observation: np.ndarray, action: int, reward: float, terminal: bool) -> None:
        """Store o_t, a_t, r_t and whether o_{t+1} is terminal."""
        self._write(observation, action, reward, terminal, is_last=False)

    def add_last(self, observation: np.ndarray) -> None:
        """Store the final observation of an episode (terminal or truncated)."""
        self._write(observation, 0, 0.0, False, is_last=True)

    def _write(
        self, observation: np.ndarray, action: int, reward: float, terminal: bool, is_last: bool
    ) -> None:
        slot = self.position
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
        self.position = (slot + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        self.writes += 1
        if sealed is not None and self.frames.sealed_slots != sealed:  # type: ignore[union-attr]
            self._check_projection()

    # Sampling -------------------------------------------------------------------------

    def _valid(self, slots: np.ndarray) -> np.ndarray:
        """Which slots can start a sampled transition: o_{t+1} must be stored already."""
        if self.size < self.capacity:  # slots 0..size-1 written, size-1 the newest
            return ~self.is_last[slots] & (slots < self.size - 1)
        newest = (self.position - 1) % self.capacity
        # The oldest slots' histories reach back into overwritten (newest) data.
        age = (slots - self.position) % self.capacity
        return ~self.is_last[slots] & (slots != newest) & (age >= self.history_length - 1)

    def has_transition(self) -> bool:
        """Whether a complete transition (o_t and o_{t+1}) is stored, so sampling can succeed."""
        return bool(self._valid(np.arange(self.size)).any())

    def sample_indices(self, count: int, rng: np.random.Generator | None = None) -> np.ndarray:
        """Uniform with replacement over valid transitions, by rejection (as the Lua code),
        with the replay's own generator unless `rng` is given."""
        rng = self.rng if rng is None else rng
        indices = np.empty(count, dtype=np.int64)
        filled = 0
        rejected_rounds = 0
        while filled < count:
            candidates = rng.integers(0, max(self.size, 1), size=2 * (count - filled))
            accepted = candidates[self._valid(candidates)][: count - filled]
            indices[filled : filled + len(accepted)] = accepted
            filled += len(accepted)
            rejected_rounds = 0 if len(accepted) else rejected_rounds + 1
            if rejected_rounds == 20 and not self.has_transition():
                raise RuntimeError("the replay memory holds no complete transition yet")
        return indices

    def sample(self) -> Batch:
        return self.gather(self.sample_indices(self.batch_size))

    def gather(self, indices: np.ndarray) -> Batch:
        """Stack the histories of transitions starting at `indices` (len == batch_size)."""
        history = self.history_length
        raw_slots = indices[:, None] + self._offsets
        np.remainder(raw_slots, self.capacity, out=self._slots)
        # A frame of the window is kept only if no episode ended between it and the
        # transition's own observation (window position history - 1).
        mask = self._mask
        mask[:, history - 1 :] = True
        for j in range(history - 2, -1, -1):
            mask[:, j] = mask[:, j + 1] & ~self.is_last[self._slots[:, j]]
            if self.size < self.capacity:  # before the first write there is nothing
                mask[:, j] &= raw_slots[:, j] >= 0
        if self.device is None:
            if isinstance(self.frames, CompressedFrames):
                self.frames.gather(self._slots_view.numpy(), self._window_frames)
            else:
                assert self._frames_view is not None
                torch.index_select(self._frames_view, 0, self._slots_view, out=self._window_view)
            if not mask.all():
                self._window[~mask] = 0
        else:
            self._device_slots.copy_(self._slots_view)
            frames = self._device_window.view(-1, *self.frame_shape)
            torch.index_select(self._device_frames, 0, self._device_slots, out=frames)
            if not mask.all():
                self._device_mask.view(mask.shape).copy_(torch.from_numpy(mask))
                self._device_window.mul_(self._device_mask)
        batch = self._batch
        batch.actions[:] = self.actions[indices]
        batch.rewards[:] = self.rewards[indices]
        batch.terminals[:] = self.terminals[indices]
        return batch

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

    def _check_projection(self) -> None:
        """After a chunk is compressed: stop before memory runs out, not in it.

        The replay grows until it is full; the chunk just compressed tells how large this
        game's frames are when compressed, which the start-up check could only assume. If
        the slots still to fill, at this size, need more than the memory available, raise
        now (a ResourceError, with the figures), minutes into a run rather than hours.
        """
        assert isinstance(self.frames, CompressedFrames)
        per_slot = self.frames.last_sealed_bytes / self.frames.last_sealed_slots
        remaining = self.capacity - self.size
        needed = remaining * per_slot
        available = psutil.virtual_memory().available
        if needed > available:
            raise ResourceError(
                f"this game's frames compress to {per_slot:.0f} bytes each "
                f"({self.raw_frame_bytes / per_slot:.1f}x): the {remaining:,} replay slots "
                f"still to fill need {needed / 2**30:.2f} GiB but only "
                f"{available / 2**30:.2f} GiB of memory is available; lower replay_capacity"
            )

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
        """The small state; the arrays are saved separately (`arrays`)."""
        return {
            "position": self.position,
            "size": self.size,
            "writes": self.writes,
            "rng": self.rng.bit_generator.state,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.position = int(state["position"])
        self.size = int(state["size"])
        self.writes = int(state["writes"])
        self.rng.bit_generator.state = state["rng"]


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
