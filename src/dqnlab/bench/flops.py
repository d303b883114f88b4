"""The update's floating-point work, counted by PyTorch's `FlopCounterMode` on one update,
and the limit to hold it against: this machine's dense float32 matrix-multiply
throughput, timed in the same run on the same threads (issue 22, part 1).

Convention (`FlopCounterMode`'s): a FLOP is one multiply or one add, and a product's
FLOPs are 2 x its multiply-accumulates (MACs). Only matrix products and convolutions are
counted, forward and backward, the dense work a matrix multiply's throughput bounds: bias
additions, ReLU, the input scaling, noisy layers' weight composition (mu + sigma * eps),
the dueling combination, softmax, the loss and the optimizer step are elementwise, and
left out (under 1% of the Nature update). Products a part computes besides the networks
are counted too: C51's projection of the target distribution (a 51 x 51 product per
transition: 0.17 MFLOP per minibatch), IQN's fraction embeddings.

What it comes to for the shipped TD losses, per layer and per input:

    convolution    2 x output elements x in_channels / groups x kernel elements
    linear         2 x in_features x out_features x positions (1 for flat input)

F, the forward FLOPs of one input, is their sum. The backward of a layer computes the
weight gradient (dL/dW = dY^T X: the forward's MACs again) when its weights learn, and
the input gradient (dL/dX = dY W: the same again) when its input needs one, which every
layer's does but the first's (the observations need no gradient). So with F_first the
FLOPs of the first layer, the update of `Agent.update` per minibatch of B is:

    target network forward on s' (no gradient)                  B F
    target = "double": online forward on s' (no gradient; a*)   B F
    online forward on s                                         B F
    backward: weight gradients B F, input gradients B (F - F_first)

    update = B (4 F - F_first) with target = "max", B (5 F - F_first) with "double".

Where the target network is a copy of the online network at the update (a preset that
copies it after every update: `drq_epsilon`), the online network stands in for it and
Double DQN's target takes the one pass on s': B (4 F - F_first) with either target.

The Nature CNN on 4x84x84 with 4 actions: F = 18,690,048 (conv 8x8/4 to 32x20x20
6,553,600; conv 4x4/2 to 64x9x9 5,308,416; conv 3x3/1 to 64x7x7 3,612,672; linear
3136-512 3,211,264; linear 512-4 4,096), F_first = 6,553,600, so the update of a
minibatch of 32 is 2.18 GFLOP (2.78 with the double target); tests/bench/test_flops.py
holds `FlopCounterMode`'s count to these figures.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from dqnlab.algorithm.agent import Agent
from dqnlab.algorithm.minibatch import Batch
from dqnlab.bench.measure import call_seconds, copies_target_every_update

# 2 x 2048^3 = 17.2 GFLOP per product: about 80 ms at the 2 cores' 215 GFLOP/s, far
# above the timer's and the call's overheads.
MATMUL_SIZE = 2048
MATMUL_REPEATS = 10


def update_flops(agent: Agent, batch: Batch) -> int:
    """The FLOPs of one `agent.update(batch)` (the module's convention), with the target as
    training's updates see it: a copy of the online network where training copies it after
    every update (then Double DQN's target takes one pass on s', see the module's note),
    otherwise a network the online one has moved away from (an update first where they are
    still equal, as in a freshly built agent). The updates run: the agent has learned one
    or two steps more. A compiled update (`compile_update`) runs eagerly under the counter,
    as torch.compile does under any dispatch mode; it compiles at its next call."""
    if copies_target_every_update(agent):
        agent.sync_target()
    elif agent.target_is_a_copy():
        agent.update(batch)
    with FlopCounterMode(display=False) as counter:
        agent.update(batch)
    return int(counter.get_total_flops())


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

    def multiply() -> None:
        torch.mm(left, right, out=product)
        product[0, 0].item()  # waits for the device

    seconds = call_seconds(multiply, repeats)
    flop = 2 * size**3
    return MatmulThroughput(
        size,
        torch.get_num_threads(),
        flop / float(np.median(seconds)) / 1e9,
        flop / float(np.min(seconds)) / 1e9,
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
