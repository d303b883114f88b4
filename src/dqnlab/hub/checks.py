"""What a folder from a stranger must pass before dqnlab keeps it: no pickle anywhere, a
configuration this version of dqnlab reads, no code to import unless the user allows it,
and a network whose shapes fit its environment.

Nothing here imports or unpickles anything from the folder: model.safetensors is JSON and
raw tensor bytes, config.toml is TOML, and settings that name code (`module:Name`) are
refused before anything is built from them. Opting in with `allow_user_parts` imports
those modules from the Python environment, never from the repository: a pull downloads
only the files of an exported folder (`exported.FOLDER_FILES`).
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dqnlab import __version__
from dqnlab.config import (
    FIELD_NAMES,
    USER_PARTS,
    Config,
    config_fingerprint,
    config_from_dict,
    differing_settings,
)
from dqnlab.envs import make_env
from dqnlab.errors import ConfigError, DqnlabError
from dqnlab.run import exported
from dqnlab.run.rundir import agent_from_network

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

# Files that are, or may be, pickles: PyTorch's .pt/.pth/.bin/.ckpt, pickle, joblib.
PICKLE_SUFFIXES = (".pt", ".pth", ".bin", ".ckpt", ".pkl", ".pickle", ".joblib")
# Settings whose value may name code to import: `module:Name`, or any wrapper at all.
CODE_SETTINGS = ("env", "network", *USER_PARTS)
ALLOW_OPTION = "--allow-user-parts"


@dataclass(frozen=True)
class CheckedFolder:
    config: Config
    step: int | None
    dqnlab_version: str | None  # the version that wrote the network


def refuse_pickles(names: Iterable[str], where: str) -> None:
    """A one-line refusal when any of `names` may be a pickle."""
    pickles = sorted(name for name in names if name.lower().endswith(PICKLE_SUFFIXES))
    if pickles:
        raise DqnlabError(
            f"{where} holds {', '.join(pickles)}: files that may be pickles, which can run "
            f"code when read; dqnlab reads networks only from {exported.MODEL_FILE}"
        )


def code_settings(values: Mapping[str, Any]) -> list[str]:
    """The settings in `values` that name code to import, as `name = value`."""
    named = [
        f"{name} = {values[name]!r}"
        for name in CODE_SETTINGS
        if isinstance(values.get(name), str) and ":" in values[name]
    ]
    wrappers = values.get("env_wrappers") or []
    if wrappers:
        named.append(f"env_wrappers = {list(wrappers)!r}")
    return named


def checked_config(values: Any, where: str, version: str | None, allow_user_parts: bool) -> Config:
    """`values` as a Config, refused with one line when they name settings unknown to this
    dqnlab (a newer version's) or, without `allow_user_parts`, code to import."""
    if not isinstance(values, dict):
        raise DqnlabError(f"{where} holds no table of settings")
    unknown = [name for name in values if name not in FIELD_NAMES]
    if unknown:
        raise ConfigError(
            f"{where} names settings this dqnlab ({__version__}) does not know: "
            f"{', '.join(unknown)}; it was written by dqnlab {version or 'of another version'}: "
            "upgrade dqnlab to play it"
        )
    named = code_settings(values)
    if named and not allow_user_parts:
        raise DqnlabError(
            f"{where} names code to import ({'; '.join(named)}); a pulled agent's settings "
            f"may not import code unless you pass {ALLOW_OPTION} (the modules then come from "
            "your Python environment, never from the repository)"
        )
    try:
        return config_from_dict(values)
    except ConfigError as error:
        raise ConfigError(f"{where}: {error}") from None


def check_folder(folder: Path, allow_user_parts: bool = False) -> CheckedFolder:
    """Check an exported folder from elsewhere; one line naming the first problem."""
    refuse_pickles(
        (path.relative_to(folder).as_posix() for path in folder.rglob("*") if path.is_file()),
        str(folder),
    )
    model = exported.network_path(folder)
    if not model.is_file():
        raise DqnlabError(f"{folder} is not an exported dqnlab agent: no {exported.MODEL_FILE}")
    description = exported.read_description(model)  # the header alone: JSON
    version = description.get("dqnlab_version")
    toml_path = folder / exported.CONFIG_FILE
    try:
        with toml_path.open("rb") as handle:
            values = tomllib.load(handle)
    except FileNotFoundError:
        raise DqnlabError(f"{folder} has no {exported.CONFIG_FILE}") from None
    except tomllib.TOMLDecodeError as error:
        raise DqnlabError(f"{toml_path} is not valid TOML: {error}") from None
    config = checked_config(values, exported.CONFIG_FILE, version, allow_user_parts)
    network_config = checked_config(
        description.get("config"), f"{exported.MODEL_FILE}'s metadata", version, allow_user_parts
    )
    if config_fingerprint(config) != config_fingerprint(network_config):
        raise DqnlabError(
            f"{exported.CONFIG_FILE} and {exported.MODEL_FILE} disagree on "
            f"{', '.join(differing_settings(config, network_config))}"
        )
    check_shapes(network_config, description, model)
    step = description.get("step")
    return CheckedFolder(config, None if step is None else int(step), version)


def check_shapes(config: Config, description: dict[str, Any], model: Path) -> None:
    """The stored input shape, dtype and actions are the environment's, and the tensors
    fit the network the configuration builds for them."""
    try:
        stored_shape = tuple(int(n) for n in description["input_shape"])
        stored_actions = [str(name) for name in description["action_names"]]
        stored_dtype = np.dtype(description.get("observation_dtype", "float32"))
    except (KeyError, TypeError, ValueError) as error:
        raise DqnlabError(f"{model}'s metadata lacks or garbles {error}") from None
    env = make_env(config, training=False, seed=0)
    try:
        shape = (config.history_length, *env.observation_shape)
        actions, dtype = list(env.action_names), np.dtype(env.observation_dtype)
    finally:
        env.close()
    if (stored_shape, len(stored_actions), stored_dtype) != (shape, len(actions), dtype):
        raise DqnlabError(
            f"{exported.MODEL_FILE} does not match {config.env}: the network takes "
            f"{stored_dtype} inputs of shape {stored_shape} and has {len(stored_actions)} "
            f"actions; the environment gives {dtype} inputs of shape {shape} and has "
            f"{len(actions)} actions"
        )
    payload = exported.load_network(model)
    agent_from_network(payload, model, 0, torch.device("cpu"))  # the tensors' shapes
