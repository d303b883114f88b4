"""A user's own part (`module:Name` in a setting): loading it, one place, one kind of error;
and the settings a part declares for itself (`PartSetting`, `fill_settings`).

A part declares its own settings as a `SETTINGS` attribute, a dict from name to
`PartSetting(default, doc)` (a class attribute, or an attribute of a factory function). The
user sets them per part setting: `[parts.loss]` in a TOML file, `--set parts.loss.tau=0.1`
on the command line; `resolve_config` fills in the declared defaults, so the run's
`config.toml` holds every value the part ran with, and the part reads
`config.parts["loss"]["tau"]`.

A part that draws random numbers subclasses `RandomPart`: the agent gives it a generator
of its own (`generator`, a `torch.Generator` on the training device) and saves its state in
every checkpoint, so that a resumed run draws what it would have drawn
(`algorithm/part_generators.py`).
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from dqnlab.errors import ConfigError

Scalar = bool | int | float | str


@dataclass(frozen=True)
class PartSetting:
    """One setting of a part: its default (whose type is the setting's: bool, int, float
    or str; an int is accepted for a float) and a one-line doc."""

    default: Scalar
    doc: str


class RandomPart:
    """Mixin of a part that draws random numbers (a loss part, or any module of the
    network: a head, a torso). The agent sets `generator` before the part is first used: a
    `torch.Generator` on the training device, the part's own, seeded from the run's seed and
    the part's name, saved in checkpoints. Draw only from it (`torch.rand(...,
    generator=self.generator, device=...)`): numbers from torch's global generator are not
    saved, and a resumed run would draw others. It stays None where no agent owns the part
    (a network built on its own), and torch's functions then draw from the global one."""

    generator: Any = None


def load_part(setting: str, path: str, *args: Any) -> Any:
    """`Name(*args)` from `module`, for the setting `setting`; a one-line ConfigError naming
    the setting when the module or name cannot be loaded or the call fails."""
    part = load_object(setting, path)
    try:
        return part(*args)
    except Exception as error:  # noqa: BLE001 - the user's code: report, don't crash
        raise ConfigError(f"{setting} = {path!r} failed to build: {error!r}") from None


def load_object(setting: str, path: str) -> Any:
    """`Name` from `module` (not called), for the setting `setting`."""
    module_name, _, attribute = path.partition(":")
    try:
        return getattr(importlib.import_module(module_name), attribute)
    except (ImportError, AttributeError) as error:
        reason = " ".join(str(error).split())  # one line, whatever the module raised
        raise ConfigError(f"{setting} = {path!r} cannot be loaded: {reason}") from None


def declared_settings(setting: str, part: Any) -> dict[str, PartSetting]:
    """The settings `part` declares (its `SETTINGS`), checked: names are identifiers and
    each value a `PartSetting` with a bool, int, float or str default."""
    declared = getattr(part, "SETTINGS", None) or {}
    name = getattr(part, "__name__", type(part).__name__)
    if not isinstance(declared, Mapping):
        raise ConfigError(f"{setting} part {name}: SETTINGS must be a dict of PartSetting")
    for key, value in declared.items():
        if not (isinstance(key, str) and key.isidentifier()) or not isinstance(value, PartSetting):
            raise ConfigError(
                f"{setting} part {name}: SETTINGS[{key!r}] must be a PartSetting under a name"
            )
        if not isinstance(value.default, Scalar):  # type: ignore[arg-type, misc]
            raise ConfigError(
                f"{setting} part {name}: {key}'s default {value.default!r} is not a bool, "
                "int, float or str"
            )
    return dict(declared)


def fill_settings(
    setting: str, label: str, declared: Mapping[str, PartSetting], given: Mapping[str, Any]
) -> dict[str, Scalar]:
    """The part's settings: `given` (the user's, from `parts.SETTING`) checked against
    `declared`, the declared defaults for the others. `label` names the part in errors
    (`loss = 'examples.munchausen:MunchausenLoss'`). One-line ConfigErrors: an unknown name
    (with the names the part has), a value of the wrong type."""
    for key in given:
        if key not in declared:
            known = ", ".join(declared) or "none"
            raise ConfigError(
                f"parts.{setting}.{key}: {label} has no setting {key!r} (its settings: {known})"
            )
    filled: dict[str, Scalar] = {}
    for key, spec in declared.items():
        value = given.get(key, spec.default)
        filled[key] = _typed(f"parts.{setting}.{key}", value, spec.default)
    return filled


# The head settings a head factory may honour, which it lists in its `HEAD_OPTIONS`.
HEAD_OPTIONS = ("dueling", "noisy")


def check_head_options(config: Any, factory: Any) -> None:
    """Refuse `dueling` or `noisy` on with a user's head (`head = module:factory`) whose
    factory does not list them in its `HEAD_OPTIONS`: it would build a head without them."""
    honoured = getattr(factory, "HEAD_OPTIONS", ())
    missing = [name for name in HEAD_OPTIONS if getattr(config, name) and name not in honoured]
    if missing:
        raise ConfigError(
            f"head = {config.head!r} is your own head, so {', '.join(missing)} cannot be "
            "added to it: build them into your factory (it gets the settings; heads.QHead is "
            "there to compose) and list them in its HEAD_OPTIONS"
        )


def part_settings(setting: str, part: Any, config: Any) -> dict[str, Scalar]:
    """The settings of `part` (a class or factory named by the setting `setting`) in a run of
    `config`: what `config.parts[setting]` gives, the declared defaults for the rest. A part
    calls it when it is built; `resolve_config` calls it to record them in the run's
    configuration (the same values either way)."""
    name = getattr(part, "__name__", type(part).__name__)
    declared = declared_settings(setting, part)
    return fill_settings(setting, f"{setting} part {name}", declared, config.parts.get(setting, {}))


def _typed(name: str, value: Any, default: Scalar) -> Scalar:
    expected = type(default)
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if type(value) is not expected:
        raise ConfigError(f"{name} = {value!r} is not a valid {expected.__name__}")
    return value  # type: ignore[no-any-return]
