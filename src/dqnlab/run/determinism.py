"""Deterministic arithmetic on a CUDA device (the `deterministic` setting).

On the CPU, PyTorch's operations give the same bits from the same inputs. On a GPU, some
do not by default: cuDNN's convolution gradients and cuBLAS's split reductions add in an
order that varies from call to call. Measured on an H200 (2026-12-04): two `der` runs on
Pong from the same seed differed in every weight after 2,500 steps. With PyTorch's
deterministic algorithms they repeat bit for bit, and so does a resumed run.
"""

from __future__ import annotations

import os

import torch

from dqnlab.config import Config

# cuBLAS's documented workspace setting for reproducible results (CUDA's cuBLAS guide,
# "Results reproducibility"); PyTorch refuses deterministic matrix products without it.
CUBLAS_WORKSPACE = ":4096:8"


def use_deterministic_algorithms(config: Config, device: torch.device) -> None:
    """On CUDA, with `deterministic` set, make every later operation of this process
    deterministic (an operation with no deterministic kernel then raises, naming itself,
    rather than run differently). Process-wide, as PyTorch's switch is; call it before the
    first operation on the device, since cuBLAS reads its workspace setting once."""
    if device.type != "cuda" or not config.deterministic:
        return
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", CUBLAS_WORKSPACE)
    torch.use_deterministic_algorithms(True)
    torch.backends.cudnn.deterministic = True
    torch.backends.cudnn.benchmark = False


def resume_warning(config: Config, device: torch.device) -> str | None:
    """What a resumed run on CUDA without `deterministic` must say: it continues from the
    checkpoint, but not as the uninterrupted run would have."""
    if device.type != "cuda" or config.deterministic:
        return None
    return (
        "dqnlab: warning: deterministic = false on CUDA: the resumed run continues from its "
        "checkpoint, but not bit for bit as it would have without the stop"
    )
