"""Networks: the Nature CNN's shape and initialisation, the MLP, and a user's own factory."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from dqnlab.algorithm.networks import MLP, NatureCNN, build_network
from dqnlab.errors import ConfigError


def test_nature_cnn_layers_and_flatten_size() -> None:
    network = NatureCNN((4, 84, 84), num_actions=6)
    convs = [m for m in network.modules() if isinstance(m, nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size, c.stride) for c in convs] == [
        (4, 32, (8, 8), (4, 4)), (32, 64, (4, 4), (2, 2)), (64, 64, (3, 3), (1, 1))
    ]  # fmt: skip
    linears = [m for m in network.modules() if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(3136, 512), (512, 6)]
    frames = torch.randint(0, 256, (5, 4, 84, 84), dtype=torch.uint8)
    assert network(frames).shape == (5, 6)
    # uint8 frames are scaled by 1/255 inside.
    torch.testing.assert_close(network(frames), network(frames.float() / 255 * 255))


def test_initialisation_is_uniform_within_one_over_sqrt_fan_in() -> None:
    torch.manual_seed(0)
    network = NatureCNN((4, 84, 84), num_actions=18)
    for module in network.modules():
        if isinstance(module, (nn.Conv2d, nn.Linear)):
            fan_in = module.weight[0].numel()
            bound = 1 / math.sqrt(fan_in)
            for tensor in (module.weight, module.bias):
                assert tensor.abs().max() <= bound
                assert tensor.abs().max() > 0.9 * bound  # spread over the whole interval


def test_images_with_channels_are_stacked_along_channels() -> None:
    network = NatureCNN((4, 3, 64, 48), num_actions=3)
    assert network.features[0].in_channels == 12
    assert network(torch.zeros(2, 4, 3, 64, 48, dtype=torch.uint8)).shape == (2, 3)


def test_auto_picks_cnn_for_images_and_mlp_for_vectors() -> None:
    assert isinstance(build_network("auto", (4, 84, 84), 4, is_image=True), NatureCNN)
    mlp = build_network("auto", (2, 5), 3, is_image=False, mlp_hidden_sizes=(7,))
    assert isinstance(mlp, MLP)
    assert [m.in_features for m in mlp.modules() if isinstance(m, nn.Linear)] == [10, 7]
    with pytest.raises(ConfigError, match="needs image observations"):
        build_network("nature_cnn", (1, 4), 2, is_image=False)


def tiny_factory(input_shape, num_actions):
    return nn.Sequential(nn.Flatten(), nn.Linear(math.prod(input_shape), num_actions))


def wrong_shape_factory(input_shape, num_actions):
    return nn.Sequential(nn.Flatten(), nn.Linear(math.prod(input_shape), num_actions + 1))


def test_user_factory() -> None:
    network = build_network(f"{__name__}:tiny_factory", (1, 4), 2, is_image=False)
    assert isinstance(network[1], nn.Linear) and network[1].out_features == 2
    with pytest.raises(ConfigError, match=r"expected \(2, 2\)"):
        build_network(f"{__name__}:wrong_shape_factory", (1, 4), 2, is_image=False)
    with pytest.raises(ConfigError, match="cannot be loaded"):
        build_network(f"{__name__}:missing", (1, 4), 2, is_image=False)
    with pytest.raises(ConfigError, match="auto, nature_cnn, mlp"):
        build_network("resnet", (1, 4), 2, is_image=False)


def failing_factory(input_shape, num_actions):
    raise ValueError("no such layer")


def wrong_input_factory(input_shape, num_actions):
    return nn.Linear(3, num_actions)  # expects 3 features, gets (batch, 1, 4)


def test_failures_of_user_code_and_tiny_images_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="failed: ValueError"):
        build_network(f"{__name__}:failing_factory", (1, 4), 2, is_image=False)
    with pytest.raises(ConfigError, match="fails on a batch of shape"):
        build_network(f"{__name__}:wrong_input_factory", (1, 4), 2, is_image=False)
    with pytest.raises(ConfigError, match="at least 36x36"):
        build_network("auto", (4, 16, 16), 2, is_image=True)


def test_channels_last_gives_the_values_of_the_default_layout() -> None:
    torch.manual_seed(1)
    network = NatureCNN((4, 84, 84), num_actions=5)
    frames = torch.randint(0, 256, (3, 4, 84, 84), dtype=torch.uint8)
    expected = network.head(network.features.to(memory_format=torch.contiguous_format)(
        frames.float() / 255.0
    ))  # fmt: skip
    network.features.to(memory_format=torch.channels_last)
    torch.testing.assert_close(network(frames), expected, rtol=1e-5, atol=1e-5)


def test_uint8_frames_are_scaled_in_float32_exactly_as_divided_by_255() -> None:
    torch.manual_seed(2)
    network = NatureCNN((4, 84, 84), num_actions=4)
    frames = torch.randint(0, 256, (6, 4, 84, 84), dtype=torch.uint8)
    scaled = (frames.float() / 255.0).contiguous(memory_format=torch.channels_last)
    assert torch.equal(network(frames), network.head(network.features(scaled)))
