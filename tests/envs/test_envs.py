"""Non-Atari environments through Gymnasium (envs/generic.py) and `make_env` (envs/__init__.py)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from dqnlab.config import Config
from dqnlab.envs import check_env_name, is_atari, make_env
from dqnlab.envs.generic import GymnasiumEnv
from dqnlab.errors import EnvError


class TinyImageEnv(gym.Env):
    """6x5 RGB images: pixel (h, w, c) after t steps is 15h + 3w + c + t. Never ends itself.

    The reward is the action it received, to show how actions are mapped.
    """

    def __init__(self, action_start: int = 0) -> None:
        self.observation_space = gym.spaces.Box(0, 255, (6, 5, 3), np.uint8)
        self.action_space = gym.spaces.Discrete(3, start=action_start)
        self.t = 0

    def _observation(self) -> np.ndarray:
        return (np.arange(90).reshape(6, 5, 3) + self.t).astype(np.uint8)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self._observation(), {}

    def step(self, action):
        self.t += 1
        return self._observation(), float(action), False, False, {}


class DictObservationEnv(TinyImageEnv):
    def __init__(self) -> None:
        super().__init__()
        self.observation_space = gym.spaces.Dict({"image": self.observation_space})


def not_an_env() -> int:
    return 42


TINY = f"{TinyImageEnv.__module__}:TinyImageEnv"
TINY_ID = "DqnlabTest/TinyImage-v0"
if TINY_ID not in gym.registry:
    gym.register(TINY_ID, entry_point=TinyImageEnv, max_episode_steps=4)


def by_hand_tiny_observation(t: int) -> np.ndarray:
    """Channels-first: element (c, h, w) is 15h + 3w + c + t."""
    return np.fromfunction(lambda c, h, w: 15 * h + 3 * w + c + t, (3, 6, 5)).astype(np.uint8)


def test_cartpole_gives_float32_vectors_and_two_actions():
    env = make_env(Config(env="CartPole-v1"), training=True, seed=3)
    assert isinstance(env, GymnasiumEnv)
    assert env.observation_shape == (4,)
    assert env.observation_dtype == np.float32
    assert env.num_actions == 2
    assert len(env.action_names) == 2
    observation = env.reset()
    assert observation.shape == (4,) and observation.dtype == np.float32
    direct, _ = gym.make("CartPole-v1").reset(seed=3)
    assert np.array_equal(observation, direct.astype(np.float32))
    observation, reward, terminated, truncated = env.step(1)
    assert observation.dtype == np.float32
    assert (reward, terminated, truncated) == (1.0, False, False)
    assert env.frames == 1  # for a non-Atari environment a frame is a step


def test_seed_fixes_the_first_observation():
    def first(seed):
        return make_env(Config(env="CartPole-v1"), training=True, seed=seed).reset().copy()

    assert np.array_equal(first(5), first(5))
    assert not np.array_equal(first(5), first(6))


def test_module_class_entry_point_gives_channels_first_images():
    env = make_env(Config(env=TINY), training=True, seed=0)
    assert env.observation_shape == (3, 6, 5)
    assert env.observation_dtype == np.uint8
    assert env.num_actions == 3
    observation = env.reset()
    assert observation.shape == (3, 6, 5) and observation.dtype == np.uint8
    assert observation[2, 1, 0] == 17 and observation[0, 5, 4] == 87
    assert np.array_equal(observation, by_hand_tiny_observation(0))
    observation, reward, terminated, truncated = env.step(2)
    assert np.array_equal(observation, by_hand_tiny_observation(1))
    assert (reward, terminated, truncated) == (2.0, False, False)


def test_actions_are_shifted_to_the_space_start():
    env = GymnasiumEnv(TinyImageEnv(action_start=-1), seed=0)
    env.reset()
    assert [env.step(a)[1] for a in range(3)] == [-1.0, 0.0, 1.0]


def test_time_limit_is_truncation_not_termination():
    env = make_env(Config(env=TINY_ID), training=True, seed=0)
    env.reset()
    results = [env.step(0)[2:] for _ in range(4)]
    assert results == [(False, False)] * 3 + [(False, True)]
    assert env.game_ended
    env.reset()
    assert not env.game_ended
    cartpole = GymnasiumEnv(gym.make("CartPole-v1", max_episode_steps=3), seed=0)
    cartpole.reset()
    assert [cartpole.step(a)[2:] for a in (0, 1, 0)] == [(False, False)] * 2 + [(False, True)]


def test_episode_cap_from_the_config_truncates():
    env = make_env(Config(env=TINY), training=False, seed=0, max_episode_frames=2)
    env.reset()
    assert [env.step(0)[2:] for _ in range(2)] == [(False, False), (False, True)]
    assert env.game_ended


def test_termination_wins_over_a_time_limit_on_the_same_step():
    env = GymnasiumEnv(gym.make("CartPole-v1"), seed=0)
    env.reset()
    steps = 0
    while True:
        steps += 1
        _, _, terminated, truncated = env.step(0)  # always push left: falls in a few steps
        if terminated:
            break
        assert not truncated
    assert env.game_ended and steps < 30
    same_step = GymnasiumEnv(gym.make("CartPole-v1", max_episode_steps=steps), seed=0)
    same_step.reset()
    results = [same_step.step(0)[2:] for _ in range(steps)]
    assert results[-1] == (True, False)


@pytest.mark.parametrize("name", ["Pendulum-v1", "MountainCarContinuous-v0"])
def test_continuous_actions_are_refused(name):
    with pytest.raises(EnvError, match="Discrete action space"):
        make_env(Config(env=name), training=True, seed=0)
    with pytest.raises(EnvError, match="Discrete action space"):
        check_env_name(name)


@pytest.mark.parametrize(
    ("name", "suggestion"), [("pongg", "pong"), ("CartPole-v9", "CartPole-v1")]
)
def test_unknown_names_suggest_close_matches(name, suggestion):
    with pytest.raises(EnvError) as error:
        make_env(Config(env=name), training=True, seed=0)
    message = str(error.value)
    assert "close matches" in message
    assert suggestion in message.split("close matches")[1]
    with pytest.raises(EnvError):
        check_env_name(name)


def test_bad_entry_points_and_empty_names_are_refused():
    with pytest.raises(EnvError, match="cannot load"):
        make_env(Config(env="no_such_module_for_dqnlab:Env"), training=True, seed=0)
    with pytest.raises(EnvError, match="gymnasium.Env"):
        make_env(Config(env=f"{__name__}:not_an_env"), training=True, seed=0)
    with pytest.raises(EnvError, match="no environment"):
        check_env_name("")


def test_every_gymnasium_observation_space_of_the_tests_is_accepted():
    env = GymnasiumEnv(DictObservationEnv(), seed=0)
    assert env.observation_layout.packed and env.observation_dtype == np.uint8


def test_is_atari():
    assert is_atari("pong") and is_atari("breakout")
    assert not is_atari("CartPole-v1") and not is_atari("pongg")
