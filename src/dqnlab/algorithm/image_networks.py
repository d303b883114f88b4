"""The image networks of Atari: the Nature CNN (Mnih et al. 2015) and Data-efficient
Rainbow's two-convolution network (`der_cnn`, van Hasselt et al. 2019, for Atari 100k), each
whole (a Q-network) or as a torso under the DQN family's heads (`networks.build_torso`).

Both read stacked uint8 frames (batch, history, [C,] H, W), scaled by 1/255 inside, as
channels-last float planes (oneDNN's faster layout on CPU, the same values).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from dqnlab.algorithm.encoders import NATURE_MIN_SIDE, nature_convolutions
from dqnlab.errors import ConfigError

NATURE_HIDDEN_WIDTH = 512  # Mnih et al. 2015, Methods: the fully connected layer's units
# Data-efficient Rainbow's hidden layer (van Hasselt et al. 2019, Appendix, "Q network:
# hidden units" 256; Kaixhin/Rainbow --architecture data-efficient --hidden-size 256).
DATA_EFFICIENT_HIDDEN_WIDTH = 256


class NatureCNN(nn.Module):
    """Mnih et al. 2015, Methods: three convolutions and a 512-unit layer, ReLU between.

    PyTorch's default initialisation (uniform +-1/sqrt(fan_in) for weights and biases) is
    the Lua code's (convnet.lua with torch's nn defaults).
    """

    def __init__(self, input_shape: Sequence[int], num_actions: int) -> None:
        super().__init__()
        channels, height, width = _image_planes(input_shape)
        self.features = nature_convolutions(channels)
        flat = _flat_size(self.features, channels, height, width)
        self.head = nn.Sequential(
            nn.Linear(flat, NATURE_HIDDEN_WIDTH),
            nn.ReLU(inplace=True),
            nn.Linear(NATURE_HIDDEN_WIDTH, num_actions),
        )
        # Channels-last convolutions are about a third faster on CPU (oneDNN), same values.
        self.features.to(memory_format=torch.channels_last)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(_scaled_planes(observations)))


class NatureTorso(nn.Module):
    """The Nature CNN's three convolutions, flattened: `output_size` features per input."""

    def __init__(self, input_shape: Sequence[int]) -> None:
        super().__init__()
        channels, height, width = _image_planes(input_shape)
        self.features = nature_convolutions(channels)
        self.output_size = _flat_size(self.features, channels, height, width)
        self.features.to(memory_format=torch.channels_last)  # as in NatureCNN

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.features(_scaled_planes(observations))


def _image_planes(
    input_shape: Sequence[int], min_side: int = NATURE_MIN_SIDE
) -> tuple[int, int, int]:
    """(input planes, height, width) of stacked images: images with channels, (history, C,
    H, W), give history*C planes."""
    history, *frame_shape = input_shape
    channels = history * (frame_shape[0] if len(frame_shape) == 3 else 1)
    height, width = frame_shape[-2:]
    if min(height, width) < min_side:
        network = "the Nature CNN" if min_side == NATURE_MIN_SIDE else "network = 'der_cnn'"
        raise ConfigError(
            f"{network} needs images of at least {min_side}x{min_side} pixels, got {height}x{width}"
        )
    return channels, height, width


def _flat_size(convolutions: nn.Module, channels: int, height: int, width: int) -> int:
    with torch.no_grad():
        return int(convolutions(torch.zeros(1, channels, height, width)).shape[1])


# The last conversion: (input, its version, the autograd modes, the planes). Double DQN's
# update passes the same next observations through the online and the target network, and
# each pass converts them (a third of the conversions of a `der` update, 9% of its time in
# stacking alone): the second pass takes the first's planes. The input is held, so its
# memory cannot be reused by another tensor while it is the key; an in-place change to it
# bumps its version and misses.
_last_planes: tuple[torch.Tensor, int, bool, bool, torch.Tensor] | None = None


def _scaled_planes(observations: torch.Tensor) -> torch.Tensor:
    """Stacked frames (batch, history, [C,] H, W) as float planes in [0, 1], channels-last,
    the previous call's planes when it converted the same unchanged tensor in the same
    autograd modes (the same values: nothing is computed differently).

    Stacking the frames along a new last axis is twice as fast as a strided copy to
    channels-last, and gives a fresh tensor that can be scaled in place."""
    global _last_planes
    if torch.compiler.is_compiling() or observations.is_inference():
        return _converted(observations)  # traced as a pure function; no version to key on
    key = (observations._version, torch.is_inference_mode_enabled(), torch.is_grad_enabled())
    last = _last_planes
    if last is not None and last[0] is observations and last[1:4] == key:
        return last[4]
    planes = _converted(observations)
    _last_planes = (observations, *key, planes)
    return planes


def _converted(observations: torch.Tensor) -> torch.Tensor:
    planes = torch.stack(observations.flatten(1, -3).unbind(1), dim=-1).permute(0, 3, 1, 2)
    return planes.float().div_(255.0)


class DataEfficientCNN(nn.Module):
    """Data-efficient Rainbow's network (van Hasselt, Hessel & Aslanides 2019, "When to use
    parametric models in reinforcement learning?", Appendix: two convolutions, 32 filters
    of 5x5 at stride 5 and 64 of 5x5 at stride 5, then 256 hidden units; Kaixhin/Rainbow
    `model.py`, architecture data-efficient, likewise): 84x84 inputs give 64x3x3 = 576
    features. Initialised as `NatureCNN` (PyTorch's defaults)."""

    def __init__(self, input_shape: Sequence[int], num_actions: int) -> None:
        super().__init__()
        self.torso = DataEfficientTorso(input_shape)
        self.head = nn.Sequential(
            nn.Linear(self.torso.output_size, DATA_EFFICIENT_HIDDEN_WIDTH),
            nn.ReLU(inplace=True),
            nn.Linear(DATA_EFFICIENT_HIDDEN_WIDTH, num_actions),
        )

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.head(self.torso(observations))


class DataEfficientTorso(nn.Module):
    """`DataEfficientCNN`'s two convolutions, flattened: `output_size` features per input."""

    def __init__(self, input_shape: Sequence[int]) -> None:
        super().__init__()
        channels, height, width = _image_planes(input_shape, DATA_EFFICIENT_MIN_SIDE)
        self.features = nn.Sequential(
            nn.Conv2d(channels, 32, kernel_size=5, stride=5),
            nn.ReLU(inplace=True),
            nn.Conv2d(32, 64, kernel_size=5, stride=5),
            nn.ReLU(inplace=True),
            nn.Flatten(),
        )
        self.output_size = _flat_size(self.features, channels, height, width)
        self.features.to(memory_format=torch.channels_last)  # as in NatureCNN

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.features(_scaled_planes(observations))


# The smallest side two 5x5 convolutions at stride 5 can read: 5 * 4 + 5.
DATA_EFFICIENT_MIN_SIDE = 25
