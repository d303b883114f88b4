"""Small Gymnasium environments, one per kind of observation space, for the tests of
`envs/spaces.py` and everything downstream of it (trained as `tests.envs.space_envs:Name`).

Each is a cue game: every step shows a cue, action 1 is rewarded +1 when the cue is on
and action 0 when it is off, eight steps a game; the optimal score is 8 and random play
scores 4 on average. Where the cue is shown differs with the space, so a network that
reads its observation wrongly cannot score 8.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

GAME_STEPS = 8


class CueEnv(gym.Env):
    """The cue game; subclasses say how the cue is shown (`observe`)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}
    observation_space: spaces.Space

    def __init__(self, render_mode: str | None = None) -> None:
        self.render_mode = render_mode
        self.action_space = spaces.Discrete(2)
        self.cue = False
        self.t = 0

    def observe(self) -> Any:
        raise NotImplementedError

    def _next_cue(self) -> None:
        self.cue = bool(self.np_random.integers(2))

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.t = 0
        self._next_cue()
        return self.observe(), {}

    def step(self, action: int):
        reward = 1.0 if int(action) == int(self.cue) else 0.0
        self.t += 1
        self._next_cue()
        return self.observe(), reward, self.t >= GAME_STEPS, False, {}

    def render(self) -> np.ndarray:
        frame = np.zeros((16, 16, 3), np.uint8)
        frame[4:12, 4:12] = (255, 255, 255) if self.cue else (40, 40, 40)
        return frame


class IntVectorEnv(CueEnv):
    """Box int16 vector: the cue is entry 2 (0 or 1000), the others noise."""

    observation_space = spaces.Box(-1000, 1000, (4,), np.int16)

    def observe(self) -> np.ndarray:
        noise = self.np_random.integers(-1000, 1000, 4).astype(np.int16)
        noise[2] = 1000 if self.cue else 0
        return noise


class BoolImageEnv(CueEnv):
    """Box bool image, 7x7 with 2 channels (a small grid): the cue lights the centre of
    channel 1; channel 0 is noise."""

    observation_space = spaces.Box(0, 1, (7, 7, 2), np.bool_)

    def observe(self) -> np.ndarray:
        grid = np.zeros((7, 7, 2), np.bool_)
        grid[..., 0] = self.np_random.integers(2, size=(7, 7)).astype(np.bool_)
        grid[2:5, 2:5, 1] = self.cue
        return grid


class FloatImageEnv(CueEnv):
    """Box float32 image, 10x12 with 3 channels, in [0, 1]: the cue brightens the left
    half of channel 2."""

    observation_space = spaces.Box(0.0, 1.0, (10, 12, 3), np.float32)

    def observe(self) -> np.ndarray:
        image = self.np_random.random((10, 12, 3), dtype=np.float32) * 0.2
        image[:, :6, 2] += 0.8 if self.cue else 0.0
        return image


class DiscreteEnv(CueEnv):
    """Discrete(5) starting at 3: values 3..7, the cue on for the odd ones."""

    observation_space = spaces.Discrete(5, start=3)

    def _next_cue(self) -> None:
        self.value = int(self.np_random.integers(3, 8))
        self.cue = self.value % 2 == 1

    def observe(self) -> int:
        return self.value


class MultiDiscreteEnv(CueEnv):
    """MultiDiscrete([3, 4]): the cue is the second entry being 3; the first is noise."""

    observation_space = spaces.MultiDiscrete([3, 4])

    def observe(self) -> np.ndarray:
        other = int(self.np_random.integers(3))
        return np.array([int(self.np_random.integers(3)), 3 if self.cue else other], np.int64)


class MultiBinaryEnv(CueEnv):
    """MultiBinary(6): the cue is the parity of the six bits."""

    observation_space = spaces.MultiBinary(6)

    def observe(self) -> np.ndarray:
        bits = self.np_random.integers(2, size=6).astype(np.int8)
        if bits.sum() % 2 != int(self.cue):
            bits[0] ^= 1
        return bits


class TupleEnv(CueEnv):
    """Tuple(Discrete(2), Box float32 (2,)): the Discrete says which of the two floats
    carries the cue (> 0.5)."""

    observation_space = spaces.Tuple((spaces.Discrete(2), spaces.Box(0.0, 1.0, (2,), np.float32)))

    def observe(self) -> tuple[int, np.ndarray]:
        where = int(self.np_random.integers(2))
        values = self.np_random.random(2).astype(np.float32) * 0.4
        values[where] += 0.6 if self.cue else 0.0
        return where, values


class NestedDictEnv(CueEnv):
    """Dict with a nested Dict: the cue is in the bool grid or in the Discrete code, and
    `where` (a MultiBinary of one bit inside `meta`) says which; a float `clock` too."""

    observation_space = spaces.Dict(
        {
            "grid": spaces.Box(0, 1, (5, 5), np.bool_),
            "meta": spaces.Dict({"where": spaces.MultiBinary(1), "code": spaces.Discrete(3)}),
            "clock": spaces.Box(0.0, 1.0, (1,), np.float64),
        }
    )

    def observe(self) -> dict[str, Any]:
        in_grid = bool(self.np_random.integers(2))
        grid = self.np_random.random((5, 5)) < 0.1
        grid[2, 2] = self.cue if in_grid else bool(self.np_random.integers(2))
        code = (2 if self.cue else 1) if not in_grid else int(self.np_random.integers(3))
        return {
            "grid": grid,
            "meta": {"where": np.array([in_grid], np.int8), "code": code},
            "clock": np.array([self.t / GAME_STEPS]),
        }


class TextEnv(CueEnv):
    """A Dict with a Text part, which dqnlab cannot encode."""

    observation_space = spaces.Dict({"position": spaces.Discrete(3), "note": spaces.Text(8)})

    def observe(self) -> dict[str, Any]:
        return {"position": 0, "note": "a"}


class ContinuousActionEnv(CueEnv):
    def __init__(self, render_mode: str | None = None) -> None:
        super().__init__(render_mode)
        self.observation_space = spaces.Box(0.0, 1.0, (2,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    def observe(self) -> np.ndarray:
        return np.zeros(2, np.float32)


SPACE_ENVS = {
    "int-vector": IntVectorEnv,
    "bool-image": BoolImageEnv,
    "float-image": FloatImageEnv,
    "discrete": DiscreteEnv,
    "multi-discrete": MultiDiscreteEnv,
    "multi-binary": MultiBinaryEnv,
    "tuple": TupleEnv,
    "nested-dict": NestedDictEnv,
}
