"""Settings as text: the presets (TOML files), `--set KEY=VALUE` overrides, a run's
`config.toml`, and a `Config` resolved from them and checked field by field."""

from __future__ import annotations

import dataclasses
import datetime
import difflib
import functools
import re
import sys
import typing
from importlib import resources
from pathlib import Path
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from dqnlab.config.settings import FIELD_NAMES, Config
from dqnlab.config.validation import USER_PARTS
from dqnlab.errors import ConfigError
from dqnlab.parts import check_head_options, load_object, part_settings

# Tuned settings for one environment id, as rl-baselines3-zoo keeps its hyperparameters by
# id: presets/tuned/ID.toml, the preset `dqnlab train --env ID` takes when none is given.
TUNED = "tuned"


def preset_names() -> list[str]:
    """The shipped presets: the family's by name, then the tuned ones as tuned/ENV-ID."""
    files = resources.files("dqnlab").joinpath("presets").iterdir()
    names = sorted(f.name.removesuffix(".toml") for f in files if f.name.endswith(".toml"))
    return names + [f"{TUNED}/{env}" for env in tuned_envs()]


def tuned_envs() -> list[str]:
    """The environment ids dqnlab ships tuned settings for."""
    folder = resources.files("dqnlab") / "presets" / TUNED
    if not folder.is_dir():
        return []
    return sorted(
        f.name.removesuffix(".toml") for f in folder.iterdir() if f.name.endswith(".toml")
    )


def tuned_preset(env: str) -> str | None:
    """tuned/ENV-ID when dqnlab ships tuned settings for this environment id, else None."""
    return f"{TUNED}/{env}" if env in tuned_envs() else None


def preset_text(name: str) -> str:
    """A shipped preset's TOML text (`name` as `preset_names` gives it)."""
    return (resources.files("dqnlab") / "presets" / f"{name}.toml").read_text()


def load_preset(name_or_path: str) -> dict[str, Any]:
    """Read a preset by name (shipped in the package) or from a TOML file path."""
    path = Path(name_or_path)
    if name_or_path.endswith(".toml") and path.is_file():
        text = path.read_text()
    elif name_or_path in preset_names():
        text = preset_text(name_or_path)
    else:
        raise ConfigError(
            f"unknown preset {name_or_path!r}; accepted: {', '.join(preset_names())} "
            "or the path of a .toml file"
        )
    try:
        values = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"preset {name_or_path!r} is not valid TOML: {error}") from None
    _check_names(values, f"preset {name_or_path!r}")
    return values


def _check_names(values: dict[str, Any], where: str) -> None:
    for name in values:
        if name.startswith("parts."):
            if len(name.split(".")) != 3 or not all(name.split(".")):
                raise ConfigError(
                    f"{name!r} in {where}: a part's setting is parts.PART.NAME (parts.loss.tau)"
                )
            continue
        if name not in FIELD_NAMES:
            close = difflib.get_close_matches(name, FIELD_NAMES, n=3)
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            raise ConfigError(f"unknown setting {name!r} in {where}{hint}")


def parse_value(raw: str) -> Any:
    """A value given on the command line: read as a TOML literal (`false`, `3`, `[64, 64]`,
    `{is_slippery = false}`), else taken as the plain string it is (`8x8`)."""
    try:
        return tomllib.loads(f"value = {raw.strip()}")["value"]
    except tomllib.TOMLDecodeError:
        return raw.strip()


def parse_pairs(pairs: list[str], option: str) -> dict[str, Any]:
    """`KEY=VALUE` strings, values read by `parse_value`; a later KEY wins."""
    values: dict[str, Any] = {}
    for pair in pairs:
        key, sep, raw = pair.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ConfigError(f"{option} expects KEY=VALUE, got {pair!r}")
        values[key] = parse_value(raw)
    return values


def parse_overrides(pairs: list[str]) -> dict[str, Any]:
    """Parse `key=value` strings; values are read as TOML, else taken as plain strings."""
    values = parse_pairs(pairs, "--set")
    _check_names(values, "--set")
    return values


@functools.cache
def _field_types() -> dict[str, Any]:
    """Config's fields and their types, evaluated once: `get_type_hints` evaluates every
    annotation at each call, and a sweep's driver reads every run's config.toml at each
    status poll (it took 13% of a core in a 26-game sweep when called per field)."""
    return typing.get_type_hints(Config)


def _coerce(name: str, value: Any) -> Any:
    """Convert a value read from TOML or the command line to the field's declared type."""
    expected = _field_types()[name]
    try:
        if expected is bool:
            if isinstance(value, str) and value.lower() in ("true", "false"):
                return value.lower() == "true"
            if not isinstance(value, bool):
                raise TypeError
            return value
        if expected is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise TypeError
            return int(value)
        if expected is float:
            if isinstance(value, bool):
                raise TypeError
            return float(value)
        if expected is str:
            return str(value)
        if typing.get_origin(expected) is dict:  # a TOML table: any TOML values
            if not isinstance(value, dict):
                raise TypeError
            return dict(value)
        item = typing.get_args(expected)[0]  # tuple[int, ...] or tuple[str, ...]
        if isinstance(value, (int, str)) and not isinstance(value, bool):
            value = [v.strip() for v in str(value).split(",") if v.strip()]
            value = [int(v) for v in value] if item is int else value
        if any(isinstance(v, bool) or not isinstance(v, item) for v in value):
            raise TypeError
        return tuple(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} = {value!r} is not a valid {_type_name(expected)}") from None


def _type_name(expected: Any) -> str:
    if expected in (bool, int, float, str):
        return expected.__name__
    if typing.get_origin(expected) is dict:
        return 'table (e.g. {key = 1, other = "text"})'
    item = typing.get_args(expected)[0]
    return "list of integers" if item is int else "list of strings"


def resolve_config(preset: str, overrides: dict[str, Any] | None = None, **explicit: Any) -> Config:
    """The preset's values, then `overrides` (from --set), then explicit non-None arguments;
    a dotted `parts.PART.NAME` key sets one of a part's own settings, and the settings a
    user's part declares are filled in with their defaults (`with_part_settings`)."""
    values = load_preset(preset)
    given = {**(overrides or {}), **{k: v for k, v in explicit.items() if v is not None}}
    if "preset" in given:
        raise ConfigError("preset is where the settings came from: choose it with --preset")
    values.update(given)
    values.setdefault("preset", preset)  # a saved config.toml keeps the record it has
    _check_names(values, "the configuration")
    values = _budget_scaled(_nest_part_settings(values), given)
    config = Config(**{name: _coerce(name, value) for name, value in values.items()})
    return with_part_settings(config)


def _budget_scaled(values: dict[str, Any], given: dict[str, Any]) -> dict[str, Any]:
    """`epsilon_decay_steps` from `epsilon_decay_fraction` of `total_steps` when the fraction
    is above 0, so that `--steps` scales the anneal (SB3's exploration_fraction); an
    `epsilon_decay_steps` the user gives wins, and turns the fraction off."""
    fraction = _coerce("epsilon_decay_fraction", values.get("epsilon_decay_fraction", 0.0))
    if fraction <= 0:
        return values
    if "epsilon_decay_steps" in given:
        if "epsilon_decay_fraction" in given:
            raise ConfigError(
                "epsilon_decay_steps and epsilon_decay_fraction are both given: give one "
                "(the fraction of total_steps, or the steps)"
            )
        return {**values, "epsilon_decay_fraction": 0.0}
    total_steps = _coerce("total_steps", values.get("total_steps", Config.total_steps))
    return {**values, "epsilon_decay_steps": max(1, round(fraction * total_steps))}


def _nest_part_settings(values: dict[str, Any]) -> dict[str, Any]:
    """`parts.PART.NAME = value` keys moved into the `parts` table, over what it has."""
    dotted = {key: value for key, value in values.items() if key.startswith("parts.")}
    if not dotted:
        return values
    nested = {key: value for key, value in values.items() if key not in dotted}
    parts = nested.get("parts", {})
    if not isinstance(parts, dict):
        raise ConfigError(f"parts = {parts!r} must be a table (a dict) of tables")
    parts = {setting: dict(table) for setting, table in parts.items()}
    for key, value in dotted.items():
        _, setting, name = key.split(".")
        table = parts.setdefault(setting, {})
        if not isinstance(table, dict):
            raise ConfigError(f"parts.{setting} = {table!r} must be a table of settings")
        table[name] = value
    nested["parts"] = parts
    return nested


def with_part_settings(config: Config) -> Config:
    """`config` with `parts` holding every setting of each user's part (`module:Name`) that
    declares some: the given values checked against the declaration, the defaults for the
    rest (`dqnlab.parts.part_settings`). A shipped part declares none, so a setting given
    for one is refused. A part that cannot be imported here is left to the run that builds
    it (which says so in one line), unless settings were given for it."""
    parts = {setting: dict(table) for setting, table in config.parts.items()}
    for setting in USER_PARTS:
        path = getattr(config, setting)
        given = parts.get(setting, {})
        if ":" not in path:
            if given:
                raise ConfigError(
                    f"parts.{setting}: {setting} = {path!r} is a shipped part with no settings "
                    f"of its own (given: {', '.join(given)})"
                )
            continue
        try:
            part = load_object(setting, path)
        except ConfigError:
            if given:
                raise
            continue
        if setting == "head":
            check_head_options(config, part)
        filled = part_settings(setting, part, config)
        if filled:
            parts[setting] = filled
    if parts == config.parts:
        return config
    return dataclasses.replace(config, parts=parts)


def config_from_dict(values: dict[str, Any]) -> Config:
    _check_names(values, "the saved configuration")
    return Config(**{name: _coerce(name, value) for name, value in values.items()})


# The settings that change only how a trained network is played, not the network: what
# `dqnlab evaluate --set` may change (another protocol for the same network).
EVALUATION_SETTINGS = (
    "eval_epsilon", "eval_noise", "noop_max_frames", "sticky_action_probability",
    "final_eval_max_episode_frames",
)  # fmt: skip


def with_evaluation_settings(config: Config, overrides: dict[str, Any]) -> Config:
    """`config` with `overrides` of `EVALUATION_SETTINGS` (from `dqnlab evaluate --set`);
    any other setting is refused, since it would change the network or its training."""
    for name in overrides:
        if name not in EVALUATION_SETTINGS:
            raise ConfigError(
                f"--set {name}: evaluate changes only how the network plays "
                f"({', '.join(EVALUATION_SETTINGS)})"
            )
    if not overrides:
        return config
    return dataclasses.replace(
        config, **{name: _coerce(name, value) for name, value in overrides.items()}
    )


def with_env_arguments(
    config: Config, env_kwargs: dict[str, Any], env_wrappers: typing.Sequence[str]
) -> Config:
    """`config` with `--env-kwarg` and `--wrapper` added: each keyword argument replaces
    one of the same name (from the preset or --set), the wrappers go after theirs."""
    if not env_kwargs and not env_wrappers:
        return config
    return dataclasses.replace(
        config,
        env_kwargs={**config.env_kwargs, **env_kwargs},
        env_wrappers=config.env_wrappers + tuple(env_wrappers),
    )


_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def toml_value(value: Any) -> str:
    """A setting's value as TOML writes it (strings quoted, a table inline)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        items = ", ".join(f"{_toml_key(k)} = {toml_value(v)}" for k, v in value.items())
        return "{" + items + "}"
    if isinstance(value, (datetime.date, datetime.time)):  # datetime too: a date's subclass
        return value.isoformat()
    return repr(value)


def _toml_key(key: str) -> str:
    return key if _BARE_KEY.fullmatch(key) else toml_value(key)


def setting_text(value: Any) -> str:
    """A setting's value as `--set` takes it: TOML, but a string as it is."""
    return value if isinstance(value, str) else toml_value(value)


def config_to_toml(config: Config) -> str:
    lines = ["# Resolved dqnlab configuration of this run."]
    for f in dataclasses.fields(Config):
        lines.append(f"{f.name} = {toml_value(getattr(config, f.name))}  # {f.metadata['doc']}")
    return "\n".join(lines) + "\n"
