"""The algorithm's state: where the replay keeps its frames, and an exact state round trip."""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import torch

from dqnlab.algorithm.samplers import PrioritizedSampler, UniformSampler
from dqnlab.run.state import TrainingState, replay_device


def test_replay_frames_stay_on_the_host_on_cpu_unless_asked(cartpole) -> None:
    cpu = torch.device("cpu")
    assert replay_device(cartpole, cpu, (4,), np.dtype(np.float32)) is None  # auto
    host = dataclasses.replace(cartpole, replay_storage="host")
    assert replay_device(host, cpu, (4,), np.dtype(np.float32)) is None
    device = dataclasses.replace(cartpole, replay_storage="device")
    assert replay_device(device, cpu, (4,), np.dtype(np.float32)) == cpu


def test_a_state_loaded_into_a_fresh_one_steps_the_same(cartpole) -> None:
    config = dataclasses.replace(
        cartpole, replay_capacity=2000, replay_start_steps=50, target_update_steps=30
    )
    first = TrainingState(config, torch.device("cpu"))
    for _ in range(120):
        first.advance()
    second = TrainingState(config, torch.device("cpu"))
    saved = io.BytesIO()  # as a checkpoint stores it: no tensor shared between the two
    torch.save(first.state_dict(), saved)
    saved.seek(0)
    second.load_state_dict(torch.load(saved, weights_only=False))
    for name, array in first.replay.arrays.items():
        second.replay.arrays[name][...] = array
    games = [(first.advance(), second.advance()) for _ in range(200)]
    assert all(a == b for a, b in games)
    assert first.steps == second.steps == 320 and first.env.frames == second.env.frames
    for a, b in zip(first.agent.online.parameters(), second.agent.online.parameters(), strict=True):
        assert torch.equal(a, b)
    first.close()
    second.close()


def test_the_replay_is_built_with_the_configs_n_step_and_sampling(cartpole) -> None:
    config = dataclasses.replace(
        cartpole,
        replay_capacity=300,
        n_step=3,
        discount=0.9,
        replay_sampling="prioritized",
        priority_exponent=0.5,
        priority_epsilon=0.01,
    )
    state = TrainingState(config, torch.device("cpu"))
    replay = state.replay
    assert (replay.n_step, replay.discount) == (3, 0.9)
    assert isinstance(replay.sampler, PrioritizedSampler)
    assert (replay.sampler.priorities.exponent, replay.sampler.priorities.epsilon) == (0.5, 0.01)
    state.close()
    uniform = TrainingState(dataclasses.replace(cartpole, replay_capacity=300), torch.device("cpu"))
    assert isinstance(uniform.replay.sampler, UniformSampler) and uniform.replay.n_step == 1
    uniform.close()
