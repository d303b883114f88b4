"""Any Gymnasium environment with a Discrete action space, seen through dqnlab's env API.

Its observations are stored as `envs/spaces.py` lays them out: uint8 images (channels
first) and float vectors as frames of their own, anything else packed into rows of bytes.
"""

from __future__ import annotations

import pickle
import warnings
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from dqnlab.envs.spaces import ObservationLayout, observation_layout
from dqnlab.errors import EnvError


class GymnasiumEnv:
    """Wraps a Gymnasium env; `observation_images` is the setting of that name
    (`envs/spaces.py`: how Box parts are read)."""

    def __init__(
        self,
        env: gym.Env,
        *,
        seed: int,
        max_episode_steps: int = 0,
        observation_images: str = "auto",
    ) -> None:
        name = env.spec.id if env.spec else type(env.unwrapped).__name__
        if not isinstance(env.action_space, gym.spaces.Discrete):
            raise EnvError(
                f"{name}: DQN needs a Discrete action space (one Q-value per action); this "
                f"environment's is {env.action_space}"
            )
        self.env = env
        try:
            self.observation_layout: ObservationLayout = observation_layout(
                env.observation_space, observation_images
            )
        except EnvError as error:
            raise EnvError(f"{name}: {error}") from None
        self.observation_shape = self.observation_layout.frame_shape
        self.observation_dtype = self.observation_layout.frame_dtype
        self.num_actions = int(env.action_space.n)
        self._action_start = int(env.action_space.start)
        meanings = getattr(env.unwrapped, "get_action_meanings", None)
        self.action_names = (
            list(meanings()) if meanings else [str(a) for a in range(self.num_actions)]
        )
        self.max_episode_steps = max_episode_steps
        self._seed: int | None = seed
        self._episode_steps = 0
        self._observation = np.zeros(self.observation_shape, dtype=self.observation_dtype)
        self.frames = 0  # for a non-Atari environment a frame is a step
        self.game_over = True
        self.truncated = False
        # Called with `env.render()` after every reset and step (videos): the env must have
        # been made with render_mode="rgb_array" for that to be an image.
        self.frame_callback: Callable[[Any], None] | None = None

    def state_dict(self) -> dict[str, Any]:
        """The whole environment pickled (Gymnasium envs such as CartPole pickle with their
        RNG); an environment that cannot be pickled resumes with a new episode.

        Gymnasium has no other general way to save an environment's state, so resuming
        unpickles it, which can run any code the file names: docs/resuming.md
        tells users to resume only run directories they trust as they trust code.
        """
        try:
            env_bytes: bytes | None = pickle.dumps(self.env)
        except Exception:  # noqa: BLE001 - any unpicklable environment
            env_bytes = None
        return {
            "env": env_bytes,
            "seed": self._seed,
            "episode_steps": self._episode_steps,
            "frames": self.frames,
            "game_over": self.game_over,
            "truncated": self.truncated,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if state["env"] is None:
            warnings.warn(
                "this environment cannot be pickled: the resumed run starts a new episode",
                stacklevel=2,
            )
            self.game_over = True
        else:
            self.env.close()
            # Trusts the run directory as code: see state_dict.
            self.env = pickle.loads(state["env"])
            self.game_over = bool(state["game_over"])
        self._seed = state["seed"]
        self._episode_steps = int(state["episode_steps"])
        self.frames = int(state["frames"])
        self.truncated = bool(state["truncated"])

    @property
    def game_ended(self) -> bool:
        return self.game_over or self.truncated

    @property
    def step_limit(self) -> int:
        """The most steps of an episode: dqnlab's cap, else the env's registered
        TimeLimit (`max_episode_steps`), else 0 (episodes end only when the env ends them)."""
        registered = self.env.spec.max_episode_steps if self.env.spec is not None else None
        return self.max_episode_steps or int(registered or 0)

    def _convert(self, observation: Any) -> np.ndarray:
        return self.observation_layout.pack(observation, self._observation)

    def reset(self, new_game: bool = False) -> np.ndarray:
        """A new episode (every Gymnasium reset is a new game)."""
        observation, _ = self.env.reset(seed=self._seed)
        self._seed = None  # seed once; later resets continue the seeded stream
        self._episode_steps = 0
        self.game_over = False
        self.truncated = False
        if self.frame_callback is not None:
            self._send_frame()
        return self._convert(observation)

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool]:
        observation, reward, terminated, truncated, _ = self.env.step(action + self._action_start)
        self._episode_steps += 1
        self.frames += 1
        if self.max_episode_steps and self._episode_steps >= self.max_episode_steps:
            truncated = True
        self.game_over = bool(terminated)
        self.truncated = bool(truncated) and not terminated
        if self.frame_callback is not None:
            self._send_frame()
        return self._convert(observation), float(reward), bool(terminated), self.truncated

    def _send_frame(self) -> None:
        assert self.frame_callback is not None
        try:
            frame = self.env.render()
        except gym.error.Error as error:  # e.g. pygame missing for the classic-control envs
            name = self.env.spec.id if self.env.spec else type(self.env.unwrapped).__name__
            raise EnvError(f"{name} cannot render its frames: {error}") from None
        self.frame_callback(frame)

    def close(self) -> None:
        self.env.close()
