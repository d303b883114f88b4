"""Environments: Atari through the faithful pipeline, anything else through Gymnasium.

Every environment offers the same small API to the training loop:
`reset(new_game=False) -> observation`,
`step(action) -> (observation, reward, terminated, truncated)`,
`game_ended` (the scored game is over, not just a life), `frames` (raw frames so far),
`num_actions`, `action_names`, `observation_shape` and `observation_dtype`.
Observations are returned in a buffer the environment reuses: copy to keep one.
"""

from __future__ import annotations

import difflib
import importlib
from typing import Any, Protocol

import gymnasium as gym
import numpy as np

from dqnlab.config import Config
from dqnlab.envs.atari import AtariEnv, game_names
from dqnlab.envs.generic import GymnasiumEnv
from dqnlab.errors import EnvError


class Environment(Protocol):
    num_actions: int
    action_names: list[str]
    observation_shape: tuple[int, ...]
    observation_dtype: np.dtype
    frames: int

    @property
    def game_ended(self) -> bool: ...

    def reset(self, new_game: bool = False) -> np.ndarray: ...

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool]: ...

    def close(self) -> None: ...

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...


def is_atari(env_name: str) -> bool:
    return env_name in game_names()


def make_env(
    config: Config,
    *,
    training: bool,
    seed: int,
    max_episode_frames: int | None = None,
    render_mode: str | None = None,
) -> Environment:
    """Build the environment named by `config.env`.

    `max_episode_frames` overrides the configured cap (evaluation uses its own caps);
    for a non-Atari environment a frame is a step. `render_mode` is Gymnasium's, for a
    non-Atari environment (an Atari game's frames come from `AtariEnv.frame_callback`).
    """
    cap = config.max_episode_frames if max_episode_frames is None else max_episode_frames
    name = config.env
    if is_atari(name):
        return AtariEnv(
            name,
            seed=seed,
            training=training,
            action_repeat_frames=config.action_repeat_frames,
            frame_pooling=config.frame_pooling,
            grayscale=config.grayscale,
            byte_conversion=config.byte_conversion,
            resize_interpolation=config.resize_interpolation,
            screen_size=config.screen_size,
            noop_max_frames=config.noop_max_frames,
            sticky_action_probability=config.sticky_action_probability,
            full_action_space=config.full_action_space,
            life_loss_terminal=config.life_loss_terminal,
            max_episode_frames=cap,
        )
    env = _make_gymnasium(name, render_mode)
    try:
        return GymnasiumEnv(env, seed=seed, max_episode_steps=cap)
    except EnvError:
        env.close()
        raise


def check_env_name(name: str) -> None:
    """Raise a one-line error if `name` is neither an Atari game nor a usable Gymnasium env."""
    if is_atari(name):
        return
    env = _make_gymnasium(name)
    try:
        GymnasiumEnv(env, seed=0)
    finally:
        env.close()


def _make_gymnasium(name: str, render_mode: str | None = None) -> gym.Env:
    if not name:
        raise EnvError("no environment given; pass --env (e.g. pong, CartPole-v1)")
    if ":" in name and "/" not in name.split(":")[0]:
        return _make_from_entry_point(name, render_mode)
    try:
        return gym.make(name, **_render_kwargs(render_mode))
    except gym.error.Error as error:
        raise EnvError(_unknown_env_message(name, error)) from None


def _render_kwargs(render_mode: str | None) -> dict[str, Any]:
    """No render_mode argument at all unless one is asked for: gym.make passes even None
    on to the environment's constructor, which may take no such argument."""
    return {} if render_mode is None else {"render_mode": render_mode}


def _make_from_entry_point(name: str, render_mode: str | None = None) -> gym.Env:
    """`module:EnvClass` (any callable returning an env, called without arguments), or
    Gymnasium's `module:Env-v0` (made with `render_mode`)."""
    module_name, _, attribute = name.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise EnvError(f"cannot load environment {name!r}: {error}") from None
    factory = getattr(module, attribute, None)
    if factory is None:  # importing the module may have registered the id
        try:
            return gym.make(attribute, **_render_kwargs(render_mode))
        except gym.error.Error as error:
            raise EnvError(_unknown_env_message(name, error)) from None
    try:
        env = factory()
    except Exception as error:  # noqa: BLE001 - the user's code: report, don't crash
        raise EnvError(f"environment factory {name!r} failed: {error!r}") from None
    if not isinstance(env, gym.Env):
        raise EnvError(f"{name!r} did not return a gymnasium.Env (got {type(env)})")
    return env


def _unknown_env_message(name: str, error: Exception) -> str:
    games = difflib.get_close_matches(name.lower().replace("-", "_"), game_names(), n=3)
    ids = difflib.get_close_matches(name, list(gym.registry.keys()), n=3, cutoff=0.5)
    close = games + [i for i in ids if i not in games]
    hint = f"; close matches: {', '.join(close)}" if close else ""
    return (
        f"unknown environment {name!r}: not an ale-py Atari game nor a registered Gymnasium id"
        f" ({error}){hint}. Accepted: an Atari game (`dqnlab games` lists them), a Gymnasium id "
        "such as CartPole-v1, or module:EnvClass"
    )
