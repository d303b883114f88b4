"""Q-networks: the Nature CNN for images, an MLP for vectors, or a user's own factory.

A network takes a batch of stacked observations of shape (batch, history, *frame_shape)
in their stored dtype (uint8 images are scaled by 1/255 inside) and returns one Q-value
per action. A user's factory is called as `factory(input_shape, num_actions)` with
`input_shape = (history, *frame_shape)` and must return such a `torch.nn.Module`.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence

import torch
from torch import nn

from dqnlab.errors import ConfigError


class NatureCNN(nn.Module):
    """Mnih et al. 2015, Methods: three convolutions and a 512-unit layer, ReLU between.

    PyTorch's default initialisation (uniform +-1/sqrt(fan_in) for weights and biases) is
    the Lua code's (convnet.lua with torch's nn defaults).
    """

    def __init__(self, input_shape: Sequence[int], num_actions: int) -> None:
        super().__init__()
        history, *frame_shape = input_shape
        # Images may carry channels: (history, C, H, W) becomes history*C input planes.
        channels = history * (frame_shape[0] if len(frame_shape) == 3 else 1)
        height, width = frame_shape[-2:]
        self.features = nn.Sequential(
            nn.Conv2d(channels, 32, kernel_size=8, stride=4),
            nn.ReLU(),
            nn.Conv2d(32, 64, kernel_size=4, stride=2),
            nn.ReLU(),
            nn.Conv2d(64, 64, kernel_size=3, stride=1),
            nn.ReLU(),
            nn.Flatten(),
        )
        if min(height, width) < 36:
            raise ConfigError(
                f"the Nature CNN needs images of at least 36x36 pixels, got {height}x{width}"
            )
        with torch.no_grad():
            flat = self.features(torch.zeros(1, channels, height, width)).shape[1]
        self.head = nn.Sequential(nn.Linear(flat, 512), nn.ReLU(), nn.Linear(512, num_actions))
        # Channels-last convolutions are about a third faster on CPU (oneDNN), same values.
        self.features.to(memory_format=torch.channels_last)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        # Channels-last planes by stacking the frames along a new last axis: twice as fast
        # as a strided copy to channels-last, and a fresh tensor that can be scaled in place.
        planes = torch.stack(observations.flatten(1, -3).unbind(1), dim=-1).permute(0, 3, 1, 2)
        return self.head(self.features(planes.float().div_(255.0)))


class MLP(nn.Module):
    """Fully connected Q-network for vector observations (histories are concatenated)."""

    def __init__(
        self, input_shape: Sequence[int], num_actions: int, hidden_sizes: Sequence[int]
    ) -> None:
        super().__init__()
        inputs = 1
        for n in input_shape:
            inputs *= n
        layers: list[nn.Module] = [nn.Flatten()]
        for width in hidden_sizes:
            layers += [nn.Linear(inputs, width), nn.ReLU()]
            inputs = width
        layers.append(nn.Linear(inputs, num_actions))
        self.layers = nn.Sequential(*layers)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.layers(observations.float())


def build_network(
    name: str,
    input_shape: tuple[int, ...],
    num_actions: int,
    is_image: bool,
    mlp_hidden_sizes: Sequence[int] = (256, 256),
) -> nn.Module:
    """`auto` picks the Nature CNN for images and the MLP for vectors."""
    if name == "auto":
        name = "nature_cnn" if is_image else "mlp"
    if name == "nature_cnn":
        if not is_image:
            raise ConfigError("network = 'nature_cnn' needs image observations; use mlp or auto")
        return NatureCNN(input_shape, num_actions)
    if name == "mlp":
        return MLP(input_shape, num_actions, mlp_hidden_sizes)
    if ":" not in name:
        raise ConfigError(
            f"network = {name!r} is not one of: auto, nature_cnn, mlp, or module:factory"
        )
    return _user_network(name, input_shape, num_actions, is_image)


def _user_network(
    name: str, input_shape: tuple[int, ...], num_actions: int, is_image: bool
) -> nn.Module:
    module_name, _, attribute = name.partition(":")
    try:
        factory = getattr(importlib.import_module(module_name), attribute)
    except (ImportError, AttributeError) as error:
        raise ConfigError(f"network = {name!r} cannot be loaded: {error}") from None
    try:
        network = factory(input_shape, num_actions)
    except Exception as error:  # noqa: BLE001 - the user's code: report, don't crash
        raise ConfigError(f"network factory {name!r} failed: {error!r}") from None
    if not isinstance(network, nn.Module):
        raise ConfigError(f"network factory {name!r} returned {type(network)}, not nn.Module")
    probe = torch.zeros((2, *input_shape), dtype=torch.uint8 if is_image else torch.float32)
    try:
        with torch.no_grad():
            q_values = network(probe)
    except Exception as error:  # noqa: BLE001
        raise ConfigError(
            f"network {name!r} fails on a batch of shape {tuple(probe.shape)} "
            f"({probe.dtype}): {error!r}"
        ) from None
    if tuple(q_values.shape) != (2, num_actions):
        raise ConfigError(
            f"network {name!r} returns shape {tuple(q_values.shape)} for a batch of 2; "
            f"expected (2, {num_actions})"
        )
    return network


def has_noise(network: nn.Module) -> bool:  # placeholder until the heads land
    return False


def sample_noise(network: nn.Module, generator: torch.Generator) -> None:  # placeholder
    return None
