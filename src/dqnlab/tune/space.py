"""The search space of `dqnlab tune`: which settings a study searches and over what, as
data (the default space below, or a user's TOML file over it), checked against the
configuration the trials start from, and sampled for one trial (`suggest`).

An entry is a setting of `Config` or a part's own setting (`parts.loss.tau`), its kind and
its range: `float` and `float-log` (low, high), `int` and `int-log` (low, high),
`categorical` (choices). With `of_steps = true` a range is in fractions of the study's
training budget (`--steps`), rounded to whole steps: the ε anneal, for one, scales with it.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any, Protocol

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from dqnlab.config import Config, resolve_config
from dqnlab.errors import ConfigError

KINDS = ("float", "float-log", "int", "int-log", "categorical")
# The kinds each type of setting may be searched with (bool and str settings: choices).
KINDS_OF_TYPE = {
    float: ("float", "float-log", "categorical"),
    int: ("int", "int-log", "categorical"),
    bool: ("categorical",),
    str: ("categorical",),
}
ENTRY_KEYS = {"kind", "low", "high", "choices", "of_steps", "group"}


@dataclasses.dataclass(frozen=True)
class SearchEntry:
    """One searched setting: `name` as `--set` writes it, how it is drawn, and the part of
    the agent it belongs to (`group`, for the documentation's table)."""

    name: str
    kind: str
    low: float | None = None
    high: float | None = None
    choices: tuple[Any, ...] = ()
    of_steps: bool = False
    group: str = ""

    def as_dict(self) -> dict[str, Any]:
        """The entry as its TOML table (what study.json records)."""
        record: dict[str, Any] = {"kind": self.kind, "group": self.group}
        if self.kind == "categorical":
            record["choices"] = list(self.choices)
        else:
            record.update(low=self.low, high=self.high, of_steps=self.of_steps)
        return record


def _range(name: str, kind: str, low: float, high: float, group: str, **kw: Any) -> SearchEntry:
    return SearchEntry(name, kind, low, high, group=group, **kw)


def _choices(name: str, choices: tuple[Any, ...], group: str) -> SearchEntry:
    return SearchEntry(name, "categorical", choices=choices, group=group)


# The default space, by part of the agent. Its ranges follow rl-baselines3-zoo's DQN
# sampler (rl_zoo3/hyperparams_opt.py, sample_dqn_params: learning rate 1e-5..2e-3 log,
# batch 16..512, target_update_interval 1..20,000, exploration_final_eps 0..0.2,
# exploration_fraction 0..0.5, buffer 1e4..1e6, learning_starts 0..20,000, train_freq
# 1..256), the two budget-bound ones (the ε anneal, learning_starts) as fractions of the
# budget so that every trial learns and is evaluated whatever --steps.
DEFAULT_SPACE = (
    _range("learning_rate", "float-log", 1e-5, 2e-3, "optimizer"),
    _choices("batch_size", (16, 32, 64, 128, 256, 512), "optimizer"),
    _choices("update_period_steps", (1, 2, 4, 8, 16), "optimizer"),
    _choices("target_update_steps", (1, 100, 250, 500, 1_000, 5_000, 10_000), "target"),
    _choices("target", ("max", "double"), "target"),
    _range("epsilon_end", "float", 0.0, 0.2, "exploration"),
    _range("epsilon_decay_steps", "float", 0.0, 0.5, "exploration", of_steps=True),
    _choices("replay_capacity", (10_000, 50_000, 100_000, 1_000_000), "replay"),
    _range("replay_start_steps", "float", 0.01, 0.2, "replay", of_steps=True),
    _choices("n_step", (1, 3, 5), "replay"),
    _choices("dueling", (False, True), "network"),
)


class Trial(Protocol):
    """What `suggest` asks of a trial: Optuna's `Trial`, `FixedTrial` or a fake."""

    def suggest_float(self, name: str, low: float, high: float, *, log: bool = False) -> float: ...

    def suggest_int(self, name: str, low: int, high: int, *, log: bool = False) -> int: ...

    def suggest_categorical(self, name: str, choices: Any) -> Any: ...


def suggest(trial: Trial, space: tuple[SearchEntry, ...], steps: int) -> dict[str, Any]:
    """One trial's settings: each entry drawn from `trial`, as `--set` overrides."""
    overrides: dict[str, Any] = {}
    for entry in space:
        if entry.kind == "categorical":
            overrides[entry.name] = trial.suggest_categorical(entry.name, list(entry.choices))
            continue
        low, high = _bounds(entry, steps)
        log = entry.kind.endswith("-log")
        if entry.kind.startswith("int"):
            overrides[entry.name] = trial.suggest_int(entry.name, int(low), int(high), log=log)
        else:
            value = trial.suggest_float(entry.name, float(low), float(high), log=log)
            overrides[entry.name] = round(value) if entry.of_steps else value
    return overrides


def _bounds(entry: SearchEntry, steps: int) -> tuple[float, float]:
    assert entry.low is not None and entry.high is not None
    if entry.of_steps:
        return entry.low * steps, entry.high * steps
    return entry.low, entry.high


def load_space(path: Path | None) -> tuple[SearchEntry, ...]:
    """The default space, with a user's TOML file's entries over it (`[learning_rate]`
    then `kind = "float-log"`, `low = 1e-5`, `high = 1e-3`; a part's own setting as
    `["parts.loss.tau"]`). `extend_default = false` at the top searches the file's alone;
    `drop = ["n_step", ...]` at the top leaves those default entries out."""
    if path is None:
        return DEFAULT_SPACE
    try:
        values = tomllib.loads(path.read_text())
    except OSError as error:
        raise ConfigError(f"--space {path}: cannot read it: {error.strerror}") from None
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"--space {path} is not valid TOML: {error}") from None
    extend = values.pop("extend_default", True)
    if not isinstance(extend, bool):
        raise ConfigError(f"--space {path}: extend_default = {extend!r} must be true or false")
    space = {entry.name: entry for entry in (DEFAULT_SPACE if extend else ())}
    for name in _dropped(path, values.pop("drop", []), extend):
        del space[name]
    for name, table in values.items():
        space[name] = _entry(name, table)
    if not space:
        raise ConfigError(f"--space {path} searches no setting")
    return tuple(space.values())


def _dropped(path: Path, drop: Any, extend: bool) -> list[str]:
    """The default entries `drop = [...]` leaves out, each checked to be one."""
    if not isinstance(drop, list) or not all(isinstance(name, str) for name in drop):
        raise ConfigError(f"--space {path}: drop = {drop!r} must be a list of setting names")
    if drop and not extend:
        raise ConfigError(
            f"--space {path}: drop = {drop!r} with extend_default = false: there is no "
            "default entry to drop"
        )
    defaults = [entry.name for entry in DEFAULT_SPACE]
    for name in drop:
        if name not in defaults:
            raise ConfigError(
                f"--space {path}: drop names {name!r}, which is not in the default space "
                f"({', '.join(defaults)})"
            )
    return list(dict.fromkeys(drop))


def _entry(name: str, table: Any) -> SearchEntry:
    """One entry of a space file, its keys and their types checked."""
    where = f"search space entry {name!r}"
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table (kind, low and high, or choices)")
    unknown = sorted(set(table) - ENTRY_KEYS)
    if unknown:
        raise ConfigError(f"{where}: unknown key {unknown[0]!r}; accepted: {sorted(ENTRY_KEYS)}")
    kind = table.get("kind", "categorical" if "choices" in table else None)
    if kind not in KINDS:
        raise ConfigError(f"{where}: kind = {kind!r} is not one of {', '.join(KINDS)}")
    group = str(table.get("group", "yours"))
    if kind == "categorical":
        choices = table.get("choices")
        if not isinstance(choices, list) or not choices or "low" in table or "high" in table:
            raise ConfigError(f"{where}: a categorical entry has a non-empty list of choices")
        return SearchEntry(name, kind, choices=tuple(choices), group=group)
    low, high, of_steps = table.get("low"), table.get("high"), table.get("of_steps", False)
    if not (_is_number(low) and _is_number(high)):
        raise ConfigError(f"{where}: a {kind} entry has numbers low and high")
    assert isinstance(low, (int, float)) and isinstance(high, (int, float))
    if not low < high or (kind.endswith("-log") and low <= 0):
        raise ConfigError(f"{where}: low = {low} and high = {high} are not a {kind} range")
    if not isinstance(of_steps, bool):
        raise ConfigError(f"{where}: of_steps = {of_steps!r} must be true or false")
    return SearchEntry(name, kind, float(low), float(high), of_steps=of_steps, group=group)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def check_space(
    space: tuple[SearchEntry, ...], preset: str, fixed: dict[str, Any], env: str, steps: int
) -> None:
    """Every entry names a setting the trials' configuration has, with a kind its type
    takes, and every bound and choice is a value the configuration accepts: a
    ConfigError naming the entry otherwise, before any trial runs."""
    base = resolve_config(preset, fixed, env=env, total_steps=steps)
    for entry in space:
        where = f"search space entry {entry.name!r}"
        if entry.name in fixed:
            raise ConfigError(f"{where}: {entry.name} is also fixed by --set; search or fix it")
        current = _current_value(base, entry.name, where)
        kinds = KINDS_OF_TYPE.get(type(current), ())
        if entry.of_steps and isinstance(current, int) and not isinstance(current, bool):
            kinds = ("float", "float-log", "int", "int-log")  # fractions, rounded to steps
        if entry.kind not in kinds:
            raise ConfigError(
                f"{where}: {entry.name} is a {type(current).__name__} setting, searched with "
                f"{' or '.join(kinds) or 'nothing'}, not {entry.kind}"
            )
        values = entry.choices if entry.kind == "categorical" else _bounds(entry, steps)
        if entry.of_steps and entry.kind.startswith("float"):
            values = tuple(round(v) for v in values)
        for value in values:
            try:
                resolve_config(preset, {**fixed, entry.name: value}, env=env, total_steps=steps)
            except ConfigError as error:
                raise ConfigError(
                    f"{where}: {entry.name} = {value!r} is refused: {error}"
                ) from None


def _current_value(config: Config, name: str, where: str) -> Any:
    """The value of setting `name` (or `parts.PART.NAME`) in `config`."""
    if name.startswith("parts."):
        _, part, setting = (name.split(".") + ["", ""])[:3]
        table = config.parts.get(part, {})
        if setting not in table:
            declared = ", ".join(sorted(table)) or "none"
            raise ConfigError(
                f"{where}: the {part or '?'} part of this configuration declares no setting "
                f"{setting!r} (declared: {declared})"
            )
        return table[setting]
    if name not in {f.name for f in dataclasses.fields(Config)}:
        raise ConfigError(f"{where}: unknown setting {name!r}")
    return getattr(config, name)
