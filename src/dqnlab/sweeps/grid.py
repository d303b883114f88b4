"""The grid of a sweep: games × --vary settings × seeds, each run's name, configuration
and directory, all resolved and checked before anything starts; and the sweep directory's
sweep.json, which `dqnlab status` and each run's worker read."""

from __future__ import annotations

import itertools
import json
import os
import re
import secrets
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dqnlab.analysis import status as run_states
from dqnlab.config import (
    Config,
    differing_settings,
    parse_overrides,
    resolve_config,
    with_env_arguments,
)
from dqnlab.errors import ConfigError, DqnlabError
from dqnlab.run import rundir

SWEEP_FORMAT = "dqnlab-sweep-1"


@dataclass(frozen=True)
class Variation:
    """One `--vary` option: settings `keys` take the value tuples in `choices` in turn."""

    keys: tuple[str, ...]
    choices: tuple[tuple[Any, ...], ...]


@dataclass
class PlannedRun:
    name: str
    run_dir: Path
    config: Config
    settings: dict[str, Any]  # the varied settings and their values
    status: str = "pending"  # pending, done (already finished), ok, failed, stopped
    seconds: float = 0.0
    log: Path | None = None
    node: str | None = None


@dataclass
class Sweep:
    directory: Path
    runs: list[PlannedRun] = field(default_factory=list)
    preset: str = ""
    vary_keys: tuple[str, ...] = ()

    @property
    def failed(self) -> list[PlannedRun]:
        return [run for run in self.runs if run.status == "failed"]


def parse_variation(text: str) -> Variation:
    """`KEY=V1,V2,...` or linked `KEY1+KEY2=A1+A2,B1+B2`; values are read as TOML (as
    `--set`), and commas inside brackets or braces belong to the value
    (`mlp_hidden_sizes=[64,64],[256]`, `env_kwargs={map_name="4x4"},{map_name="8x8"}`)."""
    names, sep, values = text.partition("=")
    keys = tuple(name.strip() for name in names.split("+"))
    if not sep or not all(keys) or not values.strip():
        raise ConfigError(f"--vary expects KEY=V1,V2 or KEY1+KEY2=A1+A2,B1+B2, got {text!r}")
    if len(set(keys)) != len(keys):
        raise ConfigError(f"--vary {text!r} names a setting twice")
    choices = []
    for choice in _split_top_level(values):
        parts = choice.split("+") if len(keys) > 1 else [choice]
        if len(parts) != len(keys):
            raise ConfigError(
                f"--vary {text!r}: value {choice!r} gives {len(parts)} values for "
                f"{len(keys)} settings ({'+'.join(keys)})"
            )
        parsed = parse_overrides([f"{key}={part}" for key, part in zip(keys, parts, strict=True)])
        choices.append(tuple(parsed[key] for key in keys))
    if len(set(map(repr, choices))) != len(choices):
        raise ConfigError(f"--vary {text!r} lists a value twice")
    return Variation(keys, tuple(choices))


def _split_top_level(text: str) -> list[str]:
    pieces, depth, current = [], 0, ""
    for character in text:
        depth += {"[": 1, "]": -1, "{": 1, "}": -1}.get(character, 0)
        if character == "," and depth == 0:
            pieces.append(current.strip())
            current = ""
        else:
            current += character
    pieces.append(current.strip())
    if any(not piece for piece in pieces):
        raise ConfigError(f"--vary values {text!r} contain an empty value")
    return pieces


def _value_text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "-".join(str(v) for v in value)
    if isinstance(value, dict):  # env_kwargs: KEY=VALUE pairs
        return "+".join(f"{k}={_value_text(v)}" for k, v in value.items())
    return str(value)


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.=,+-]+", "_", text)


GAME_SETS = ("nature49", "atari57", "atari100k")


def game_set(name: str) -> list[str]:
    """The games of `--games`: nature49 (the Nature table's 49), atari57, atari100k (the
    Atari 100k benchmark's 26, Kaiser et al. 2019), or a file with one game per line (#
    starts a comment); each checked to be a game ale-py ships."""
    from dqnlab.analysis.report.scores import load_atari100k_scores, load_reference_scores
    from dqnlab.envs import check_env_name

    scores = load_reference_scores()
    if name == "nature49":
        return sorted(game for game, row in scores.items() if row.nature_dqn is not None)
    if name == "atari57":
        return sorted(scores)
    if name == "atari100k":
        return sorted(load_atari100k_scores())
    path = Path(name)
    if not path.is_file():
        raise ConfigError(
            f"--games {name!r} is not a game set; accepted: {', '.join(GAME_SETS)}, or a "
            "file with one game per line"
        )
    games = [line.split("#")[0].strip() for line in path.read_text().splitlines()]
    games = [game for game in games if game]
    if not games:
        raise ConfigError(f"--games {name}: the file lists no games")
    for game in games:
        check_env_name(game)
    return games


def plan_grid(
    envs: Sequence[str],
    variations: Sequence[Variation],
    *,
    preset: str | None,
    overrides: dict[str, Any],
    seeds: int,
    first_seed: int,
    steps: int | None,
    sweep_dir: Path,
    env_in_names: bool = True,
    env_kwargs: dict[str, Any] | None = None,
    env_wrappers: Sequence[str] = (),
) -> Sweep:
    """Every run of envs × the product of the variations × seeds, each config resolved
    and validated before anything starts, `env_kwargs` and `env_wrappers` (--env-kwarg,
    --wrapper) added to its own. Run names are ENV-SETTINGS-sSEED (`ablate`, one
    environment: SETTINGS-sSEED)."""
    from dqnlab.envs import default_preset

    if seeds <= 0:
        raise ConfigError(f"--seeds {seeds} must be positive")
    varied = [key for variation in variations for key in variation.keys]
    repeated = {key for key in varied if varied.count(key) > 1}
    if repeated:
        raise ConfigError(f"--vary names {', '.join(sorted(repeated))} more than once")
    fixed = {"seed", "env", "total_steps"} & set(varied)
    if fixed:
        raise ConfigError(
            f"--vary cannot vary {', '.join(sorted(fixed))}: use --seeds, --env, --steps"
        )
    presets = {preset or default_preset(env) for env in envs}
    sweep = Sweep(sweep_dir, preset=",".join(sorted(presets)), vary_keys=tuple(varied))
    for env in envs:
        env_preset = preset or default_preset(env)
        for combination in itertools.product(*(variation.choices for variation in variations)):
            settings = {
                key: value
                for variation, values in zip(variations, combination, strict=True)
                for key, value in zip(variation.keys, values, strict=True)
            }
            label = ",".join(f"{key}={_value_text(value)}" for key, value in settings.items())
            prefix = rundir.safe_name(env) if env_in_names else ""
            for seed in range(first_seed, first_seed + seeds):
                config = resolve_config(
                    env_preset, {**overrides, **settings}, env=env, seed=seed, total_steps=steps
                )
                config = with_env_arguments(config, env_kwargs or {}, env_wrappers)
                name = _safe("-".join(part for part in (prefix, label, f"s{seed}") if part))
                sweep.runs.append(PlannedRun(name, sweep_dir / name, config, settings))
    return sweep


def check_sweep_dir(sweep: Sweep) -> None:
    """Refuse a sweep directory that holds a different sweep: other varied settings or
    preset in its sweep.json, or other runs under this grid's run names (a finished or
    interrupted run of the same grid is fine: it is skipped or resumed)."""
    if rundir.is_run_dir(sweep.directory):
        raise DqnlabError(f"{sweep.directory} is a run directory, not a sweep directory")
    recorded = run_states.load_sweep_file(sweep.directory)
    if recorded is not None and (
        tuple(recorded.get("vary_keys", ())) != sweep.vary_keys
        or recorded.get("preset") != sweep.preset
    ):
        raise DqnlabError(
            f"{sweep.directory} holds a different sweep (preset {recorded.get('preset')}, "
            f"varied: {', '.join(recorded.get('vary_keys', [])) or 'nothing'}); "
            "choose another --sweep-dir"
        )
    for run in sweep.runs:
        if not rundir.is_run_dir(run.run_dir):
            continue
        differing = differing_settings(rundir.load_run_config(run.run_dir), run.config)
        if differing:
            raise DqnlabError(
                f"{run.run_dir} holds a run with other settings ({', '.join(differing)}); "
                "choose another --sweep-dir"
            )


def planned_record(run: PlannedRun) -> dict[str, Any]:
    """The run as sweep.json and `status.run_status` know it."""
    return {"name": run.name, "env": run.config.env, "seed": run.config.seed,
            "settings": run.settings, "total_steps": run.config.total_steps}  # fmt: skip


def write_sweep_file(sweep: Sweep) -> str:
    """SWEEP/sweep.json: the grid (for `dqnlab status`) and the marker token each run
    checks it sees (the shared-storage check). An existing sweep keeps its token."""
    recorded = run_states.load_sweep_file(sweep.directory) or {}
    token = recorded.get("token") or secrets.token_hex(8)
    runs = {run["name"]: run for run in recorded.get("runs", [])}
    for run in sweep.runs:
        runs[run.name] = planned_record(run)
    record = {
        "format": SWEEP_FORMAT,
        "token": token,
        "preset": sweep.preset,
        "vary_keys": list(sweep.vary_keys),
        "runs": list(runs.values()),
    }
    sweep.directory.mkdir(parents=True, exist_ok=True)
    path = rundir.sweep_file_path(sweep.directory)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(json.dumps(record, indent=2) + "\n")
    os.replace(temporary, path)
    return token
