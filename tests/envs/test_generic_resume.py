"""A Gymnasium environment's state in a checkpoint: pickled where pickling keeps it, else its
episode replayed on a newly made environment, checked against the observation it reached."""

from __future__ import annotations

import io
import pickle
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch

from dqnlab.envs.generic import GymnasiumEnv, pickles_its_state
from tests.envs.replayed_envs import Drift, EzDrift, Locked, Loose


def lunar_lander() -> gym.Env:
    pytest.importorskip("Box2D")
    return gym.make("LunarLander-v3")


def ale_pong() -> gym.Env:
    """ale-py's own Gymnasium environment (EzPickle too), with sticky actions: its emulator
    draws from a generator of its own, which the episode's replay restores as well."""
    import ale_py

    gym.register_envs(ale_py)
    return gym.make("ALE/Pong-v5", obs_type="grayscale")


MAKERS = {
    "ezpickle": lambda: gym.wrappers.TimeLimit(EzDrift(), max_episode_steps=40),
    "unpicklable": lambda: Locked(),
    "lunar_lander": lunar_lander,
    "ale_pong": ale_pong,
}


def play(env: GymnasiumEnv, actions: list[int]) -> list[tuple[Any, ...]]:
    """Each step's outcome (a new episode where the last ended), as bytes and numbers."""
    outcomes = []
    for action in actions:
        if env.game_ended:
            outcomes.append(("reset", env.reset().tobytes()))
        observation, reward, terminal, truncated = env.step(action)
        outcomes.append((observation.tobytes(), reward, terminal, truncated))
    return outcomes


def through_a_checkpoint(state: dict[str, Any]) -> dict[str, Any]:
    """`state` saved and read back as a checkpoint's state.pt is (weights-only)."""
    saved = io.BytesIO()
    torch.save(state, saved)
    saved.seek(0)
    return torch.load(saved, weights_only=True)


@pytest.mark.parametrize("name", sorted(MAKERS))
@pytest.mark.parametrize("saved_after", ["37 steps", "an episode's end", "37 steps more"])
def test_an_environment_that_does_not_pickle_its_state_resumes_exactly(name, saved_after) -> None:
    make = MAKERS[name]
    first = GymnasiumEnv(make(), seed=11)
    actions = np.random.default_rng(4).integers(0, first.num_actions, 5000)
    played = 0
    if saved_after != "37 steps":  # to the first episode's end
        while not (played and first.game_ended):
            play(first, [int(actions[played])])
            played += 1
    if saved_after != "an episode's end":  # 37 steps into an episode, the first or the next
        play(first, [int(action) for action in actions[played : played + 37]])
        played += 37
    state = through_a_checkpoint(first.state_dict())
    assert state["env"] is None and state["episode"] is not None  # nothing pickled that lies
    second = GymnasiumEnv(make(), seed=11)  # as resume makes it: new, from the config
    second.load_state_dict(state)
    rest = [int(action) for action in actions[played : played + 600]]
    assert play(second, rest) == play(first, rest)  # across episode ends: the same stream


def test_what_pickling_keeps() -> None:
    assert pickles_its_state(gym.make("CartPole-v1"))
    assert pickles_its_state(Drift())
    assert not pickles_its_state(gym.wrappers.TimeLimit(EzDrift(), max_episode_steps=40))


def test_a_pickled_environment_keeps_no_episode_in_the_checkpoint() -> None:
    env = GymnasiumEnv(gym.make("CartPole-v1"), seed=0)
    play(env, [0, 1, 0])
    state = env.state_dict()
    assert state["env"] is not None and state["episode"] is None


def test_a_replay_that_does_not_repeat_starts_a_new_episode_and_says_so() -> None:
    first = GymnasiumEnv(Loose(), seed=2)
    play(first, [2] * 5)
    second = GymnasiumEnv(Loose(), seed=2)
    with pytest.warns(UserWarning, match="does not reach the observation saved"):
        second.load_state_dict(through_a_checkpoint(first.state_dict()))
    assert second.game_ended
    assert len(play(second, [1, 1])) == 3  # a reset, then two steps


@pytest.mark.parametrize("make", [Locked, EzDrift], ids=["unpicklable", "ezpickle"])
def test_an_older_checkpoint_without_the_episode_starts_a_new_one_and_says_so(make) -> None:
    first = GymnasiumEnv(make(), seed=2)
    play(first, [2] * 5)
    state = first.state_dict()
    del state["episode"]  # as checkpoints written before the replay have it
    if make is EzDrift:  # which pickled the constructor's arguments alone
        state["env"] = pickle.dumps(first.env)
    second = GymnasiumEnv(make(), seed=2)
    with pytest.warns(UserWarning, match="keeps no state of this environment"):
        second.load_state_dict(state)
    assert second.game_ended
    assert len(play(second, [1, 1])) == 3  # a reset first: never a step on an unreset env
