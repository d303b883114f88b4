"""What lets an update run on a GPU without waiting for it: the minibatch's small arrays
sent in one copy that does not block (`HostToDevice`), and the update captured once as a
CUDA graph and replayed (`CapturedUpdate`, `update_graph = "cuda"`).

A blocking host-to-device copy waits for the device to finish all the work queued before
it; a Python-launched update is dozens of kernel launches, each a few microseconds of host
time. The graph replays them all with one launch (PyTorch's "whole network capture",
docs/source/notes/cuda.rst, section "CUDA Graphs", of pytorch/pytorch).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

ALIGNMENT = 16  # bytes: every array's offset in the staging buffer, so views of any dtype fit
STAGING_SLOTS = 4  # host buffers in turn: the host waits only if the device is this far behind
WARMUP_UPDATES = 3  # eager updates on a side stream before capture, as PyTorch's notes ask

Arrays = Sequence[np.ndarray | None]
Tensors = tuple[torch.Tensor | None, ...]


class HostToDevice:
    """The per-update NumPy arrays (actions, rewards, terminals, discounts, weights) as
    tensors on `device`. On a CUDA device they are packed into one page-locked buffer and
    sent in one copy that does not block, into a device buffer that stays in place (the
    same addresses every update, as a CUDA graph needs); the host buffers are used in turn
    and one is refilled only after its last copy has run. On another device the tensors
    share the arrays' memory (`torch.from_numpy`), as before this class, unless `packed`
    (the CUDA path's packing, without page-locking or events: what a CPU test can run)."""

    def __init__(
        self, device: torch.device, slots: int = STAGING_SLOTS, packed: bool | None = None
    ) -> None:
        self.device = device
        self.slots = slots
        self.cuda = device.type == "cuda"
        self.packed = self.cuda if packed is None else packed
        self._layout: tuple[tuple[np.dtype, tuple[int, ...]] | None, ...] = ()
        self._host: list[torch.Tensor] = []
        self._events: list[torch.cuda.Event | None] = []
        self._device_buffer: torch.Tensor | None = None
        self._views: Tensors = ()
        self._offsets: list[int] = []
        self._next = 0

    def upload(self, arrays: Arrays) -> Tensors:
        if not self.packed:
            return tuple(None if a is None else torch.from_numpy(a).to(self.device) for a in arrays)
        layout = tuple(None if a is None else (a.dtype, a.shape) for a in arrays)
        if layout != self._layout:
            self._allocate(layout)
        slot = self._next
        self._next = (slot + 1) % self.slots
        event = self._events[slot]
        if event is not None:
            event.synchronize()  # its previous copy has run: free to refill
        host = self._host[slot].numpy()
        for offset, array in zip(self._offsets, arrays, strict=True):
            if array is not None:
                host[offset : offset + array.nbytes] = array.reshape(-1).view(np.uint8)
        assert self._device_buffer is not None
        self._device_buffer.copy_(self._host[slot], non_blocking=self.cuda)
        if event is not None:
            event.record()
        return self._views

    def owns(self, tensor: torch.Tensor) -> bool:
        """Whether `tensor` is one of the device views `upload` returns every time."""
        return any(tensor is view for view in self._views)

    def _allocate(self, layout: tuple[tuple[np.dtype, tuple[int, ...]] | None, ...]) -> None:
        offsets, views_at, size = [], [], 0
        for entry in layout:
            offsets.append(size)
            if entry is not None:
                dtype, shape = entry
                views_at.append((size, dtype, shape))
                size += -(-int(np.prod(shape)) * dtype.itemsize // ALIGNMENT) * ALIGNMENT
        self._layout, self._offsets = layout, offsets
        self._host = [
            torch.empty(size, dtype=torch.uint8, pin_memory=self.cuda) for _ in range(self.slots)
        ]
        self._events = [torch.cuda.Event() if self.cuda else None for _ in range(self.slots)]
        for event in self._events:
            if event is not None:
                event.record()
        buffer = torch.empty(size, dtype=torch.uint8, device=self.device)
        self._device_buffer = buffer
        views: list[torch.Tensor | None] = []
        found = iter(views_at)
        for entry in layout:
            if entry is None:
                views.append(None)
                continue
            offset, dtype, shape = next(found)
            nbytes = int(np.prod(shape)) * dtype.itemsize
            torch_dtype = torch.from_numpy(np.zeros(0, dtype=dtype)).dtype
            views.append(buffer[offset : offset + nbytes].view(torch_dtype).view(shape))
        self._views = tuple(views)
        self._next = 0


class CapturedUpdate:
    """`step` (the whole update: zero the gradients, loss, backward, clip, optimizer step)
    captured as a CUDA graph on its first call after `WARMUP_UPDATES` eager ones, then
    replayed. The graph reads its inputs from the tensors it was captured with: a later
    input at another address is first copied there (a minibatch's frames, 1.1 MB for
    Nature's), one already there (`HostToDevice`'s) is not. Its outputs (the loss, the
    priorities) are the graph's own tensors, overwritten by the next update.

    Every update, warm-up or replayed, is the same arithmetic as an eager one: the warm-up
    updates are real updates (run on a side stream, which lets the capture see the memory
    they allocated), and capture records without running, so the update being captured is
    then replayed. What the graph holds is addresses: the parameters, their gradients and
    the optimizer's state must stay where they were (`reset` after loading a state dict,
    which replaces the optimizer's tensors)."""

    def __init__(
        self,
        step: Callable[..., tuple[torch.Tensor, torch.Tensor | None]],
        keeps_address: Callable[[torch.Tensor], bool],
    ) -> None:
        """`keeps_address(tensor)`: whether an input stays where it is from update to
        update (`HostToDevice.owns`), so the graph may read it in place."""
        self.step = step
        self.keeps_address = keeps_address
        self.reset()

    def reset(self) -> None:
        """Forget the graph: the next updates warm up and capture again."""
        self.graph: torch.cuda.CUDAGraph | None = None
        self.warmups = 0
        self._inputs: Tensors = ()
        self._signature: tuple[object, ...] = ()
        self._outputs: tuple[torch.Tensor, torch.Tensor | None] | None = None

    def __call__(self, *inputs: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        signature = _signature(inputs)
        if self.graph is not None and signature != self._signature:
            self.reset()  # another kind of minibatch: a graph of its own
        if self.graph is None:
            if self.warmups < WARMUP_UPDATES:
                self.warmups += 1
                return self._eager_on_side_stream(inputs)
            self._capture(inputs, signature)
        for static, given in zip(self._inputs, inputs, strict=True):
            if static is not None and given is not None and given.data_ptr() != static.data_ptr():
                static.copy_(given)
        assert self.graph is not None and self._outputs is not None
        self.graph.replay()
        return self._outputs

    def _eager_on_side_stream(self, inputs: Tensors) -> tuple[torch.Tensor, torch.Tensor | None]:
        side, current = torch.cuda.Stream(), torch.cuda.current_stream()
        side.wait_stream(current)
        with torch.cuda.stream(side):
            outputs = self.step(*inputs)
        current.wait_stream(side)
        return outputs

    def _capture(self, inputs: Tensors, signature: tuple[object, ...]) -> None:
        # The staging buffer's views are the agent's own and stay in place; anything else
        # (a view of the replay's minibatch buffer) is copied into a tensor of the graph's.
        self._inputs = tuple(
            None if t is None else (t if self.keeps_address(t) else t.clone()) for t in inputs
        )
        graph = torch.cuda.CUDAGraph()
        torch.cuda.synchronize()
        with torch.cuda.graph(graph):
            self._outputs = self.step(*self._inputs)
        self.graph, self._signature = graph, signature


def _signature(inputs: Tensors) -> tuple[object, ...]:
    return tuple(None if t is None else (t.shape, t.dtype, t.device) for t in inputs)
