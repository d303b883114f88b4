"""Loading a user's own part (`module:Name` in a setting): one place, one kind of error."""

from __future__ import annotations

import importlib
from typing import Any

from dqnlab.errors import ConfigError


def load_part(setting: str, path: str, *args: Any) -> Any:
    """`Name(*args)` from `module`, for the setting `setting`; a one-line ConfigError naming
    the setting when the module or name cannot be loaded or the call fails."""
    module_name, _, attribute = path.partition(":")
    try:
        part = getattr(importlib.import_module(module_name), attribute)
    except (ImportError, AttributeError) as error:
        raise ConfigError(f"{setting} = {path!r} cannot be loaded: {error}") from None
    try:
        return part(*args)
    except Exception as error:  # noqa: BLE001 - the user's code: report, don't crash
        raise ConfigError(f"{setting} = {path!r} failed to build: {error!r}") from None
