"""The update's floating-point work, counted from the network's layers, and the limit to
hold it against: this machine's dense float32 matrix-multiply throughput, timed in the
same run on the same threads (issue 22, part 1).

Convention: a FLOP is one multiply or one add, and a layer's FLOPs are 2 x its
multiply-accumulates (MACs). Only the products of convolutions and linear layers are
counted, the dense work a matrix multiply's throughput bounds: bias additions, ReLU, the
input scaling, noisy layers' weight composition (mu + sigma * eps: 2 FLOPs per weight
per forward pass), the dueling combination, softmax, the loss and the optimizer step are
elementwise, and left out (under 1% of the Nature update), as is C51's projection of the
target distribution (a 51 x 51 product per transition: 0.17 MFLOP per minibatch). It is
the convention of `torch.utils.flop_counter.FlopCounterMode`, which the tests compare
against.

Per layer and per input, with the shapes traced by forward hooks on a probe batch of the
network's real input shape and dtype, in train mode as in the update:

    convolution (Conv1d/2d/3d)   2 x output elements x in_channels / groups x kernel elements
    linear (Linear, NoisyLinear) 2 x in_features x out_features x positions (1 for flat input)

F, the forward FLOPs of one input, is their sum. The backward of a layer computes the
weight gradient (dL/dW = dY^T X: the forward's MACs again) when its weights learn, and
the input gradient (dL/dX = dY W: the same again) when its input needs one, which every
layer's does but the first's (the observations need no gradient). So with F_first the
FLOPs of the layers whose input needs no gradient, the update of `Agent.update` with the
shipped loss parts, per minibatch of B, is:

    target network forward on s' (no gradient)                  B F
    target = "double": online forward on s' (no gradient; a*)   B F
    online forward on s                                         B F
    backward: weight gradients B F, input gradients B (F - F_first)

    update = B (4 F - F_first) with target = "max", B (5 F - F_first) with "double".

The Nature CNN on 4x84x84 with 4 actions: F = 18,690,048 (conv 8x8/4 to 32x20x20
6,553,600; conv 4x4/2 to 64x9x9 5,308,416; conv 3x3/1 to 64x7x7 3,612,672; linear
3136-512 3,211,264; linear 512-4 4,096), F_first = 6,553,600, so the update of a
minibatch of 32 is 2.18 GFLOP (2.78 with the double target).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from dqnlab.algorithm.agent import Agent
from dqnlab.algorithm.heads import NoisyLinear

# 2 x 2048^3 = 17.2 GFLOP per product: about 80 ms at the 2 cores' 215 GFLOP/s, far
# above the timer's and the call's overheads.
MATMUL_SIZE = 2048
MATMUL_REPEATS = 10
_CONVOLUTIONS = (nn.Conv1d, nn.Conv2d, nn.Conv3d)
_LINEARS = (nn.Linear, NoisyLinear)


@dataclass(frozen=True)
class LayerFlops:
    """One convolution or linear layer: the FLOPs of its product for one input, and which
    gradients the backward pass computes for it."""

    name: str  # the module's name in the network
    forward: int
    weight_gradient: bool  # its weights learn: dL/dW, the forward's FLOPs again
    input_gradient: bool  # its input needs a gradient: dL/dX, the forward's FLOPs again

    @property
    def backward(self) -> int:
        return self.forward * (int(self.weight_gradient) + int(self.input_gradient))


@dataclass(frozen=True)
class NetworkFlops:
    """A network's counted layers in the order they ran, and the names of the modules with
    parameters of a kind not counted (a user's network may have some; the shipped ones
    have none)."""

    layers: tuple[LayerFlops, ...]
    not_counted: tuple[str, ...]

    @property
    def forward(self) -> int:
        """F: the forward FLOPs of one input."""
        return sum(layer.forward for layer in self.layers)

    @property
    def backward(self) -> int:
        """The backward FLOPs of one input: weight and input gradients."""
        return sum(layer.backward for layer in self.layers)

    def update(self, batch_size: int, target: str = "max") -> int:
        """The FLOPs of one update on a minibatch of `batch_size` (the module's formula)."""
        forwards = 3 if target == "double" else 2
        return batch_size * (forwards * self.forward + self.backward)


def _layer_forward_flops(module: nn.Module, inputs: torch.Tensor, output: torch.Tensor) -> int:
    """2 x the MACs of one input (the batch is the first axis)."""
    batch = inputs.shape[0]
    if isinstance(module, _CONVOLUTIONS):
        kernel = int(np.prod(module.kernel_size))
        macs = output.numel() // batch * (module.in_channels // module.groups) * kernel
    elif isinstance(module, _LINEARS):
        # in_features x out_features at each position (the input's other axes).
        macs = inputs.numel() // batch * module.out_features
    else:
        raise TypeError(f"no FLOP count for {type(module).__name__}")
    return 2 * macs


def count_network_flops(
    network: nn.Module, input_shape: tuple[int, ...], dtype: torch.dtype
) -> NetworkFlops:
    """Trace one forward pass of `network` on a probe batch of 2 zero inputs of
    `input_shape` (history, *observation shape) and `dtype`, with gradients enabled and in
    train mode, as the update runs it; the network's mode is restored afterwards."""
    names = {module: name for name, module in network.named_modules()}
    layers: list[LayerFlops] = []

    def record(module: nn.Module, inputs: tuple[Any, ...], output: Any) -> None:
        weights = [p for p in module.parameters(recurse=False) if p.ndim > 1]
        layers.append(
            LayerFlops(
                names[module],
                _layer_forward_flops(module, inputs[0], output),
                weight_gradient=any(p.requires_grad for p in weights),
                input_gradient=bool(inputs[0].requires_grad),
            )
        )

    counted = {m for m in network.modules() if isinstance(m, _CONVOLUTIONS + _LINEARS)}
    not_counted = tuple(
        name
        for name, module in network.named_modules()
        if module not in counted and any(True for _ in module.parameters(recurse=False))
    )
    parameter = next(network.parameters(), None)
    device = parameter.device if parameter is not None else torch.device("cpu")
    hooks = [module.register_forward_hook(record) for module in counted]
    modes = {module: module.training for module in network.modules()}
    try:
        network.train()
        with torch.enable_grad():
            network(torch.zeros((2, *input_shape), dtype=dtype, device=device))
    finally:
        for hook in hooks:
            hook.remove()
        for module, training in modes.items():
            module.training = training
    return NetworkFlops(tuple(layers), not_counted)


def agent_network_flops(agent: Agent) -> NetworkFlops:
    """`count_network_flops` of the agent's online network on its input."""
    if agent.input_shape is None or agent.observation_dtype is None:
        raise ValueError("counting FLOPs needs an agent built with its input shape and dtype")
    dtype = torch.from_numpy(np.zeros(0, dtype=agent.observation_dtype)).dtype
    return count_network_flops(agent.online, agent.input_shape, dtype)


@dataclass(frozen=True)
class MatmulThroughput:
    """`torch.mm` of two `size` x `size` float32 matrices: GFLOP/s = 2 size^3 / seconds,
    from the median and the fastest of the timed products."""

    size: int
    threads: int
    median_gflop_per_s: float
    best_gflop_per_s: float


def measure_matmul(
    device: torch.device, size: int | None = None, repeats: int = MATMUL_REPEATS
) -> MatmulThroughput:
    """Time `repeats` products (after one untimed) on `device`, with the process's
    `torch.get_num_threads()` threads: those the update runs on. `size`: MATMUL_SIZE."""
    size = size or MATMUL_SIZE
    generator = torch.Generator().manual_seed(0)
    left = torch.rand(size, size, generator=generator).to(device)
    right = torch.rand(size, size, generator=generator).to(device)
    product = torch.empty(size, size, device=device)
    torch.mm(left, right, out=product)
    timings = []
    for _ in range(repeats):
        start = time.perf_counter()
        torch.mm(left, right, out=product)
        product[0, 0].item()  # waits for the device
        timings.append(time.perf_counter() - start)
    flop = 2 * size**3
    return MatmulThroughput(
        size,
        torch.get_num_threads(),
        flop / float(np.median(timings)) / 1e9,
        flop / min(timings) / 1e9,
    )


def update_flop_figures(
    prefix: str, flop: int, update_ms: float, matmul: MatmulThroughput
) -> dict[str, Any]:
    """The update's FLOPs per minibatch, the GFLOP/s it achieved in `update_ms` (median),
    and its fraction of the matrix multiply's median GFLOP/s, as `{prefix}...` figures."""
    achieved = flop / (update_ms / 1e3) / 1e9
    return {
        f"{prefix}update_gflop": flop / 1e9,
        f"{prefix}update_gflop_per_s": achieved,
        f"{prefix}update_fraction_of_matmul": achieved / matmul.median_gflop_per_s,
    }


def matmul_figures(matmul: MatmulThroughput) -> dict[str, Any]:
    return {
        "matmul_size": matmul.size,
        "matmul_threads": matmul.threads,
        "matmul_gflop_per_s": matmul.median_gflop_per_s,
        "matmul_gflop_per_s_best": matmul.best_gflop_per_s,
    }
