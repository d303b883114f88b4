"""Samplers as parts (`replay_sampling = "module:Class"`): a user's sampler draws the
update's minibatches and is told its priorities; one that needs priorities makes the run
check the loss gives them; a wrong name is one line."""

from __future__ import annotations

import gc
import sys
import types
import weakref

import numpy as np
import pytest
import torch

from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.algorithm.samplers import (
    PrioritizedSampler,
    UniformSampler,
    build_sampler,
    needs_priorities,
)
from dqnlab.config import resolve_config
from dqnlab.errors import ConfigError
from dqnlab.run.state import TrainingState


class NewestFirst(UniformSampler):
    """Draws the batch from the newest valid transitions only, and counts what it hears."""

    NEEDS_PRIORITIES = True

    def __init__(self, config) -> None:  # noqa: ANN001
        super().__init__(config)
        self.window = int(config.batch_size) * 2
        self.written_slots: list[int] = []
        self.told: list[tuple[np.ndarray, np.ndarray]] = []

    def written(self, slot: int) -> None:
        self.written_slots.append(slot)

    def sample(self, step: int = 0):  # noqa: ANN201
        replay = self.replay
        newest = np.arange(replay.size - self.window, replay.size)
        valid = newest[replay.valid(newest)]
        return replay.gather(replay.rng.choice(valid, size=replay.batch_size))

    def tell(self, batch, priorities) -> None:  # noqa: ANN001
        self.told.append((batch.indices.copy(), priorities.detach().cpu().numpy()))


@pytest.fixture
def user_sampler(monkeypatch: pytest.MonkeyPatch) -> str:
    module = types.ModuleType("user_samplers")
    module.NewestFirst = NewestFirst  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "user_samplers", module)
    return "user_samplers:NewestFirst"


def test_a_users_sampler_draws_every_minibatch_and_hears_writes_and_priorities(
    user_sampler: str,
) -> None:
    config = resolve_config(
        "classic", env="CartPole-v1", replay_sampling=user_sampler, replay_start_steps=100,
        total_steps=300, replay_capacity=1000, mlp_hidden_sizes=[16],
    )  # fmt: skip
    assert needs_priorities(config)
    state = TrainingState(config, torch.device("cpu"))
    sampler = state.replay.sampler
    assert isinstance(sampler, NewestFirst) and sampler.replay.size == state.replay.size == 0
    for _ in range(300):
        state.advance()
    assert len(sampler.written_slots) == state.replay.writes
    assert len(sampler.told) == state.agent.updates == 100
    indices, priorities = sampler.told[-1]
    assert priorities.shape == (config.batch_size,) and (priorities >= 0).all()
    assert indices.min() >= state.replay.size - 2 * config.batch_size  # the newest only
    state.close()


def test_a_sampler_name_that_does_not_load_is_one_line() -> None:
    with pytest.raises(ConfigError, match="replay_sampling = 'ranked' is not one of: uniform"):
        resolve_config("classic", env="CartPole-v1", replay_sampling="ranked")
    config = resolve_config("classic", env="CartPole-v1", replay_sampling="no_such_mod:Sampler")
    with pytest.raises(ConfigError, match="replay_sampling = 'no_such_mod:Sampler' cannot be"):
        TrainingState(config, torch.device("cpu"))


def test_a_sampler_without_the_interface_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    module = types.ModuleType("user_samplers_2")
    module.Half = type("Half", (), {"__init__": lambda self, config: None, "sample": print})
    monkeypatch.setitem(sys.modules, "user_samplers_2", module)
    config = resolve_config("classic", env="CartPole-v1", replay_sampling="user_samplers_2:Half")
    with pytest.raises(ConfigError, match="has no bind, written, tell, state_dict") as error:
        build_sampler(config)
    assert "\n" not in str(error.value)


@pytest.mark.parametrize("sampler", [UniformSampler, PrioritizedSampler])
def test_a_replay_is_freed_as_soon_as_it_is_dropped(sampler) -> None:  # noqa: ANN001
    """The sampler holds its replay weakly: no cycle keeps a replay's memory until the
    garbage collector's next pass."""
    gc.disable()
    try:
        replay = ReplayMemory(100, (2, 2), np.uint8, 4, 8, 0, sampler=sampler())
        dropped = weakref.ref(replay)
        del replay
        assert dropped() is None
    finally:
        gc.enable()
