"""Networks: the Nature CNN's shape and initialisation, the MLP, a user's own factory, and the
DQN family's heads on every torso (the heads themselves: test_heads.py)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from torch import nn

from dqnlab.algorithm.heads import NoisyLinear, has_noise, sample_noise
from dqnlab.algorithm.networks import (
    MLP,
    DistributionalQNetwork,
    NatureCNN,
    QNetwork,
    build_network,
    build_q_network,
)
from dqnlab.config import resolve_config
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
    with pytest.raises(ConfigError, match="needs observations that are one image"):
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
    with pytest.raises(ConfigError, match="auto, nature_cnn, der_cnn, small_cnn, multi_input, mlp"):
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


# The DQN family's heads on every torso ----------------------------------------------------


def test_default_settings_build_todays_networks_from_the_same_seed(nature, cartpole) -> None:
    for config, input_shape, is_image, direct in [
        (nature, (4, 36, 36), True, lambda: NatureCNN((4, 36, 36), 6)),
        (cartpole, (1, 4), False, lambda: MLP((1, 4), 6, cartpole.mlp_hidden_sizes)),
    ]:
        torch.manual_seed(0)
        built = build_q_network(config, input_shape, 6, is_image)
        torch.manual_seed(0)
        expected = direct()
        assert type(built) is type(expected)
        assert list(built.state_dict()) == list(expected.state_dict())
        for name, tensor in expected.state_dict().items():
            assert torch.equal(built.state_dict()[name], tensor), name
    assert list(NatureCNN((4, 36, 36), 2).state_dict()) == [
        "features.0.weight", "features.0.bias", "features.2.weight", "features.2.bias",
        "features.4.weight", "features.4.bias", "head.0.weight", "head.0.bias",
        "head.2.weight", "head.2.bias",
    ]  # fmt: skip
    user = dataclasses.replace(cartpole, network=f"{__name__}:tiny_factory")
    assert isinstance(build_q_network(user, (1, 4), 2, is_image=False), nn.Sequential)


def tiny_torso(input_shape):
    return nn.Sequential(nn.Flatten(), nn.Linear(math.prod(input_shape), 5), nn.ReLU())


class ImageTorso(nn.Module):
    """A user's torso for uint8 images: it scales them itself, as the Nature torso does."""

    def __init__(self, input_shape) -> None:
        super().__init__()
        self.layers = nn.Sequential(nn.Flatten(), nn.Linear(math.prod(input_shape), 5))

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        return self.layers(frames.float() / 255.0)


HEADS = {
    "plain": {},
    "dueling": {"dueling": True},
    "noisy": {"noisy": True},
    "c51": {"distributional": "c51", "distributional_atoms": 7},
    "rainbow": {"dueling": True, "noisy": True, "distributional": "c51", "distributional_atoms": 7},
}
# (preset, input shape, is image, torso setting, hidden width of the head or None)
TORSOS = {
    "nature": ("nature", (4, 36, 36), True, "auto", 512),
    "mlp": ("classic", (2, 4), False, "auto", 256),
    "user_vectors": ("classic", (2, 4), False, f"{__name__}:tiny_torso", None),
    "user_images": ("nature", (4, 36, 36), True, f"{__name__}:ImageTorso", None),
}


@pytest.mark.parametrize("torso", TORSOS)
@pytest.mark.parametrize("head", HEADS)
def test_every_head_on_every_torso(head: str, torso: str) -> None:
    preset, input_shape, is_image, torso_setting, hidden = TORSOS[torso]
    config = resolve_config(preset, env="pong", torso=torso_setting, **HEADS[head])
    network = build_q_network(config, input_shape, 3, is_image)
    if head == "plain" and torso_setting == "auto":
        assert isinstance(network, (NatureCNN, MLP))  # today's network: tested above
        return
    assert isinstance(network, QNetwork)
    assert isinstance(network, DistributionalQNetwork) == (config.distributional == "c51")
    assert has_noise(network) == config.noisy
    linears = [m for m in network.head.modules() if isinstance(m, (nn.Linear, NoisyLinear))]
    atoms = 7 if config.distributional == "c51" else 1
    hidden_layer = [hidden] if hidden else []
    value_stream = hidden_layer + [atoms] if config.dueling else []
    expected_widths = value_stream + hidden_layer + [3 * atoms]
    assert [m.out_features for m in linears] == expected_widths
    sample_noise(network, torch.Generator().manual_seed(0))
    dtype = torch.uint8 if is_image else torch.float32
    inputs = torch.randint(0, 256, (5, *input_shape)).to(dtype)
    q_values = network(inputs)
    assert q_values.shape == (5, 3)
    q_values.sum().backward()
    assert all(p.grad is not None for p in network.parameters())
    if isinstance(network, DistributionalQNetwork):
        assert network.log_probabilities(inputs).shape == (5, 3, 7)


def test_the_mlp_torso_is_all_hidden_layers_but_the_last(cartpole) -> None:
    config = dataclasses.replace(cartpole, mlp_hidden_sizes=(7, 5), dueling=True)
    network = build_q_network(config, (2, 4), 3, is_image=False)
    torso = [m for m in network.torso.modules() if isinstance(m, nn.Linear)]
    head = [m for m in network.head.modules() if isinstance(m, nn.Linear)]
    assert [m.out_features for m in torso] == [7]
    assert [(m.in_features, m.out_features) for m in head] == [(7, 5), (5, 1), (7, 5), (5, 3)]
    bare = build_q_network(dataclasses.replace(config, mlp_hidden_sizes=()), (2, 4), 3, False)
    assert [m.in_features for m in bare.head.modules() if isinstance(m, nn.Linear)] == [8, 8]


def test_the_nature_torso_gives_the_nature_cnns_features(nature) -> None:
    torch.manual_seed(6)
    network = build_q_network(dataclasses.replace(nature, dueling=True), (4, 36, 36), 3, True)
    torch.manual_seed(6)
    cnn = NatureCNN((4, 36, 36), 3)  # the same convolutions from the same seed
    frames = torch.randint(0, 256, (2, 4, 36, 36), dtype=torch.uint8)
    assert torch.equal(network.torso(frames), cnn.features(_scaled(frames)))


def _scaled(frames: torch.Tensor) -> torch.Tensor:
    return (frames.float() / 255.0).contiguous(memory_format=torch.channels_last)


def test_c51_expected_q_values_and_log_probabilities_by_a_loop(cartpole) -> None:
    config = dataclasses.replace(
        cartpole, distributional="c51", distributional_atoms=5,
        distributional_v_min=-2.0, distributional_v_max=6.0, dueling=True,
    )  # fmt: skip
    torch.manual_seed(7)
    network = build_q_network(config, (1, 4), 3, is_image=False)
    assert network.support.tolist() == [-2.0, 0.0, 2.0, 4.0, 6.0]  # v_min + i dz, dz = 2
    assert network.atom_spacing == 2.0 and "support" not in network.state_dict()
    inputs = torch.randn(4, 1, 4) * 5
    with torch.no_grad():
        logits = network.logits(inputs)
        log_probabilities = network.log_probabilities(inputs)
        q_values = network(inputs)
        q_once, log_once = network.forward_with_log_probabilities(inputs)
    assert torch.equal(q_once, q_values) and torch.equal(log_once, log_probabilities)
    torch.testing.assert_close(log_probabilities.exp().sum(dim=2), torch.ones(4, 3))
    torch.testing.assert_close(log_probabilities, torch.log(torch.softmax(logits, dim=2)))
    for b in range(4):
        for a in range(3):
            row = logits[b, a].tolist()
            total = sum(math.exp(x) for x in row)
            support = network.support.tolist()
            expected = sum(z * math.exp(x) / total for z, x in zip(support, row, strict=True))
            assert q_values[b, a].item() == pytest.approx(expected, rel=1e-5, abs=1e-6)


def test_log_probabilities_stay_finite_where_a_probability_vanishes(cartpole) -> None:
    config = dataclasses.replace(cartpole, distributional="c51", mlp_hidden_sizes=())
    network = build_q_network(config, (1, 4), 2, is_image=False)
    with torch.no_grad():
        network.head.outputs[0].weight.zero_()
        network.head.outputs[0].bias.copy_(torch.arange(102.0) * 10)  # logits 0 .. 1010
        log_probabilities = network.log_probabilities(torch.zeros(1, 1, 4))
    assert torch.isfinite(log_probabilities).all()
    assert log_probabilities[0, 0, 0].item() == pytest.approx(-500.0)  # log(softmax) gives -inf


def test_a_noisy_network_acts_on_its_means_in_eval_mode(cartpole) -> None:
    network = build_q_network(dataclasses.replace(cartpole, noisy=True), (1, 4), 2, False)
    inputs = torch.randn(3, 1, 4)
    with torch.no_grad():
        before = network.eval()(inputs)
        sample_noise(network, torch.Generator().manual_seed(0))
        assert torch.equal(network.eval()(inputs), before)
        assert not torch.equal(network.train()(inputs), before)


def failing_torso(input_shape):
    raise ValueError("no such layer")


def three_d_torso(input_shape):
    return nn.Identity()  # (batch, history, 4): not flat


def not_a_module_torso(input_shape):
    return "a string"


@pytest.mark.parametrize(
    ("factory", "message"),
    [
        ("failing_torso", r"torso factory '.*' failed: ValueError"),
        ("three_d_torso", r"torso '.*' returns shape \(2, 1, 4\) .*expected \(2, features\)"),
        ("not_a_module_torso", r"torso factory '.*' returned <class 'str'>, not nn.Module"),
        ("missing", r"torso = '.*' cannot be loaded"),
        ("tiny_factory", r"torso factory '.*' failed: TypeError"),  # a network's signature
    ],
)
def test_a_torso_that_fails_is_a_one_line_config_error(cartpole, factory, message) -> None:
    config = dataclasses.replace(cartpole, torso=f"{__name__}:{factory}")
    with pytest.raises(ConfigError, match=message) as error:
        build_q_network(config, (1, 4), 2, is_image=False)
    assert "\n" not in str(error.value)


def test_der_cnn_is_data_efficient_rainbows_network() -> None:
    network = build_network("der_cnn", (4, 84, 84), 6, is_image=True)
    convs = [m for m in network.modules() if isinstance(m, nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size, c.stride) for c in convs] == [
        (4, 32, (5, 5), (5, 5)), (32, 64, (5, 5), (5, 5))
    ]  # fmt: skip
    linears = [m for m in network.modules() if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(576, 256), (256, 6)]
    frames = torch.randint(0, 256, (3, 4, 84, 84), dtype=torch.uint8)
    features = nn.functional.relu(convs[1](nn.functional.relu(convs[0](frames.float() / 255))))
    torch.testing.assert_close(network.torso(frames), features.flatten(1))
    assert network(frames).shape == (3, 6)


@pytest.mark.parametrize(
    ("head", "widths"),
    [("plain", [256, 6]), ("rainbow", [256, 7, 256, 6 * 7])],
)
def test_der_cnn_takes_the_family_heads_with_256_hidden_units(head: str, widths) -> None:
    config = resolve_config("nature", env="pong", network="der_cnn", **HEADS[head])
    network = build_q_network(config, (4, 84, 84), 6, is_image=True)
    linears = [m for m in network.modules() if isinstance(m, (nn.Linear, NoisyLinear))]
    assert [m.out_features for m in linears] == widths
    assert linears[0].in_features == 576


def test_der_cnn_refuses_what_it_cannot_read() -> None:
    with pytest.raises(ConfigError, match=r"der_cnn' needs images of at least 25x25 pixels"):
        build_network("der_cnn", (4, 20, 20), 3, is_image=True)
    with pytest.raises(ConfigError, match="der_cnn' needs observations that are one image"):
        build_network("der_cnn", (4, 8), 3, is_image=False)


def test_the_same_unchanged_frames_are_converted_once_and_changed_frames_again(
    monkeypatch,
) -> None:
    """Double DQN's two passes on s' share one conversion of the frames; an in-place change
    to them, another tensor, or other autograd modes convert afresh; the values are those
    of a conversion every time."""
    from dqnlab.algorithm import image_networks

    conversions = []
    converted = image_networks._converted
    monkeypatch.setattr(
        image_networks, "_converted", lambda frames: conversions.append(1) or converted(frames)
    )
    monkeypatch.setattr(image_networks, "_last_planes", None)
    frames = torch.randint(0, 256, (2, 4, 84, 84), dtype=torch.uint8)
    first = image_networks._scaled_planes(frames)
    assert image_networks._scaled_planes(frames) is first and len(conversions) == 1
    assert torch.equal(first, converted(frames))
    frames[0, 0, 0, 0] ^= 1  # in place: a new version
    changed = image_networks._scaled_planes(frames)
    assert len(conversions) == 2 and torch.equal(changed, converted(frames))
    with torch.no_grad():  # another autograd mode
        image_networks._scaled_planes(frames)
    with torch.inference_mode():
        image_networks._scaled_planes(frames)
    image_networks._scaled_planes(frames.clone())  # another tensor, the same values
    assert len(conversions) == 5
    with torch.inference_mode():  # acting's frames, made in inference mode: no version
        acting = torch.randint(0, 256, (1, 4, 84, 84), dtype=torch.uint8)
        image_networks._scaled_planes(acting)
        assert torch.equal(image_networks._scaled_planes(acting), converted(acting))
    assert len(conversions) == 7
