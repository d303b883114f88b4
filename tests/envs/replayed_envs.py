"""Small Gymnasium environments whose pickle does not keep their state, for the tests of
how a checkpoint keeps an environment (`envs/generic.py`): each a point pushed left or
right with noise, 50 steps a game at most (trained as `tests.envs.replayed_envs:Name`)."""

from __future__ import annotations

import random
import threading

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.utils import EzPickle

STEPS = 50


class Drift(gym.Env):
    """A point pushed left or right, with noise from the environment's `np_random`."""

    def __init__(self, noise: float = 0.05) -> None:
        self.noise = noise
        self.action_space = spaces.Discrete(3)
        self.observation_space = spaces.Box(-2.0, 2.0, (2,), np.float32)
        self.position: float | None = None
        self.velocity = 0.0
        self.t = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.position, self.velocity = float(self.np_random.uniform(-0.5, 0.5)), 0.0
        self.t = 0
        return self._observe(), {}

    def step(self, action: int):
        assert self.position is not None, "stepped before a reset"  # as LunarLander asserts
        self.velocity += 0.02 * (int(action) - 1) + self.noise_draw()
        self.position += self.velocity
        self.t += 1
        ended = abs(self.position) > 1.0
        return self._observe(), -abs(self.position), ended, self.t >= STEPS and not ended, {}

    def noise_draw(self) -> float:
        return float(self.np_random.normal(0.0, self.noise))

    def _observe(self) -> np.ndarray:
        return np.array([self.position, self.velocity], dtype=np.float32)


class EzDrift(Drift, EzPickle):
    """Pickled as EzPickle pickles (the constructor's arguments only), as LunarLander is."""

    def __init__(self, noise: float = 0.05) -> None:
        super().__init__(noise)
        EzPickle.__init__(self, noise)


class Locked(Drift):
    """Holds a lock: cannot be pickled at all."""

    def __init__(self, noise: float = 0.05) -> None:
        super().__init__(noise)
        self.lock = threading.Lock()


class Loose(EzDrift):
    """Draws its noise from a generator of its own, not `np_random`: a replay cannot repeat it."""

    def __init__(self, noise: float = 0.05) -> None:
        super().__init__(noise)
        self.own = random.Random()

    def noise_draw(self) -> float:
        return self.own.gauss(0.0, self.noise)
