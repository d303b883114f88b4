"""Observation layouts (`envs/spaces.py`), their encoders (`algorithm/encoders.py`) and the
networks `auto` picks for them, against values worked out by hand."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

from dqnlab.algorithm.encoders import ObservationEncoder, unpack
from dqnlab.algorithm.networks import (
    MLP,
    EncodedNetwork,
    NatureCNN,
    build_q_network,
    recorded_network_name,
)
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.config import resolve_config
from dqnlab.envs.generic import GymnasiumEnv
from dqnlab.envs.spaces import observation_layout
from dqnlab.errors import ConfigError, EnvError
from tests.envs import space_envs

NESTED = space_envs.NestedDictEnv.observation_space


def packed_frame(space: spaces.Space, observation, images: str = "auto") -> np.ndarray:
    layout = observation_layout(space, images)
    return layout.pack(observation, np.zeros(layout.frame_shape, layout.frame_dtype))


def test_a_nested_dict_is_laid_out_part_by_part_in_its_own_dtypes() -> None:
    layout = observation_layout(NESTED)
    assert layout.packed
    described = [(p.path, p.kind, p.shape, np.dtype(p.dtype)) for p in layout.parts]
    assert described == [  # Gymnasium sorts a Dict's keys
        ("clock", "vector", (1,), np.dtype(np.float32)),  # float64 read as float32
        ("grid", "image", (5, 5), np.dtype(np.bool_)),  # bool stays bool: 1 byte a cell
        ("meta/code", "onehot", (1,), np.dtype(np.uint8)),
        ("meta/where", "vector", (1,), np.dtype(np.bool_)),
    ]
    # 4 bytes of clock, 25 of grid, 1 code, 1 where: 31, rounded up to rows of 8 bytes.
    assert [p.offset for p in layout.parts] == [0, 4, 29, 30] and layout.row_bytes == 32


@pytest.mark.parametrize("name", sorted(space_envs.SPACE_ENVS))
def test_pack_then_unpack_gives_back_the_observation(name: str) -> None:
    env = space_envs.SPACE_ENVS[name]()
    space = env.observation_space
    space.seed(3)
    layout = observation_layout(space)
    for _ in range(5):
        observation = space.sample()
        frame = packed_frame(space, observation)
        flat = gym.spaces.flatten(space, observation)  # one-hots, as the encoder reads them
        for part, value in layout.unpack(frame):
            original = observation
            for key in filter(None, part.path.split("/")):
                original = original[int(key)] if isinstance(original, tuple) else original[key]
            if not layout.packed and layout.transpose:
                value = np.moveaxis(value, 0, -1)
            np.testing.assert_array_equal(value, np.asarray(original, dtype=value.dtype))
        assert flat.size > 0


def test_one_hot_parts_encode_their_value_and_a_zero_frame_encodes_nothing() -> None:
    space = spaces.Tuple((spaces.Discrete(3, start=-1), spaces.MultiDiscrete([2, 4])))
    layout = observation_layout(space)
    frame = packed_frame(space, (1, np.array([1, 2])))
    stacked = torch.from_numpy(np.stack([np.zeros_like(frame), frame]))[None]  # history 2
    features = ObservationEncoder(layout, history=2)(stacked)
    # Part by part, each its history's frames: the zero frame first, then the values
    # (Discrete(3) from -1: 1 is its third value; [1, 2] of [2, 4] categories).
    by_hand = [0, 0, 0] + [0, 0, 1] + [0, 0] + [0, 0, 0, 0] + [0, 1] + [0, 0, 1, 0]
    assert features.tolist() == [by_hand]


def test_torch_unpacking_gives_the_values_numpy_unpacking_gives() -> None:
    layout = observation_layout(NESTED)
    NESTED.seed(0)
    frames = np.stack([packed_frame(NESTED, NESTED.sample()) for _ in range(6)])
    parts = unpack(torch.from_numpy(frames.reshape(3, 2, -1)), layout)
    for (part, _), values in zip(layout.unpack(frames[0]), parts, strict=True):
        assert values.shape == (3, 2, *part.shape)
        expected = [dict(layout.unpack(frame))[part] for frame in frames]
        stored = np.stack(expected).reshape(3, 2, *part.shape)
        if part.kind == "onehot":  # torch sees the stored index (value - start + 1)
            stored = stored - np.asarray(part.start) + 1
        np.testing.assert_array_equal(values.numpy(), stored.astype(values.numpy().dtype))


@pytest.mark.parametrize(
    ("space", "images", "kind"),
    [
        (spaces.Box(0, 1, (6, 6, 3), np.float32), "auto", "image"),  # rank 3: an image
        (spaces.Box(0, 1, (6, 6), np.float32), "auto", "vector"),  # rank 2 float: a matrix
        (spaces.Box(0, 1, (6, 6), np.bool_), "auto", "image"),  # rank 2 bool: a grid
        (spaces.Box(0, 1, (6, 6), np.float32), "all", "image"),
        (spaces.Box(0, 1, (6, 6, 3), np.float32), "none", "vector"),
        (spaces.Box(0, 1, (2, 3, 4, 5), np.float32), "all", "vector"),  # rank 4: flattened
    ],
)
def test_how_a_box_is_read(space: spaces.Box, images: str, kind: str) -> None:
    assert observation_layout(space, images).parts[0].kind == kind


def test_channels_first_images_are_recognised_by_their_smallest_axis() -> None:
    last = observation_layout(spaces.Box(0, 1, (10, 12, 3), np.float32)).parts[0]
    first = observation_layout(spaces.Box(0, 1, (4, 10, 12), np.float32)).parts[0]
    assert last.channels_last and last.image_size == (3, 10, 12)
    assert not first.channels_last and first.image_size == (4, 10, 12)


def test_uint8_images_and_float_vectors_are_stored_as_before() -> None:
    image = observation_layout(spaces.Box(0, 255, (50, 40, 3), np.uint8))
    assert not image.packed and image.transpose and image.frame_shape == (3, 50, 40)
    vector = observation_layout(spaces.Box(-1, 1, (4,), np.float64))
    assert not vector.packed and vector.frame_dtype == np.float32 and vector.frame_shape == (4,)
    ints = observation_layout(spaces.Box(-5, 5, (4,), np.int16))  # no longer widened
    assert ints.packed and ints.parts[0].dtype == np.dtype(np.int16).str and ints.row_bytes == 8


def test_spaces_that_cannot_be_encoded_are_named_with_their_place() -> None:
    with pytest.raises(EnvError, match=r"Text \(at 'note' of the observation\) cannot be encoded"):
        GymnasiumEnv(space_envs.TextEnv(), seed=0)
    with pytest.raises(EnvError, match="Discrete action space.*Box"):
        GymnasiumEnv(space_envs.ContinuousActionEnv(), seed=0)
    multi = space_envs.CueEnv()
    multi.observation_space = spaces.Discrete(2)
    multi.action_space = spaces.MultiDiscrete([2, 2])
    with pytest.raises(EnvError, match="Discrete action space.*MultiDiscrete"):
        GymnasiumEnv(multi, seed=0)


def test_the_replays_memory_estimate_is_what_it_allocates() -> None:
    for space in (NESTED, spaces.Box(0, 1, (9, 9, 3), np.bool_)):
        layout = observation_layout(space)
        replay = ReplayMemory(
            1000, layout.frame_shape, layout.frame_dtype, history_length=2, batch_size=4, seed=0
        )
        allocated = sum(array.nbytes for array in replay.arrays.values())  # type: ignore[union-attr]
        assert replay.expected_bytes == allocated == replay.resident_bytes
    bool_image = observation_layout(spaces.Box(0, 1, (9, 9, 3), np.bool_))
    assert bool_image.row_bytes == 248  # 243 one-byte cells, never 4-byte floats


def test_auto_picks_a_network_by_the_observations_layout() -> None:
    config = resolve_config("classic", env="CartPole-v1")
    cases = {
        "small image": (spaces.Box(0, 1, (7, 7, 2), np.bool_), "small_cnn"),
        "large float image": (spaces.Box(0, 1, (40, 40, 1), np.float32), "auto"),
        "discrete": (spaces.Discrete(4), "auto"),
        "nested dict": (NESTED, "multi_input"),
    }
    for what, (space, recorded) in cases.items():
        layout = observation_layout(space)
        network = build_q_network(config, (1, *layout.frame_shape), 2, False, layout)
        assert isinstance(network, EncodedNetwork), what
        assert recorded_network_name("auto", False, layout) == recorded, what
        frames = torch.from_numpy(np.zeros((3, 1, *layout.frame_shape), layout.frame_dtype))
        assert network(frames).shape == (3, 2), what
    legacy_image = observation_layout(spaces.Box(0, 255, (84, 84), np.uint8))
    assert isinstance(build_q_network(config, (4, 84, 84), 2, True, legacy_image), NatureCNN)
    legacy_vector = observation_layout(spaces.Box(-1, 1, (4,), np.float32))
    assert isinstance(build_q_network(config, (1, 4), 2, False, legacy_vector), MLP)


def test_the_familys_heads_go_on_an_encoded_torso() -> None:
    config = dataclasses.replace(
        resolve_config("classic", env="CartPole-v1"),
        dueling=True, noisy=True, distributional="c51",
    )  # fmt: skip
    layout = observation_layout(NESTED)
    network = build_q_network(config, (2, *layout.frame_shape), 3, False, layout)
    frames = torch.zeros((5, 2, *layout.frame_shape), dtype=torch.uint8)
    assert network(frames).shape == (5, 3)


def test_networks_that_cannot_read_the_observation_are_refused() -> None:
    config = resolve_config("classic", env="CartPole-v1")
    layout = observation_layout(NESTED)
    for name in ("small_cnn", "nature_cnn"):
        with pytest.raises(ConfigError, match="needs observations that are one image"):
            build_q_network(dataclasses.replace(config, network=name), (1, 32), 2, False, layout)
    small = observation_layout(spaces.Box(0, 1, (7, 7), np.bool_))
    with pytest.raises(ConfigError, match="at least 36x36"):
        build_q_network(dataclasses.replace(config, network="nature_cnn"), (1, 56), 2, False, small)
