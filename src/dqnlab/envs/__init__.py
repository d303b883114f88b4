"""Environments: Atari through the faithful pipeline, anything else through Gymnasium.

Every environment offers the same small API to the training loop:
`reset(new_game=False) -> observation`,
`step(action) -> (observation, reward, terminated, truncated)`,
`game_ended` (the scored game is over, not just a life), `frames` (raw frames so far),
`num_actions`, `action_names`, `observation_shape` and `observation_dtype`.
Observations are returned in a buffer the environment reuses: copy to keep one.

A Gymnasium environment is made with the run's `env_kwargs` and wrapped in its
`env_wrappers`; an Atari game takes dqnlab's own settings instead.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Mapping, Sequence
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import find_highest_version, parse_env_id

from dqnlab.config import Config, tuned_preset
from dqnlab.envs.atari import AtariEnv, game_names
from dqnlab.envs.generic import GymnasiumEnv
from dqnlab.envs.registry import load_entry_points, unknown_env_message
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


def default_preset(env_name: str) -> str:
    """The preset a run of this environment gets when none is given: `nature` for an Atari
    game, the tuned settings for an id dqnlab has them for (tuned/ID), `classic` otherwise."""
    if is_atari(env_name):
        return "nature"
    return tuned_preset(env_name) or "classic"


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
        _refuse_env_arguments(name, config.env_kwargs, config.env_wrappers)
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
    env = _make_gymnasium(name, render_mode, config.env_kwargs, config.env_wrappers)
    try:
        return GymnasiumEnv(
            env, seed=seed, max_episode_steps=cap, observation_images=config.observation_images
        )
    except EnvError:
        env.close()
        raise


def check_env(config: Config) -> None:
    """`check_env_name` for the environment `config` builds."""
    check_env_name(
        config.env,
        env_kwargs=config.env_kwargs,
        env_wrappers=config.env_wrappers,
        observation_images=config.observation_images,
    )


def check_env_name(
    name: str,
    *,
    env_kwargs: Mapping[str, Any] | None = None,
    env_wrappers: Sequence[str] = (),
    observation_images: str = "auto",
) -> None:
    """Raise a one-line error if `name` is neither an Atari game nor a usable Gymnasium env
    (made with `env_kwargs`, wrapped in `env_wrappers`, its observations read as
    `observation_images` says)."""
    if is_atari(name):
        _refuse_env_arguments(name, env_kwargs or {}, env_wrappers)
        return
    env = _make_gymnasium(name, None, env_kwargs, env_wrappers)
    try:
        GymnasiumEnv(env, seed=0, observation_images=observation_images)
    finally:
        env.close()


def _refuse_env_arguments(name: str, kwargs: Mapping[str, Any], wrappers: Sequence[str]) -> None:
    """An Atari game runs dqnlab's own pipeline on ale-py, which is no Gymnasium env to
    pass arguments to or wrap: its options are dqnlab settings."""
    given = [what for what, value in (("env_kwargs", kwargs), ("env_wrappers", wrappers)) if value]
    if given:
        raise EnvError(
            f"{name}: {' and '.join(given)} apply to Gymnasium environments; an Atari game runs "
            "dqnlab's own ale-py pipeline, whose options are dqnlab settings (--set, e.g. "
            "sticky_action_probability, full_action_space, max_episode_frames)"
        )


def _make_gymnasium(
    name: str,
    render_mode: str | None = None,
    kwargs: Mapping[str, Any] | None = None,
    wrappers: Sequence[str] = (),
) -> gym.Env:
    """The Gymnasium environment `name`, made with `kwargs` (and `render_mode`, which a
    `module:EnvClass` factory is not given), then wrapped by each of `wrappers` in order."""
    if not name:
        raise EnvError("no environment given; pass --env (e.g. pong, CartPole-v1)")
    kwargs = dict(kwargs or {})
    if ":" in name and "/" not in name.split(":")[0]:
        env = _make_from_entry_point(name, kwargs, render_mode)
    else:
        env = _make_registered(name, kwargs, render_mode)
    for wrapper in wrappers:
        env = _wrap(env, wrapper)
    return env


def _render_kwargs(render_mode: str | None) -> dict[str, Any]:
    """No render_mode argument at all unless one is asked for: gym.make passes even None
    on to the environment's constructor, which may take no such argument."""
    return {} if render_mode is None else {"render_mode": render_mode}


def _make_registered(
    name: str, kwargs: dict[str, Any], render_mode: str | None, shown: str | None = None
) -> gym.Env:
    """gym.make, and if `name` is not registered, again after loading the installed
    packages' `gymnasium.envs` entry points that may provide it (`registry.py`)."""
    shown = shown or name
    try:
        return _gym_make(name, kwargs, render_mode, shown)
    except gym.error.Error as error:
        if _is_registered(name):
            raise EnvError(f"{shown}: {_one_line(error)}") from None
        sources, failures = load_entry_points(name)
        try:
            return _gym_make(name, kwargs, render_mode, shown)
        except gym.error.Error as again:
            if _is_registered(name):
                raise EnvError(f"{shown}: {_one_line(again)}") from None
            raise EnvError(unknown_env_message(shown, error, sources, failures)) from None


def _gym_make(name: str, kwargs: dict[str, Any], render_mode: str | None, shown: str) -> gym.Env:
    """gym.make; an error from the environment's constructor, once the id was found, is
    the environment refusing its keyword arguments when it was given some (a constructor
    without render_mode raises its TypeError as before: videos say so)."""
    try:
        return gym.make(name, **kwargs, **_render_kwargs(render_mode))
    except gym.error.DependencyNotInstalled:
        raise
    except (TypeError, ValueError, KeyError, gym.error.Error) as error:
        # gym.make adds the id and every argument to a TypeError; the env's own is its cause.
        original = error.__cause__ if isinstance(error.__cause__, TypeError) else error
        about_render_mode = render_mode is not None and "render_mode" in str(original)
        if not kwargs or about_render_mode or not _is_registered(name):
            raise
        raise EnvError(f"{shown}: env_kwargs rejected: {_one_line(original)}") from None


def _is_registered(name: str) -> bool:
    """Whether gym.make finds a spec for `name` (a versionless name finds its latest)."""
    if name in gym.registry:
        return True
    try:
        namespace, base, version = parse_env_id(name)
    except gym.error.Error:
        return False
    return version is None and find_highest_version(namespace, base) is not None


def _one_line(error: BaseException) -> str:
    """An error's message in one line, after its class unless it is Gymnasium's."""
    text = " ".join(str(error).split())
    return text if isinstance(error, gym.error.Error) else f"{type(error).__name__}: {text}"


def _takes_render_mode(factory: Any) -> bool:
    """Whether `factory` takes a `render_mode` keyword (Gymnasium's convention for envs)."""
    try:
        parameters = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(
        p.name == "render_mode" or p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters
    )


def _make_from_entry_point(name: str, kwargs: dict[str, Any], render_mode: str | None) -> gym.Env:
    """`module:EnvClass` (any callable returning an env, called with `kwargs`, and with
    `render_mode` when one is asked for and it takes one), or
    Gymnasium's `module:Env-v0` (the module registers the id when imported; made with
    `render_mode` too)."""
    module_name, _, attribute = name.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as error:
        raise EnvError(f"cannot load environment {name!r}: {error}") from None
    factory = getattr(module, attribute, None)
    if factory is None:  # importing the module may have registered the id
        return _make_registered(attribute, kwargs, render_mode, shown=name)
    arguments = dict(kwargs)
    if render_mode is not None and _takes_render_mode(factory):
        arguments["render_mode"] = render_mode  # a video of a user's class
    try:
        env = factory(**arguments)
    except TypeError as error:
        if kwargs:
            raise EnvError(f"{name}: env_kwargs rejected: {_one_line(error)}") from None
        raise EnvError(f"environment factory {name!r} failed: {error!r}") from None
    except Exception as error:  # noqa: BLE001 - the user's code: report, don't crash
        raise EnvError(f"environment factory {name!r} failed: {error!r}") from None
    if not isinstance(env, gym.Env):
        raise EnvError(f"{name!r} did not return a gymnasium.Env (got {type(env)})")
    return env


def _wrap(env: gym.Env, wrapper: str) -> gym.Env:
    """`wrapper` (module:callable) called on `env`; any failure is one line naming it, and
    closes the environment."""
    module_name, _, attribute = wrapper.partition(":")
    try:
        try:
            module = importlib.import_module(module_name)
        except ImportError as error:
            raise EnvError(f"wrapper {wrapper!r}: cannot import {module_name}: {error}") from None
        function = getattr(module, attribute, None)
        if not callable(function):
            what = "has no" if function is None else "has no callable"
            raise EnvError(f"wrapper {wrapper!r}: module {module_name} {what} {attribute}")
        try:
            wrapped = function(env)
        except Exception as error:  # noqa: BLE001 - the user's code: report, don't crash
            raise EnvError(f"wrapper {wrapper!r} failed: {_one_line(error)}") from None
        if not isinstance(wrapped, gym.Env):
            raise EnvError(
                f"wrapper {wrapper!r} did not return a gymnasium.Env (got {type(wrapped).__name__})"
            )
    except EnvError:
        env.close()
        raise
    return wrapped
