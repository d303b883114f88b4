"""Q-networks: the Nature CNN for images, or Data-efficient Rainbow's two-convolution network
(`der_cnn`, Atari 100k; both in `image_networks.py`), an MLP for vectors, a small CNN for
small images, a network over every part of a structured observation, a user's own network,
or a torso with the DQN family's heads.

A network takes a batch of stacked observations of shape (batch, history, *frame_shape)
in their stored dtype (uint8 images are scaled by 1/255 inside) and returns one Q-value
per action. `build_q_network` builds the one a configuration asks for:

- with every head setting at its default (the Nature DQN) the network of `build_network`:
  `NatureCNN`, `MLP` or the user's `network = module:factory`, built exactly as before the
  heads existed, so that a seed gives the same parameters and older network files load;
- otherwise a `QNetwork`: a torso (`NatureTorso`, `MLPTorso`, or the user's
  `torso = module:factory`) under a head (`heads.build_head`: dueling, noisy and C51 as
  the settings say, or the user's `head = module:factory`); a `DistributionalQNetwork`
  with C51's head.

Observations other than a uint8 image or a float vector come packed (`envs/spaces.py`):
their networks read them through `encoders.ObservationEncoder` (`EncodedNetwork`), as does
the small CNN. `auto` picks by the observation's layout (`_network_name`).

A user's network factory is called as `factory(input_shape, num_actions)` and a torso
factory as `factory(input_shape)`, with `input_shape = (history, *frame_shape)`; each
returns a `torch.nn.Module`, the network giving (batch, num_actions) and the torso
(batch, features).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import nn

from dqnlab.algorithm.encoders import SMALL_CNN_HIDDEN_WIDTH, ObservationEncoder, is_small
from dqnlab.algorithm.heads import CategoricalHead, QHead, build_head, head_q_values
from dqnlab.algorithm.image_networks import (
    DATA_EFFICIENT_HIDDEN_WIDTH,
    NATURE_HIDDEN_WIDTH,
    DataEfficientCNN,
    DataEfficientTorso,
    NatureCNN,
    NatureTorso,
)
from dqnlab.config import Config
from dqnlab.envs.spaces import ObservationLayout
from dqnlab.errors import ConfigError
from dqnlab.parts import load_object


class MLP(nn.Module):
    """Fully connected Q-network for vector observations (histories are concatenated)."""

    def __init__(
        self, input_shape: Sequence[int], num_actions: int, hidden_sizes: Sequence[int]
    ) -> None:
        super().__init__()
        hidden, width = _hidden_layers(math.prod(input_shape), hidden_sizes)
        self.layers = nn.Sequential(nn.Flatten(), *hidden, nn.Linear(width, num_actions))

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.layers(observations.float())


class MLPTorso(nn.Module):
    """The MLP's hidden layers: `output_size` features per input (the inputs flattened when
    `hidden_sizes` is empty)."""

    def __init__(self, input_shape: Sequence[int], hidden_sizes: Sequence[int]) -> None:
        super().__init__()
        hidden, self.output_size = _hidden_layers(math.prod(input_shape), hidden_sizes)
        self.layers = nn.Sequential(nn.Flatten(), *hidden)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.layers(observations.float())


class EncodedNetwork(nn.Module):
    """An observation encoder (`encoders.ObservationEncoder`), hidden layers of
    `hidden_sizes` units with ReLU, and one Q-value per action."""

    def __init__(
        self, encoder: ObservationEncoder, num_actions: int, hidden_sizes: Sequence[int]
    ) -> None:
        super().__init__()
        self.encoder = encoder
        hidden, width = _hidden_layers(encoder.output_size, hidden_sizes)
        self.layers = nn.Sequential(*hidden, nn.Linear(width, num_actions))

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.layers(self.encoder(observations))


class EncodedTorso(nn.Module):
    """An observation encoder and hidden layers: `output_size` features per input."""

    def __init__(self, encoder: ObservationEncoder, hidden_sizes: Sequence[int]) -> None:
        super().__init__()
        self.encoder = encoder
        hidden, self.output_size = _hidden_layers(encoder.output_size, hidden_sizes)
        self.layers = nn.Sequential(*hidden)

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return self.layers(self.encoder(observations))


def _hidden_layers(inputs: int, widths: Sequence[int]) -> tuple[list[nn.Module], int]:
    """Linear layers of `widths` units with ReLU, and the width of the last."""
    layers: list[nn.Module] = []
    for width in widths:
        layers += [nn.Linear(inputs, width), nn.ReLU(inplace=True)]
        inputs = width
    return layers, inputs


class QNetwork(nn.Module):
    """A torso and a head (`heads.py`): `outputs` gives the head's outputs per action
    (batch, actions, k), which the loss part reads, and `forward` the Q-values
    (batch, actions) acting and evaluation use (the head's `q_values`; for C51, the
    expected returns of its distributions)."""

    def __init__(self, torso: nn.Module, head: nn.Module) -> None:
        super().__init__()
        self.torso = torso
        self.head = head

    def outputs(self, observations: torch.Tensor) -> torch.Tensor:
        outputs: torch.Tensor = self.head(self.torso(observations))
        return outputs

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return head_q_values(self.head, self.outputs(observations))


class DistributionalQNetwork(QNetwork):
    """A `QNetwork` with C51's head (`heads.CategoricalHead`; Bellemare et al. 2017,
    dqn-family.md 5.1): per action, a categorical distribution of the return on the atoms
    `support` (atoms,), z_i = v_min + i dz.

    `forward` gives the expected returns sum_i z_i p_i (batch, actions), so that acting,
    evaluation, the held-out statistics and `dqnlab inspect` use it as any Q-network. The
    loss takes `log_probabilities` (batch, actions, atoms), or both from one pass of the
    torso with `forward_with_log_probabilities` (a target's greedy action and its
    distribution, say)."""

    head: CategoricalHead

    def __init__(self, torso: nn.Module, head: CategoricalHead) -> None:
        super().__init__(torso, head)

    @property
    def support(self) -> torch.Tensor:
        return self.head.support

    @property
    def atom_spacing(self) -> float:
        return self.head.atom_spacing

    def logits(self, observations: torch.Tensor) -> torch.Tensor:
        """Logits of the return distributions, (batch, actions, atoms)."""
        return self.outputs(observations)

    def log_probabilities(self, observations: torch.Tensor) -> torch.Tensor:
        """log p_i per action (`CategoricalHead.log_probabilities`), (batch, actions, atoms)."""
        return self.head.log_probabilities(self.outputs(observations))

    def forward_with_log_probabilities(
        self, observations: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """`forward` and `log_probabilities` from one pass of the torso and head."""
        logits = self.outputs(observations)
        return self.head.q_values(logits), self.head.log_probabilities(logits)


# Modules whose forward is a function of their weights and input alone, the same in either
# mode, with no draws and no state of their own: exact types, since a subclass may override
# forward. Noisy layers, dropout, batch norm and a user's modules are not among them.
_FUNCTIONAL_MODULES = frozenset(
    {
        nn.Sequential, nn.Conv2d, nn.Linear, nn.ReLU, nn.Flatten, nn.Identity,
        NatureCNN, NatureTorso, DataEfficientCNN, DataEfficientTorso, MLP, MLPTorso,
        QNetwork, QHead,
    }
)  # fmt: skip


def computes_a_function(network: nn.Module) -> bool:
    """Whether every module of `network` is one of `_FUNCTIONAL_MODULES`: two networks with
    the same weights then give the same bits for the same input, in any mode."""
    return all(type(module) in _FUNCTIONAL_MODULES for module in network.modules())


def build_q_network(
    config: Config,
    input_shape: tuple[int, ...],
    num_actions: int,
    is_image: bool,
    layout: ObservationLayout | None = None,
) -> nn.Module:
    """The Q-network `config` asks for, for inputs of `input_shape` (history, *observation
    shape) and `num_actions` actions: `build_network`'s network when every head setting
    (dueling, noisy, distributional, torso, head) holds its default, else a torso with a
    head.
    `layout`: the observation's (`envs/spaces.py`); None: a single frame, an image when
    `is_image`, else a vector."""
    if not _has_torso_and_head(config):
        return build_network(
            config.network, input_shape, num_actions, is_image, config.mlp_hidden_sizes, layout
        )
    torso = build_torso(config, input_shape, is_image, layout)
    head = build_head(config, torso.output_size, num_actions, torso.head_hidden_width)
    if isinstance(head, CategoricalHead):
        return DistributionalQNetwork(torso.module, head)
    return QNetwork(torso.module, head)


def _has_torso_and_head(config: Config) -> bool:
    """Whether a head setting differs from its default (the Nature DQN's network)."""
    return (
        config.dueling
        or config.noisy
        or config.distributional != "none"
        or config.torso != "auto"
        or config.head != "auto"
    )


class Torso(NamedTuple):
    """A torso, the features it gives per input, and the width of the hidden layer of the
    head put on it (None: no hidden layer)."""

    module: nn.Module
    output_size: int
    head_hidden_width: int | None


def build_torso(
    config: Config,
    input_shape: tuple[int, ...],
    is_image: bool,
    layout: ObservationLayout | None = None,
) -> Torso:
    """The torso of `config`: the user's `torso = module:factory` (its head has no hidden
    layer), or that of the network setting: the Nature CNN's convolutions (its head the
    Nature CNN's layer of 512), the small CNN's convolution (its head the layer of 128), or
    the MLP's hidden layers but the last (its head that)."""
    if config.torso != "auto":
        module, probe = _user_module(
            "torso", config.torso, (input_shape,), input_shape, _probe_dtype(is_image, layout)
        )
        if probe.ndim != 2 or probe.shape[0] != 2 or probe.shape[1] == 0:
            raise ConfigError(
                f"torso {config.torso!r} returns shape {tuple(probe.shape)} for a batch of 2; "
                "expected (2, features)"
            )
        return Torso(module, int(probe.shape[1]), None)
    name = _network_name(config.network, is_image, layout)
    if name in ENCODED_NETWORKS or (layout is not None and layout.packed):
        assert layout is not None
        widths = _encoded_widths(name, config.mlp_hidden_sizes)
        encoder = _encoder(name, layout, input_shape[0])
        torso = EncodedTorso(encoder, widths[:-1])
        return Torso(torso, torso.output_size, widths[-1] if widths else None)
    if name == "nature_cnn":
        nature = NatureTorso(input_shape)
        return Torso(nature, nature.output_size, NATURE_HIDDEN_WIDTH)
    if name == "der_cnn":
        data_efficient = DataEfficientTorso(input_shape)
        return Torso(data_efficient, data_efficient.output_size, DATA_EFFICIENT_HIDDEN_WIDTH)
    if name == "mlp":
        widths = config.mlp_hidden_sizes
        mlp = MLPTorso(input_shape, widths[:-1])
        return Torso(mlp, mlp.output_size, widths[-1] if widths else None)
    # Config refuses a head on a whole network of the user's (`network = module:factory`).
    raise ConfigError(f"network = {config.network!r} has no torso to put a head on")


def build_network(
    name: str,
    input_shape: tuple[int, ...],
    num_actions: int,
    is_image: bool,
    mlp_hidden_sizes: Sequence[int] = (256, 256),
    layout: ObservationLayout | None = None,
) -> nn.Module:
    """The network setting's Q-network (`auto`: `_network_name`)."""
    name = _network_name(name, is_image, layout)
    if name in ENCODED_NETWORKS or (layout is not None and layout.packed and ":" not in name):
        assert layout is not None
        encoder = _encoder(name, layout, input_shape[0])
        return EncodedNetwork(encoder, num_actions, _encoded_widths(name, mlp_hidden_sizes))
    if name == "nature_cnn":
        return NatureCNN(input_shape, num_actions)
    if name == "der_cnn":
        return DataEfficientCNN(input_shape, num_actions)
    if name == "mlp":
        return MLP(input_shape, num_actions, mlp_hidden_sizes)
    network, probe = _user_module(
        "network", name, (input_shape, num_actions), input_shape, _probe_dtype(is_image, layout)
    )
    if tuple(probe.shape) != (2, num_actions):
        raise ConfigError(
            f"network {name!r} returns shape {tuple(probe.shape)} for a batch of 2; "
            f"expected (2, {num_actions})"
        )
    return network


# Networks that read their input through `encoders.ObservationEncoder` whatever the layout.
ENCODED_NETWORKS = ("small_cnn", "multi_input")
NETWORK_NAMES = ("auto", "nature_cnn", "der_cnn", "small_cnn", "multi_input", "mlp")


def recorded_network_name(name: str, is_image: bool, layout: ObservationLayout | None) -> str:
    """The network setting a new run records: `auto` written out as the network it chose
    when that is one of `ENCODED_NETWORKS` (the small CNN, multi_input: added for small
    images and structured observations), so that the run's config says which ran; else
    the setting as given (older runs' `auto` stays `auto`)."""
    if name != "auto":
        return name
    chosen = _network_name(name, is_image, layout)
    return chosen if chosen in ENCODED_NETWORKS else name


def _network_name(name: str, is_image: bool, layout: ObservationLayout | None = None) -> str:
    """The network setting with `auto` resolved; refuses a network that cannot read the
    observation, and unknown names.

    `auto`: a single image, the Nature CNN when both sides are at least 36 pixels, else
    the small CNN; no image, the MLP; images among other parts, `multi_input` (an encoder
    per part, then the MLP's hidden layers)."""
    images = layout.images if layout is not None else ()
    single_image = (len(layout.parts) == 1 and len(images) == 1) if layout else is_image
    if name == "auto":
        if single_image:
            return "small_cnn" if images and is_small(images[0]) else "nature_cnn"
        return "multi_input" if images else "mlp"
    if name not in NETWORK_NAMES and ":" not in name:
        raise ConfigError(
            f"network = {name!r} is not one of: {', '.join(NETWORK_NAMES)}, or module:factory"
        )
    if name in ("nature_cnn", "der_cnn", "small_cnn") and not single_image:
        raise ConfigError(
            f"network = {name!r} needs observations that are one image; use multi_input or auto"
        )
    if name == "der_cnn" and layout is not None and layout.packed:
        raise ConfigError(
            "network = 'der_cnn' reads one uint8 image (Atari's frames); this observation is "
            "stored packed: use small_cnn, multi_input or auto"
        )
    if name == "small_cnn" and layout is None:
        raise ConfigError("network = 'small_cnn' needs the observation's layout")
    return name


def _encoder(name: str, layout: ObservationLayout, history: int) -> ObservationEncoder:
    small = {"small_cnn": True, "nature_cnn": False}.get(name)
    try:
        return ObservationEncoder(layout, history, small_images=small)
    except ValueError as error:
        raise ConfigError(f"network = {name!r}: {error}") from None


def _encoded_widths(name: str, mlp_hidden_sizes: Sequence[int]) -> tuple[int, ...]:
    """The hidden layers after the encoder: MinAtar's 128 for the small CNN, the Nature
    CNN's 512 for a packed image through its convolutions, else the MLP's."""
    if name == "small_cnn":
        return (SMALL_CNN_HIDDEN_WIDTH,)
    if name == "nature_cnn":
        return (NATURE_HIDDEN_WIDTH,)
    return tuple(mlp_hidden_sizes)


def _probe_dtype(is_image: bool, layout: ObservationLayout | None) -> torch.dtype:
    if layout is not None and layout.packed:
        return torch.uint8
    return torch.uint8 if is_image else torch.float32


def _user_module(
    setting: str,
    name: str,
    arguments: tuple[object, ...],
    input_shape: tuple[int, ...],
    probe_dtype: torch.dtype,
) -> tuple[nn.Module, torch.Tensor]:
    """The module `factory(*arguments)` of the setting's `module:factory`, and its output for
    a probe batch of 2 zero inputs in the stored dtype; the user's code failing in any way
    is a one-line ConfigError naming the setting."""
    factory = load_object(setting, name)
    try:
        module = factory(*arguments)
    except Exception as error:  # noqa: BLE001 - the user's code: report, don't crash
        raise ConfigError(f"{setting} factory {name!r} failed: {error!r}") from None
    if not isinstance(module, nn.Module):
        raise ConfigError(f"{setting} factory {name!r} returned {type(module)}, not nn.Module")
    probe = torch.zeros((2, *input_shape), dtype=probe_dtype)
    try:
        with torch.no_grad():
            output = module(probe)
    except Exception as error:  # noqa: BLE001
        raise ConfigError(
            f"{setting} {name!r} fails on a batch of shape {tuple(probe.shape)} "
            f"({probe.dtype}): {error!r}"
        ) from None
    if not isinstance(output, torch.Tensor):
        raise ConfigError(f"{setting} {name!r} returns {type(output)}, not a tensor")
    return module, output
