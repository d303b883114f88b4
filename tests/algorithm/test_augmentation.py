"""The augmentation part: DrQ's random shift against frames shifted by hand, its draws from
the agent's generator (the same after a restore), and the part inside the update."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from dqnlab.algorithm.agent import agent_for_input
from dqnlab.algorithm.augmentation import (
    RandomShift,
    build_augmentation,
    shift,
    shift_by_gather,
    shift_by_slices,
)
from dqnlab.algorithm.replay import Batch
from dqnlab.config import resolve_config
from dqnlab.errors import ConfigError

# A 4x5 frame whose every pixel is different: 10 * row + column.
FRAME = torch.tensor([[10 * i + j for j in range(5)] for i in range(4)], dtype=torch.uint8)


# `shift` itself (slices on the CPU) and both ways to it: the gathers run on a GPU.
SHIFTS = [shift, shift_by_gather, shift_by_slices]


@pytest.mark.parametrize("shift", SHIFTS)
def test_shift_by_hand(shift) -> None:
    frames = FRAME.expand(2, 3, 4, 5)  # two observations of three stacked frames
    offsets = torch.tensor([[0, 2], [1, 0]])  # pad 1: (dy, dx) - 1 = (-1, +1) and (0, -1)
    shifted = shift(frames, offsets, pad=1)
    # Moved down one row (the top row repeated) and left one column (the last repeated).
    first = torch.tensor(
        [[1, 2, 3, 4, 4], [1, 2, 3, 4, 4], [11, 12, 13, 14, 14], [21, 22, 23, 24, 24]]
    )
    # Moved right one column, the first column repeated.
    second = torch.tensor(
        [[0, 0, 1, 2, 3], [10, 10, 11, 12, 13], [20, 20, 21, 22, 23], [30, 30, 31, 32, 33]]
    )
    assert shifted.dtype == torch.uint8
    for frame in range(3):
        assert torch.equal(shifted[0, frame], first.to(torch.uint8))
        assert torch.equal(shifted[1, frame], second.to(torch.uint8))
    assert torch.equal(shift(frames, torch.tensor([[1, 1], [1, 1]]), pad=1), frames)


@pytest.mark.parametrize("dtype", [torch.bool, torch.uint8, torch.float32])
def test_both_ways_shift_every_stored_dtype_alike(dtype: torch.dtype) -> None:
    # `shift` is public (a user's augmentation may call it on any frames); the CPU's
    # replicate padding has no bool kernel.
    generator = torch.Generator().manual_seed(5)
    frames = (torch.rand(5, 4, 10, 10, generator=generator) * 2).to(dtype)
    offsets = torch.randint(0, 9, (5, 2), generator=generator)
    slices = shift_by_slices(frames, offsets, pad=4)
    assert slices.dtype == dtype
    assert torch.equal(slices, shift_by_gather(frames, offsets, pad=4))
    assert torch.equal(shift(frames, torch.full((5, 2), 4), pad=4), frames)


@pytest.mark.parametrize("shift", SHIFTS)
def test_shift_is_replicate_padding_then_a_crop(shift) -> None:
    generator = torch.Generator().manual_seed(3)
    frames = torch.randint(0, 256, (6, 4, 84, 84), dtype=torch.uint8, generator=generator)
    offsets = torch.randint(0, 9, (6, 2), generator=generator)
    padded = F.pad(frames.float(), (4, 4, 4, 4), mode="replicate")
    expected = torch.stack(
        [padded[b, :, dy : dy + 84, dx : dx + 84] for b, (dy, dx) in enumerate(offsets.tolist())]
    )
    assert torch.equal(shift(frames, offsets, pad=4).float(), expected)


def test_random_shift_draws_each_offset_from_zero_to_twice_the_pad() -> None:
    config = resolve_config("drq_epsilon", env="pong")
    part = RandomShift(config)
    frames = torch.zeros(20_000, 1, 9, 9, dtype=torch.uint8)
    frames[:, :, 4, 4] = 1  # one lit pixel in the middle: where it lands gives the offset
    moved = part(frames, torch.Generator().manual_seed(0))
    rows, columns = (moved[:, 0] == 1).nonzero()[:, 1:].T
    # The lit pixel lands at (8 - dy, 8 - dx): every row and column means every offset.
    assert set(rows.tolist()) == set(range(9)) and set(columns.tolist()) == set(range(9))


def test_the_generator_decides_the_draws() -> None:
    config = resolve_config("drq_epsilon", env="pong")
    part = RandomShift(config)
    frames = torch.randint(0, 256, (32, 4, 84, 84), dtype=torch.uint8)
    generator = torch.Generator().manual_seed(7)
    state = generator.get_state()
    first, second = part(frames, generator), part(frames, generator)
    assert not torch.equal(first, second)  # current and next: independent draws
    generator.set_state(state)
    assert torch.equal(part(frames, generator), first)


def test_the_update_augments_observations_and_next_observations_independently() -> None:
    config = resolve_config("drq_epsilon", {"n_step": 1}, env="pong")
    agent = agent_for_input(config, (4, 84, 84), np.uint8, list("abcdef"), torch.device("cpu"), 0)
    seen: list[torch.Tensor] = []
    augment = agent.augmentation
    assert isinstance(augment, RandomShift)

    def recording(observations: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        seen.append(observations.clone())
        out = augment(observations, generator)
        seen.append(out)
        return out

    agent.augmentation = recording  # type: ignore[assignment]
    rng = np.random.default_rng(0)
    window = rng.integers(0, 256, (32, 5, 84, 84), dtype=np.uint8)
    batch = Batch(
        observations=None, next_observations=None, window=window,
        actions=np.zeros(32, np.int64), rewards=np.zeros(32, np.float32),
        terminals=np.zeros(32, np.float32), discounts=np.full(32, 0.99, np.float32),
    )  # fmt: skip
    agent.update(batch)
    observations, shifted, next_observations, next_shifted = seen
    assert torch.equal(observations, torch.from_numpy(window[:, :4]))
    assert torch.equal(next_observations, torch.from_numpy(window[:, 1:]))
    # The frames the two share moved differently: two draws, not one.
    assert not torch.equal(shifted[:, 1:], next_shifted[:, :3])


def test_augmentation_needs_images() -> None:
    config = resolve_config("classic", {"augmentation": "random_shift"}, env="CartPole-v1")
    with pytest.raises(ConfigError, match="augmentation = 'random_shift' shifts images"):
        agent_for_input(config, (4, 4), np.float32, ["left", "right"], torch.device("cpu"), 0)
    assert build_augmentation(resolve_config("classic", env="CartPole-v1"), False) is None


def test_an_unknown_augmentation_is_one_line() -> None:
    with pytest.raises(
        ConfigError, match="augmentation = 'crop' is not one of: none, random_shift"
    ):
        resolve_config("drq_epsilon", {"augmentation": "crop"}, env="pong")


class Flip:
    """A user's augmentation part: every image mirrored left to right."""

    def __init__(self, config: object) -> None:
        self.config = config

    def __call__(self, observations: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        return observations.flip(-1)


def test_a_users_augmentation_is_a_part() -> None:
    config = resolve_config(
        "drq_epsilon", {"augmentation": "tests.algorithm.test_augmentation:Flip"}, env="pong"
    )
    agent = agent_for_input(config, (4, 84, 84), np.uint8, list("abc"), torch.device("cpu"), 0)
    assert isinstance(agent.augmentation, Flip)
    broken = resolve_config("drq_epsilon", {"augmentation": "tests.nowhere:Flip"}, env="pong")
    with pytest.raises(ConfigError, match="augmentation = 'tests.nowhere:Flip' cannot be loaded"):
        agent_for_input(broken, (4, 84, 84), np.uint8, list("abc"), torch.device("cpu"), 0)


def test_the_augmentation_generator_is_saved_and_restored() -> None:
    config = resolve_config("drq_epsilon", env="pong")
    make = lambda: agent_for_input(  # noqa: E731
        config, (4, 84, 84), np.uint8, list("abc"), torch.device("cpu"), 1
    )
    agent = make()
    agent.augmentation_generator.manual_seed(99)
    restored = make()
    restored.load_state_dict(agent.state_dict())
    frames = torch.randint(0, 256, (8, 4, 84, 84), dtype=torch.uint8)
    assert agent.augmentation is not None and restored.augmentation is not None
    assert torch.equal(
        agent.augmentation(frames, agent.augmentation_generator),
        restored.augmentation(frames, restored.augmentation_generator),
    )
