"""The minibatch (`Minibatch`: `Batch` as the replay draws it, `Transitions` on the
training device) and the buffers the replay gathers it into: allocated once, filled by
every draw, on the host (page-locked for a GPU if asked) or on the device that keeps a
copy of the frames.

A network input is the last `history_length` observations of one episode, stacked when a
transition is drawn; frames from before the episode's start are zeros, as at an episode
start while acting (`replay.FrameHistory`). A one-step transition is one window of
history + 1 consecutive slots (o_t its first `history` frames, o_{t+1} its last); an
n-step transition is the history of o_t beside the history of o_{t+m}, which m apart
share no window.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np
import torch

from dqnlab.algorithm.compression import CompressedFrames

Array = TypeVar("Array", np.ndarray, torch.Tensor)


@dataclass
class Minibatch(Generic[Array]):
    """The one minibatch type, from the replay to the loss part. The replay draws it as
    NumPy arrays (`Batch`: views into its reusable buffers, valid until the next draw; the
    frames already tensors on the device when the replay keeps its frames there); the
    agent sends it to the training device in one step (`Agent.update`) as tensors
    (`Transitions`), which is what a loss part reads, and tells the sampler its priorities
    by `indices`.

    A transition starts at slot t and sums m <= n_step steps (`dqnlab.algorithm.nstep`);
    its TD target is rewards + discounts · (1 - terminals) · value(next_observations)."""

    observations: Array | torch.Tensor  # (batch, history, *frame_shape), o_t, stored dtype
    actions: Array  # (batch,) int64
    rewards: Array  # (batch,) float32: Σ_{k<m} γ^k r_{t+k}, rewards clipped as stored
    terminals: Array  # (batch,) float32, 1.0 where the window ended in a terminal state
    discounts: Array  # (batch,) float32: γ^m, the discount of the bootstrap
    next_observations: Array | torch.Tensor  # (batch, history, *frame_shape), o_{t+m}
    # (batch,) float32: importance weights of prioritized sampling; None: uniform, all 1.
    weights: Array | None = None
    # (batch,) int64, on the host: the slots the transitions start at, what the sampler
    # is told (`samplers.py`); None for a minibatch that came from no replay.
    indices: np.ndarray | None = None
    # (batch, history + 1, *frame_shape) when both states are views of it (one-step
    # transitions: observations the first `history` frames, next_observations the last):
    # a device copies it once, not twice. None for n-step transitions.
    window: Array | torch.Tensor | None = None

    def update_inputs(self) -> tuple[torch.Tensor | None, ...]:
        """The tensors of a minibatch on the device as the update reads them, in a fixed
        order (what a CUDA graph keeps buffers for: `update_graph.CapturedUpdate`): the
        frames (the window alone where both states are views of it, then None), actions,
        rewards, terminals, discounts and weights. `from_update_inputs` inverts it."""
        assert isinstance(self.observations, torch.Tensor)  # a `Transitions`
        inputs: tuple[Any, ...] = (
            (self.window, None) if self.window is not None
            else (self.observations, self.next_observations)
        )  # fmt: skip
        return (*inputs, self.actions, self.rewards, self.terminals, self.discounts, self.weights)

    @staticmethod
    def from_update_inputs(
        inputs: tuple[torch.Tensor | None, ...], indices: np.ndarray | None = None
    ) -> Transitions:
        """The minibatch whose `update_inputs` are `inputs` (views of them, no copy)."""
        frames, next_frames, actions, rewards, terminals, discounts, weights = inputs
        assert frames is not None and actions is not None and rewards is not None
        assert terminals is not None and discounts is not None
        window = None
        if next_frames is None:  # one window of history + 1 frames holds both states
            window, history = frames, frames.shape[1] - 1
            frames, next_frames = window[:, :history], window[:, 1:]
        return Transitions(
            frames, actions, rewards, terminals, discounts, next_frames, weights, indices, window
        )


# The replay's draw: NumPy arrays (the frames possibly tensors on the device).
Batch = Minibatch[np.ndarray]
# A minibatch on the training device, as a loss part reads it.
Transitions = Minibatch[torch.Tensor]


@dataclass
class Layout:
    """One kind of minibatch in the shared buffers: `width` slots per transition.
    `anchors`: the columns of each history's newest frame, behind which frames across an
    episode start are zeroed."""

    anchors: tuple[int, ...]
    frames: np.ndarray  # (batch, width, *frame_shape), a view of the shared buffer
    frames_torch: torch.Tensor  # the same memory, (batch * width, *frame_shape)
    slots: np.ndarray  # (batch, width) int64, ring slots
    slots_torch: torch.Tensor  # the same memory, (batch * width,)
    mask: np.ndarray  # (batch, width) bool, frames kept
    batch: Batch
    device_frames: torch.Tensor | None  # (batch, width, *frame_shape) on the device
    device_slots: torch.Tensor | None  # (batch * width,)
    device_mask: torch.Tensor | None  # (batch, width, 1, ...) uint8


class MinibatchBuffers:
    """Room for `batch_size` transitions of up to `width` slots each: the host frames
    (page-locked with `pin_memory`, for faster copies to a GPU) and, with a `device`, the
    same buffers there. `layout` cuts them into one kind of minibatch; the kinds share the
    memory, so only the latest gathered one is valid."""

    def __init__(
        self,
        frame_shape: tuple[int, ...],
        frame_dtype: np.dtype,
        history_length: int,
        batch_size: int,
        width: int,
        discount: float,
        device: torch.device | None,
        pin_memory: bool,
    ) -> None:
        self.frame_shape = frame_shape
        self.history_length = history_length
        self.batch_size = batch_size
        self.discount = discount
        self.device = device
        frames = np.zeros((batch_size * width, *frame_shape), dtype=frame_dtype)
        if pin_memory:
            frames = torch.from_numpy(frames).pin_memory().numpy()
        self._frames = frames
        self._slots = np.zeros(batch_size * width, dtype=np.int64)
        self._mask = np.ones(batch_size * width, dtype=np.bool_)
        # On a GPU the slots and the mask cross page-locked, in copies that do not wait
        # for the device; the host rewrites them only once the last copy has run.
        self._copied: torch.cuda.Event | None = None
        if device is not None and device.type == "cuda":
            self._slots = torch.from_numpy(self._slots).pin_memory().numpy()
            self._mask = torch.from_numpy(self._mask).pin_memory().numpy()
            self._copied = torch.cuda.Event()
        if device is not None:
            torch_dtype = torch.from_numpy(frames[:0]).dtype
            self._device_frames = torch.zeros(frames.shape, dtype=torch_dtype, device=device)
            self._device_slots = torch.zeros(self._slots.size, dtype=torch.int64, device=device)
            # Kept frames of each window, shaped to broadcast over a frame.
            self._device_mask = torch.zeros(
                (self._slots.size, *[1] * len(frame_shape)), dtype=torch.uint8, device=device
            )

    def layout(self, width: int, next_column: int) -> Layout:
        """Transitions of `width` slots whose o_t is columns 0..history-1 and whose next
        state is the `history` columns from `next_column`: 1 for a one-step window (then
        `Batch.window` is the whole), `history` for two histories side by side."""
        batch_size, history = self.batch_size, self.history_length
        count = batch_size * width
        frames = self._frames[:count].reshape(batch_size, width, *self.frame_shape)
        next_columns = slice(next_column, next_column + history)
        is_window = next_column == 1
        batch = Batch(
            observations=frames[:, :history],
            actions=np.zeros(batch_size, dtype=np.int64),
            rewards=np.zeros(batch_size, dtype=np.float32),
            terminals=np.zeros(batch_size, dtype=np.float32),
            next_observations=frames[:, next_columns],
            window=frames if is_window else None,
            indices=np.zeros(batch_size, dtype=np.int64),
            discounts=np.full(batch_size, self.discount, dtype=np.float32),
        )
        device_frames = device_slots = device_mask = None
        if self.device is not None:
            device_frames = self._device_frames[:count].view(frames.shape)
            device_slots = self._device_slots[:count]
            device_mask = self._device_mask[:count].view(
                batch_size, width, *[1] * len(self.frame_shape)
            )
            batch = dataclasses.replace(
                batch,
                observations=device_frames[:, :history],
                next_observations=device_frames[:, next_columns],
                window=device_frames if is_window else None,
            )
        return Layout(
            anchors=(history - 1,) if is_window else (history - 1, next_column + history - 1),
            frames=frames,
            frames_torch=torch.from_numpy(self._frames[:count]),
            slots=self._slots[:count].reshape(batch_size, width),
            slots_torch=torch.from_numpy(self._slots[:count]),
            mask=self._mask[:count].reshape(batch_size, width),
            batch=batch,
            device_frames=device_frames,
            device_slots=device_slots,
            device_mask=device_mask,
        )

    def gather(
        self,
        layout: Layout,
        raw_slots: np.ndarray,
        source: torch.Tensor | CompressedFrames,
        is_last: np.ndarray,
        ring_full: bool | np.ndarray,
        segment: int | None = None,
        bases: np.ndarray | None = None,
    ) -> None:
        """Copy the frames of `raw_slots` ((batch, width) slot numbers, not yet wrapped
        round the ring of len(is_last) slots) from `source` (the replay's frames: a torch
        view of them, compressed ones, or their copy on the device, which the buffers are
        then on) into `layout`, zeros where a history reaches back across an episode's
        start (or, before the ring is full, before slot 0). With streams (`streams.py`),
        `raw_slots` count from each row's segment start `bases` and wrap round `segment`
        slots, and `ring_full` is per row."""
        history = self.history_length
        if self._copied is not None:
            self._copied.synchronize()  # the previous minibatch's slots and mask were sent
        slots = layout.slots
        np.remainder(raw_slots, segment or len(is_last), out=slots)
        if bases is not None:
            slots += bases[:, None]
        # A frame of a history is kept only if no episode ended between it and the
        # history's newest frame (its anchor column).
        mask = layout.mask
        mask[...] = True
        for anchor in layout.anchors:
            for j in range(anchor - 1, anchor - history, -1):
                mask[:, j] = mask[:, j + 1] & ~is_last[slots[:, j]]
                if isinstance(ring_full, np.ndarray):
                    mask[:, j] &= (raw_slots[:, j] >= 0) | ring_full
                elif not ring_full:  # before the first write there is nothing
                    mask[:, j] &= raw_slots[:, j] >= 0
        if self.device is None:
            if isinstance(source, CompressedFrames):
                source.gather(layout.slots_torch.numpy(), layout.frames_torch.numpy())
            else:
                # index_select copies on every core, twice as fast as np.take on 2 cores
                # (np.take with `out` and mode "raise" even buffers the whole copy).
                torch.index_select(source, 0, layout.slots_torch, out=layout.frames_torch)
            if not mask.all():
                layout.frames[~mask] = 0
        else:
            assert isinstance(source, torch.Tensor) and layout.device_frames is not None
            assert layout.device_slots is not None and layout.device_mask is not None
            pinned = self._copied is not None
            layout.device_slots.copy_(layout.slots_torch, non_blocking=pinned)
            frames = layout.device_frames.view(-1, *self.frame_shape)
            torch.index_select(source, 0, layout.device_slots, out=frames)
            if not mask.all():
                device_mask = layout.device_mask.view(mask.shape)
                device_mask.copy_(torch.from_numpy(mask), non_blocking=pinned)
                layout.device_frames.mul_(layout.device_mask)
            if self._copied is not None:
                self._copied.record()
