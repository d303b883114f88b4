"""Any Gymnasium environment with a Discrete action space, seen through dqnlab's env API.

Its observations are stored as `envs/spaces.py` lays them out: uint8 images (channels
first) and float vectors as frames of their own, anything else packed into rows of bytes.

A run's checkpoint keeps such an environment pickled where pickling keeps its state, else
its current episode as a replay (`EpisodeReplay`).
"""

from __future__ import annotations

import array
import dataclasses
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
        self._name = name
        self._pickles_state = pickles_its_state(env)
        # The episode is kept where a checkpoint cannot pickle the environment's state.
        self._episode = None if self._pickles_state and _pickles(env) else EpisodeReplay()
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
        """The whole environment pickled where pickling keeps its state (Gymnasium envs
        such as CartPole pickle with their RNG); else the current episode as its replay
        (`EpisodeReplay`).

        Gymnasium has no other general way to save an environment's state, so resuming
        unpickles it, which can run any code the file names: docs/resuming.md
        tells users to resume only run directories they trust as they trust code.
        """
        env_bytes: bytes | None = None
        if self._pickles_state:
            try:
                env_bytes = pickle.dumps(self.env)
            except Exception:  # noqa: BLE001 - any unpicklable environment
                env_bytes = None
        episode = None
        if env_bytes is None and self._episode is not None:
            episode = self._episode.state_dict(self._observation)
        return {
            "env": env_bytes,
            "episode": episode,
            "seed": self._seed,
            "episode_steps": self._episode_steps,
            "frames": self.frames,
            "game_over": self.game_over,
            "truncated": self.truncated,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._seed = state["seed"]
        self._episode_steps = int(state["episode_steps"])
        self.frames = int(state["frames"])
        self.truncated = bool(state["truncated"])
        self.game_over = bool(state["game_over"])
        if state["env"] is not None and self._pickles_state:
            self.env.close()
            # Trusts the run directory as code: see state_dict.
            self.env = pickle.loads(state["env"])
        elif state.get("episode") is not None:  # absent from older checkpoints
            if not self._replay_episode(state["episode"]):
                warnings.warn(
                    f"{self._name}: its episode replayed from the checkpoint does not reach "
                    "the observation saved (the environment draws from something other than "
                    "its np_random): the resumed run starts a new episode",
                    stacklevel=2,
                )
                self.game_over = True
        else:  # an older checkpoint: unpicklable, or pickled without its state (EzPickle)
            warnings.warn(
                f"{self._name}: the checkpoint keeps no state of this environment (it cannot "
                "be pickled, or its pickle keeps only its constructor's arguments): the "
                "resumed run starts a new episode",
                stacklevel=2,
            )
            self.game_over = True

    def _replay_episode(self, state: dict[str, Any]) -> bool:
        """The checkpoint's episode played again on this (newly made) environment, without
        frames for videos; whether it reached the observation saved."""
        self._episode = EpisodeReplay.from_state_dict(state)
        if not self._episode.started:
            return True
        self._episode.restore_generator(self.env)
        observation, _ = self.env.reset(seed=self._episode.seed)
        for action in self._episode.actions:
            observation, *_ = self.env.step(action)
        reached = self._convert(observation)
        return bool(reached.tobytes() == state["observation"].numpy().tobytes())

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
        if self._episode is not None:
            self._episode.start(self.env, self._seed)
        observation, _ = self.env.reset(seed=self._seed)
        self._seed = None  # seed once; later resets continue the seeded stream
        self._episode_steps = 0
        self.game_over = False
        self.truncated = False
        if self.frame_callback is not None:
            self._send_frame()
        return self._convert(observation)

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool]:
        action = int(action) + self._action_start
        if self._episode is not None:
            self._episode.actions.append(action)
        observation, reward, terminated, truncated, _ = self.env.step(action)
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


def pickles_its_state(env: gym.Env) -> bool:
    """Whether pickling `env` keeps its state: no layer of it (wrappers and the environment)
    pickles otherwise than by its attributes. Gymnasium's `EzPickle` (LunarLander, CarRacing,
    the MuJoCo environments) keeps the constructor's arguments only: unpickled, such an
    environment is a new one, not yet reset."""
    layer: Any = env
    while True:
        kind = type(layer)
        if hasattr(kind, "__setstate__") or any(
            getattr(kind, name) is not getattr(object, name)
            for name in ("__getstate__", "__reduce__", "__reduce_ex__")
        ):
            return False
        if not isinstance(layer, gym.Wrapper):
            return True
        layer = layer.env


@dataclasses.dataclass
class EpisodeReplay:
    """The current episode of an environment, as far as replaying it needs: the state of the
    environment's `np_random` before the episode's reset (and the seed it was reset with),
    and every action since. Played again on a newly made environment, they reach the same
    state wherever the environment's randomness is its `np_random` (Box2D's and MuJoCo's
    physics are deterministic); the observation reached is checked against the one saved.
    Kept for the environments whose pickle does not keep their state (an action appended
    per step: 8 bytes)."""

    started: bool = False
    seed: int | None = None
    generator: dict[str, Any] | None = None  # np.random.BitGenerator.state
    generator_seed: int | None = None  # gymnasium's np_random_seed
    emulator: bytes | None = None  # ale-py's emulator with its RNG (`ALE/...` ids)
    actions: array.array = dataclasses.field(default_factory=lambda: array.array("q"))

    def start(self, env: gym.Env, seed: int | None) -> None:
        """A new episode: `env` about to be reset with `seed`."""
        unwrapped = env.unwrapped
        generator = getattr(unwrapped, "_np_random", None)  # np_random would make one
        self.started = True
        self.seed = seed
        self.generator = None if generator is None else _plain(generator.bit_generator.state)
        self.generator_seed = getattr(unwrapped, "_np_random_seed", None)
        # ale-py's environments reset and act with the emulator's own generator too.
        ale: Any = unwrapped
        self.emulator = ale.clone_state(include_rng=True).serialize() if _is_ale(ale) else None
        self.actions = array.array("q")

    def restore_generator(self, env: gym.Env) -> None:
        """`env`'s `np_random` (and an emulator's generator) as before the episode's reset."""
        if self.emulator is not None:
            from ale_py import ALEState  # read from its own bytes: no pickle

            ale: Any = env.unwrapped
            ale.restore_state(ALEState(self.emulator))
        if self.generator is None:
            return
        name = str(self.generator["bit_generator"])
        kind = getattr(np.random, name, None)
        if not (isinstance(kind, type) and issubclass(kind, np.random.BitGenerator)):
            raise EnvError(f"unknown random generator in the checkpoint: {name!r}")
        bit_generator = kind()
        bit_generator.state = self.generator
        env.unwrapped.np_random = np.random.Generator(bit_generator)
        env.unwrapped._np_random_seed = self.generator_seed  # the setter made it -1

    def state_dict(self, observation: np.ndarray) -> dict[str, Any]:
        """The episode and the observation it reached, as a checkpoint keeps them (tensors
        and plain values)."""
        import torch  # kept out of the environment workers' imports

        return {
            "started": self.started,
            "seed": self.seed,
            "generator": self.generator,
            "generator_seed": self.generator_seed,
            "emulator": self.emulator,
            "actions": torch.from_numpy(np.array(self.actions, dtype=np.int64)),
            "observation": torch.from_numpy(observation.copy()),
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> EpisodeReplay:
        return cls(
            started=bool(state["started"]),
            seed=state["seed"],
            generator=state["generator"],
            generator_seed=state["generator_seed"],
            emulator=state.get("emulator"),
            actions=array.array("q", state["actions"].tolist()),
        )


def _is_ale(unwrapped: gym.Env) -> bool:
    return type(unwrapped).__module__.startswith("ale_py") and hasattr(unwrapped, "clone_state")


def _pickles(env: gym.Env) -> bool:
    try:
        pickle.dumps(env)
    except Exception:  # noqa: BLE001 - any unpicklable environment
        return False
    return True


def _plain(value: Any) -> Any:
    """`value` (a bit generator's state) with its NumPy arrays and scalars as Python
    lists and numbers, which a checkpoint keeps and a bit generator takes back."""
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    return value
