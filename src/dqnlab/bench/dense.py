"""The dense operations of one update, timed alone in the same run: `update_ms / dense_ms`
is the update's overhead over the work it cannot avoid (issue 32: at most 1.15 for nature).

The dense operations are the update's convolutions and linear layers: their forward passes
(the online network on s, and on s' where the double target asks; the target network on
s') and the backward through the online network (gradients of the weights and biases, and
of the input of every layer but the first). The rest is the overhead the ratio shows: the
uint8 -> float conversion, ReLU, the loss's elementwise work, the gradient clip, the
optimizer step, allocations, Python, and products outside the layers (C51's projection).

`dense_calls` records them on one real update: a forward hook on every `Conv2d`, `Linear`
and `NoisyLinear` of both networks (a noisy layer is the `F.linear` of its composed weight;
composing it is elementwise), and a gradient hook on each output, so that a call counts in
the backward where the backward reached it. `median_dense_ms` replays them alone on random
operands of the recorded shapes, dtype and memory layout (the Nature CNN runs
channels-last). Each call's backward (`torch.autograd.grad`: fresh gradients, not added to
`.grad`) follows its own forward, where the update runs every forward first: the operands
are warmer, so the ratio errs low if at all.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from dqnlab.algorithm.agent import Agent
from dqnlab.algorithm.heads import NoisyLinear
from dqnlab.algorithm.minibatch import Batch
from dqnlab.bench.measure import call_seconds

DENSE_LAYERS = (nn.Conv2d, nn.Linear, NoisyLinear)
WARMUP_REPLAYS = 3  # not timed: the first calls allocate and pick their kernels


@dataclass(frozen=True)
class DenseCall:
    """One call of a convolution or linear layer in an update, as `median_dense_ms` replays
    it. `input_grad` / `weight_grad`: the update's backward computed the gradient of the
    input / of the weight and bias (neither: the call was forward only)."""

    layer: str  # the network and the module's name in it: "online.features.0"
    kind: str  # "conv2d" or "linear"
    input_shape: tuple[int, ...]
    weight_shape: tuple[int, ...]
    bias: bool
    dtype: torch.dtype  # the output's: the one the operation computed in
    input_channels_last: bool
    weight_channels_last: bool
    input_grad: bool
    weight_grad: bool
    stride: tuple[int, ...] = ()  # convolutions only, as `F.conv2d` takes them
    padding: tuple[int, ...] | str = ()
    dilation: tuple[int, ...] = ()
    groups: int = 1

    @property
    def in_backward(self) -> bool:
        return self.input_grad or self.weight_grad


def dense_calls(agent: Agent, batch: Batch) -> list[DenseCall]:
    """The convolutions and linear layers one `agent.update(batch)` runs, in call order.
    The update runs (the agent has learned one step more), eagerly where it is compiled;
    the hooks are gone afterwards."""
    calls: list[DenseCall] = []
    reached: set[int] = set()  # the calls whose output the backward reached
    names: dict[nn.Module, str] = {
        module: f"{role}.{name}"
        for role, network in (("online", agent.online), ("target", agent.target))
        for name, module in network.named_modules()
        if isinstance(module, DENSE_LAYERS)
    }

    def record(module: nn.Module, args: tuple[Any, ...], output: torch.Tensor) -> None:
        calls.append(_call(names[module], module, args[0], output))
        if output.requires_grad:
            index = len(calls) - 1
            output.register_hook(lambda _gradient: reached.add(index))

    handles = [module.register_forward_hook(record) for module in names]
    try:
        with torch.compiler.set_stance("force_eager"):
            agent.update(batch)
    finally:
        for handle in handles:
            handle.remove()
    if not calls:  # a replayed CUDA graph runs no Python, hence no hook
        raise ValueError("the update ran no convolution or linear layer that a hook could see")
    return [
        call if index in reached else dataclasses.replace(call, input_grad=False, weight_grad=False)
        for index, call in enumerate(calls)
    ]


def _call(layer: str, module: nn.Module, inputs: torch.Tensor, output: torch.Tensor) -> DenseCall:
    """The call of `module` on `inputs`, as its forward hook sees it."""
    noisy = isinstance(module, NoisyLinear)  # mu + sigma * eps: the shapes of mu
    weight: torch.Tensor = getattr(module, "weight_mu" if noisy else "weight")
    bias: torch.Tensor | None = getattr(module, "bias_mu" if noisy else "bias")
    conv = isinstance(module, nn.Conv2d)
    settings = ("stride", "padding", "dilation", "groups")
    return DenseCall(
        layer=layer,
        kind="conv2d" if conv else "linear",
        input_shape=tuple(inputs.shape),
        weight_shape=tuple(weight.shape),
        bias=bias is not None,
        dtype=output.dtype,
        input_channels_last=_channels_last(inputs),
        weight_channels_last=_channels_last(weight),
        input_grad=inputs.requires_grad,
        weight_grad=torch.is_grad_enabled() and weight.requires_grad,  # the bias's alike
        **({name: getattr(module, name) for name in settings} if conv else {}),
    )


def _channels_last(tensor: torch.Tensor) -> bool:
    return (
        tensor.dim() == 4
        and tensor.is_contiguous(memory_format=torch.channels_last)
        and not tensor.is_contiguous()
    )


def median_dense_ms(calls: Sequence[DenseCall], device: torch.device, repeats: int) -> float:
    """The median time of `repeats` replays of `calls` on `device` (after WARMUP_REPLAYS not
    timed), each waited for, in milliseconds."""
    replays = [_replay(call, device) for call in calls]

    def replay_all() -> None:
        for replay in replays:
            last = replay()
        last[(0,) * last.dim()].item()  # waits for the device

    for _ in range(WARMUP_REPLAYS):
        replay_all()
    return float(np.median(call_seconds(replay_all, repeats)) * 1e3)


def _replay(call: DenseCall, device: torch.device) -> Callable[[], torch.Tensor]:
    """The call on random operands made now: its forward, then its backward where the
    update ran one."""

    def operand(shape: tuple[int, ...], channels_last: bool, grad: bool) -> torch.Tensor:
        tensor = torch.randn(shape, dtype=call.dtype, device=device)
        if channels_last:
            tensor = tensor.to(memory_format=torch.channels_last)
        return tensor.requires_grad_(grad)

    inputs = operand(call.input_shape, call.input_channels_last, call.input_grad)
    weight = operand(call.weight_shape, call.weight_channels_last, call.weight_grad)
    bias = operand(call.weight_shape[:1], False, call.weight_grad) if call.bias else None
    if call.kind == "conv2d":
        layout = {"stride": call.stride, "padding": call.padding, "dilation": call.dilation}
        forward = functools.partial(F.conv2d, inputs, weight, bias, groups=call.groups, **layout)
    else:
        forward = functools.partial(F.linear, inputs, weight, bias)
    if not call.in_backward:
        return forward
    wanted = [t for t in (inputs, weight, bias) if t is not None and t.requires_grad]
    output_gradient = torch.randn_like(forward())  # in the output's layout

    def forward_and_backward() -> torch.Tensor:
        return torch.autograd.grad(forward(), wanted, output_gradient)[0]

    return forward_and_backward


def dense_figures(
    prefix: str, agent: Agent, batch: Batch, update_ms: float, repeats: int
) -> dict[str, float]:
    """`{prefix}dense_ms`: the dense operations of one update of `batch` (recorded on one
    more update) timed alone, `repeats` times, median; `{prefix}update_over_dense`: the
    update's median `update_ms` over it."""
    dense_ms = median_dense_ms(dense_calls(agent, batch), agent.device, repeats)
    return {f"{prefix}dense_ms": dense_ms, f"{prefix}update_over_dense": update_ms / dense_ms}
