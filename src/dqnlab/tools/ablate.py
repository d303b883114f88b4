"""Ablations: a small grid of runs that differ in named settings, under one sweep directory.

`dqnlab ablate --env breakout --vary life_loss_terminal=true,false --seeds 2` trains
breakout-{life_loss_terminal=true,false}-s{0,1} one after another (or side by side where
the machine has room), each with `dqnlab train` in its own process and run directory,
then reports them together. Settings that must change together are linked with `+`:
`--vary optimizer+learning_rate=deepmind_rmsprop+0.00025,rmsprop+0.00005` is the seed
paper's optimizer comparison (two runs, not four).

Running the same command again carries on: finished runs are skipped and interrupted ones
resume from their newest checkpoint (`dqnlab train` on an existing run directory).
"""

from __future__ import annotations

import itertools
import os
import re
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil

from dqnlab.config import (
    Config,
    config_to_toml,
    differing_settings,
    parse_overrides,
    resolve_config,
)
from dqnlab.errors import ConfigError, DqnlabError
from dqnlab.run import rundir

LOGS_DIR = "logs"


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
    status: str = "pending"  # pending, done (already finished), ok, failed
    seconds: float = 0.0
    log: Path | None = None


@dataclass
class Sweep:
    directory: Path
    runs: list[PlannedRun] = field(default_factory=list)

    @property
    def failed(self) -> list[PlannedRun]:
        return [run for run in self.runs if run.status == "failed"]


def parse_variation(text: str) -> Variation:
    """`KEY=V1,V2,...` or linked `KEY1+KEY2=A1+A2,B1+B2`; values are read as TOML (as
    `--set`), and commas inside brackets belong to the value (`mlp_hidden_sizes=[64,64],[256]`)."""
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
        depth += {"[": 1, "]": -1}.get(character, 0)
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
    return str(value)


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.=,+-]+", "_", text)


def plan_sweep(
    env: str,
    variations: Sequence[Variation],
    *,
    preset: str,
    overrides: dict[str, Any],
    seeds: int,
    first_seed: int,
    steps: int | None,
    sweep_dir: Path,
) -> Sweep:
    """Every run of the grid (the product of the variations, times the seeds), each config
    resolved and validated before anything starts."""
    if seeds <= 0:
        raise ConfigError(f"--seeds {seeds} must be positive")
    if not variations:
        raise ConfigError("ablate needs at least one --vary KEY=V1,V2")
    varied = [key for variation in variations for key in variation.keys]
    repeated = {key for key in varied if varied.count(key) > 1}
    if repeated:
        raise ConfigError(f"--vary names {', '.join(sorted(repeated))} more than once")
    fixed = {"seed", "env", "total_steps"} & set(varied)
    if fixed:
        raise ConfigError(
            f"--vary cannot vary {', '.join(sorted(fixed))}: use --seeds, --env, --steps"
        )
    sweep = Sweep(sweep_dir)
    for combination in itertools.product(*(variation.choices for variation in variations)):
        settings = {
            key: value
            for variation, values in zip(variations, combination, strict=True)
            for key, value in zip(variation.keys, values, strict=True)
        }
        label = ",".join(f"{key}={_value_text(value)}" for key, value in settings.items())
        for seed in range(first_seed, first_seed + seeds):
            config = resolve_config(
                preset, {**overrides, **settings}, env=env, seed=seed, total_steps=steps
            )
            name = _safe(f"{label}-s{seed}")
            sweep.runs.append(PlannedRun(name, sweep_dir / name, config, settings))
    return sweep


def default_jobs(sweep: Sweep) -> int:
    """Runs side by side where the machine has room: two cores per run (the update keeps
    both cores of a 2-core machine busy), and each run's replay must fit in 80% of the
    available memory."""
    by_cores = max(1, (psutil.cpu_count() or 1) // 2)
    per_run = max(_replay_bytes(run.config) for run in sweep.runs) * 1.1 + 1e9
    by_memory = max(1, int(psutil.virtual_memory().available * 0.8 // per_run))
    return max(1, min(len(sweep.runs), by_cores, by_memory))


def _replay_bytes(config: Config) -> int:
    """About what the run's replay takes: one frame per transition for images."""
    from dqnlab.envs import is_atari

    if is_atari(config.env):
        return config.replay_capacity * config.screen_size * config.screen_size
    return config.replay_capacity * 64  # vector observations: small


def _finished(run: PlannedRun) -> bool:
    if not rundir.is_run_dir(run.run_dir) or rundir.load_run_config(run.run_dir) != run.config:
        return False
    step = rundir.network_step(run.run_dir, "last")
    return step is not None and step >= run.config.total_steps


def _command(run: PlannedRun, config_path: Path, device: str) -> list[str]:
    return [
        sys.executable, "-m", "dqnlab", "train",
        "--env", run.config.env,
        "--preset", str(config_path),
        "--run-dir", str(run.run_dir),
        "--device", device,
        "--no-progress",
    ]  # fmt: skip


def run_sweep(
    sweep: Sweep, *, jobs: int, device: str, echo: Any = print, poll_seconds: float = 0.5
) -> Sweep:
    """Train every run not yet finished, `jobs` at a time, each `dqnlab train` in its own
    process with its output in SWEEP/logs/NAME.log. A failed run does not stop the others."""
    logs = sweep.directory / LOGS_DIR
    logs.mkdir(parents=True, exist_ok=True)
    pending = []
    for run in sweep.runs:
        if _finished(run):
            run.status = "done"
            echo(f"dqnlab: {run.name}: already finished, skipped")
        else:
            pending.append(run)
    threads = max(1, (psutil.cpu_count() or 1) // max(1, jobs))
    environment = {**os.environ, "OMP_NUM_THREADS": str(threads)} if jobs > 1 else None
    running: list[tuple[PlannedRun, subprocess.Popen[bytes], float, Any]] = []
    total = len(sweep.runs)
    while pending or running:
        while pending and len(running) < jobs:
            run = pending.pop(0)
            # The run's whole configuration as a preset file: the child resolves exactly it.
            config_path = logs / f"{run.name}.toml"
            config_path.write_text(config_to_toml(run.config))
            run.log = logs / f"{run.name}.log"
            handle = run.log.open("ab")
            process = subprocess.Popen(
                _command(run, config_path, device),
                stdout=handle,
                stderr=subprocess.STDOUT,
                env=environment,
            )
            index = sweep.runs.index(run) + 1
            echo(f"dqnlab: [{index}/{total}] {run.name}: training (log: {run.log})")
            running.append((run, process, time.perf_counter(), handle))
        time.sleep(poll_seconds)
        for entry in list(running):
            run, process, started, handle = entry
            if process.poll() is None:
                continue
            running.remove(entry)
            handle.close()
            run.seconds = time.perf_counter() - started
            run.status = "ok" if process.returncode == 0 else "failed"
            if run.status == "ok":
                echo(f"dqnlab: {run.name}: finished in {run.seconds:.0f} s")
            else:
                tail = _tail(run.log)
                echo(f"dqnlab: {run.name}: FAILED (exit {process.returncode}); see {run.log}"
                     + (f"\n  {tail}" if tail else ""))  # fmt: skip
    return sweep


def _tail(path: Path | None, lines: int = 3) -> str:
    if path is None or not path.is_file():
        return ""
    text = path.read_text(errors="replace").strip().splitlines()
    return "\n  ".join(text[-lines:])


def check_sweep_dir(sweep: Sweep) -> None:
    """Refuse a sweep directory that holds other runs under this grid's run names (a
    finished or interrupted run of the same grid is fine: it is skipped or resumed)."""
    if rundir.is_run_dir(sweep.directory):
        raise DqnlabError(f"{sweep.directory} is a run directory, not a sweep directory")
    for run in sweep.runs:
        if not rundir.is_run_dir(run.run_dir):
            continue
        differing = differing_settings(rundir.load_run_config(run.run_dir), run.config)
        if differing:
            raise DqnlabError(
                f"{run.run_dir} holds a run with other settings ({', '.join(differing)}); "
                "choose another --sweep-dir"
            )
