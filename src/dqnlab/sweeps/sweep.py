"""Sweeps: a grid of games × settings × seeds, each run `dqnlab train` in its own run
directory, scheduled by Ray on this machine or a cluster. `dqnlab sweep` and `dqnlab
ablate` both run here: there is one scheduling code path, Ray's.

Why Ray tasks, not Ray Tune: a run already is a resumable unit (its run directory, its
newest complete checkpoint), so what a sweep needs from an engine is placement by
resources (CPUs, GPU fractions, memory) and retry of a run whose process or node died.
A Ray task with `max_retries` and `retry_exceptions` gives exactly that. Tune would add a
second checkpoint layout (its trial directories and `Tuner.restore` state) beside the run
directories, and its trial-level resume would duplicate what `dqnlab train` does on an
existing run directory.

    driver (this process)                         a Ray worker on some node
    plan the grid, check inputs, write sweep.json
    submit one task per unfinished run  ───────►  check SWEEP/sweep.json is the driver's
    poll the run directories: live table          wait for the run's lease to be free
    Ctrl-C: cancel the tasks ─────────────────►   run `dqnlab train` (a subprocess that
    report                                        dies with the worker), resume if started

A run whose subprocess was killed (SIGKILL, the OOM killer, a node preempted) raises
RunProcessKilled, which Ray retries on any node; the retry resumes the run from its newest
complete checkpoint. A run that fails for a reason a retry does not cure (a bad setting,
diverged training) is reported with the tail of its log, and the others go on.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import secrets
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from rich.live import Live

from dqnlab.analysis import status as run_states
from dqnlab.config import (
    Config,
    config_to_toml,
    differing_settings,
    parse_overrides,
    resolve_config,
)
from dqnlab.errors import ConfigError, DqnlabError
from dqnlab.run import rundir
from dqnlab.run.lease import LEASE_HELD_EXIT_STATUS, release_dead_owner, wait_until_free

SWEEP_FORMAT = "dqnlab-sweep-1"
DEFAULT_MAX_RETRIES = 3
# Host memory of a `dqnlab train` process besides its replay: peak RSS of tiny runs
# (replay of 1,000 slots) measured with `/usr/bin/time -v` (README, figures), 0.9 GB on
# CartPole and 1.1 GB on Pong, rounded up for the evaluation's worker processes.
PROCESS_OVERHEAD_BYTES = 1_500_000_000
VECTOR_SLOT_BYTES = 1024  # a vector observation's slot: up to 256 float32 features
STOP_WAIT_SECONDS = 300.0  # Ctrl-C: how long runs may take to write their checkpoint
SUMMARY_SECONDS = 30.0  # the live table's overall line, at least this often
# `dqnlab train` exit statuses after a stop request (SIGINT, SIGTERM) and SIGKILL by shell.
STOPPED_EXIT_STATUS, TERMINATED_EXIT_STATUS, KILLED_EXIT_STATUS = 130, 143, 137


class RunProcessKilled(Exception):
    """The run's process died by a signal: Ray retries the task (retry_exceptions)."""


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


@dataclass(frozen=True)
class RunResources:
    """What each run asks Ray for: CPUs (also its PyTorch threads), GPUs (fractions
    share one), and host memory in bytes (its replay plus the process)."""

    cpus: float
    gpus: float
    memory_bytes: int


# The grid ------------------------------------------------------------------------------


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


def game_set(name: str) -> list[str]:
    """The games of `--games`: nature49 (the Nature table's 49), atari57, or a file with one
    game per line (# starts a comment); each checked to be a game ale-py ships."""
    from dqnlab.analysis.report.scores import load_reference_scores
    from dqnlab.envs import check_env_name

    scores = load_reference_scores()
    if name == "nature49":
        return sorted(game for game, row in scores.items() if row.nature_dqn is not None)
    if name == "atari57":
        return sorted(scores)
    path = Path(name)
    if not path.is_file():
        raise ConfigError(
            f"--games {name!r} is not a game set; accepted: nature49, atari57, or a file "
            "with one game per line"
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
) -> Sweep:
    """Every run of envs × the product of the variations × seeds, each config resolved
    and validated before anything starts. Run names are ENV-SETTINGS-sSEED (`ablate`,
    one environment: SETTINGS-sSEED)."""
    from dqnlab.envs import is_atari

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
    presets = {preset or ("nature" if is_atari(env) else "classic") for env in envs}
    sweep = Sweep(sweep_dir, preset=",".join(sorted(presets)), vary_keys=tuple(varied))
    for env in envs:
        env_preset = preset or ("nature" if is_atari(env) else "classic")
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


def write_sweep_file(sweep: Sweep) -> str:
    """SWEEP/sweep.json: the grid (for `dqnlab status`) and the marker token each run
    checks it sees (the shared-storage check). An existing sweep keeps its token."""
    recorded = run_states.load_sweep_file(sweep.directory) or {}
    token = recorded.get("token") or secrets.token_hex(8)
    runs = {run["name"]: run for run in recorded.get("runs", [])}
    for run in sweep.runs:
        runs[run.name] = {
            "name": run.name,
            "env": run.config.env,
            "seed": run.config.seed,
            "settings": run.settings,
            "total_steps": run.config.total_steps,
        }
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


# Resources -----------------------------------------------------------------------------


def replay_memory_bytes(config: Config) -> int:
    """Host bytes of the run's replay: the frames (compressed where the codec's measured
    size is known) of an Atari game, a generous slot for vector observations."""
    from dqnlab.algorithm.compression import expected_frame_bytes
    from dqnlab.algorithm.replay import compresses, replay_bytes
    from dqnlab.envs import is_atari

    if not is_atari(config.env):
        return config.replay_capacity * VECTOR_SLOT_BYTES
    frame_shape = (config.screen_size, config.screen_size)
    compressed = None
    if compresses(config.replay_compression, frame_shape):
        compressed = expected_frame_bytes(config.replay_compression, config.env)
    import numpy as np

    return replay_bytes(config.replay_capacity, frame_shape, np.dtype(np.uint8), compressed)


def run_memory_bytes(config: Config) -> int:
    return replay_memory_bytes(config) + PROCESS_OVERHEAD_BYTES


def sweep_resources(
    sweep: Sweep, cpus: float, gpus: float, memory_bytes: int | None = None
) -> RunResources:
    """Each run's request: the largest replay of the grid, unless `memory_bytes` says."""
    if cpus <= 0:
        raise DqnlabError(f"--cpus-per-run {cpus} must be positive")
    if gpus < 0 or gpus > 1 and gpus != int(gpus):
        raise DqnlabError(f"--gpus-per-run {gpus} must be a fraction of one GPU or whole GPUs")
    memory = memory_bytes or max(run_memory_bytes(run.config) for run in sweep.runs)
    return RunResources(cpus, gpus, memory)


def check_resources(resources: RunResources, nodes: list[dict[str, float]]) -> None:
    """Refuse up front a run that no node of the cluster can hold, with the numbers."""
    if resources.gpus > 0 and not any(node.get("GPU", 0) > 0 for node in nodes):
        raise DqnlabError(
            f"--gpus-per-run {resources.gpus:g}: the cluster has no GPUs ({len(nodes)} nodes); "
            "accepted here: --gpus-per-run 0"
        )
    fits = [
        node
        for node in nodes
        if node.get("CPU", 0) >= resources.cpus
        and node.get("GPU", 0) >= resources.gpus
        and node.get("memory", 0) >= resources.memory_bytes
    ]
    if not fits:
        largest = ", ".join(
            f"{node.get('CPU', 0):g} CPUs/{node.get('GPU', 0):g} GPUs/"
            f"{node.get('memory', 0) / 1e9:.1f} GB" for node in nodes
        )  # fmt: skip
        raise DqnlabError(
            f"each run asks for {resources.cpus:g} CPUs, {resources.gpus:g} GPUs and "
            f"{resources.memory_bytes / 1e9:.1f} GB of memory, more than any node has "
            f"(nodes: {largest or 'none'}); lower --cpus-per-run/--gpus-per-run, or "
            "replay_capacity (--set), or add larger nodes"
        )


# A run, on a Ray worker ----------------------------------------------------------------

# The Ray workers that run the runs, on any cluster. A worker that exits (its node lost,
# its raylet gone) SIGKILLs its child processes unless told not to (Ray 2.60: "Try killing
# all child processes of this worker as it exits" in the worker's log): the run's process
# would die without its stop checkpoint and without releasing its lease. Without that
# kill, `_DIE_WITH_PARENT`'s SIGTERM reaches it and it checkpoints and stops.
WORKER_ENVIRONMENT = {"RAY_kill_child_processes_on_worker_exit": "0"}

# Run first in the subprocess. It sends itself one SIGTERM when the worker that started it
# dies (a lost node, a killed Ray), so that it checkpoints and stops instead of training on
# unowned. One: `dqnlab train` takes a second stop request as "stop at once", and
# PR_SET_PDEATHSIG, tried first, fires each time a thread the child is reparented to exits
# (measured with strace on a lost node: two or three SIGTERMs from the dying worker, the
# second one often before the stop checkpoint was written). Hence a thread watching the
# parent's pid. It also unblocks SIGINT and SIGTERM: a Ray worker's threads block SIGINT, a
# child inherits the mask (measured with Ray 2.60: SigBlk 0x2 in /proc/PID/status), and a
# blocked SIGINT never reaches the training loop's stop handler.
PARENT_POLL_SECONDS = 0.5
_DIE_WITH_PARENT = (
    "import os, signal, sys, threading, time\n"
    "signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})\n"
    "parent = int(sys.argv.pop(1))\n"
    "if os.getppid() != parent:\n"
    "    sys.exit(143)\n"
    "def stop_when_orphaned():\n"
    "    while os.getppid() == parent:\n"
    f"        time.sleep({PARENT_POLL_SECONDS})\n"
    "    os.kill(os.getpid(), signal.SIGTERM)\n"
    "threading.Thread(target=stop_when_orphaned, daemon=True).start()\n"
    "sys.argv[0] = 'dqnlab'\n"
    "from dqnlab.cli import main\n"
    "main()\n"
)


def train_command(task: dict[str, Any]) -> list[str]:
    return [
        sys.executable, "-c", _DIE_WITH_PARENT, str(os.getpid()), "train",
        "--env", task["env"],
        "--preset", task["config_path"],
        "--run-dir", task["run_dir"],
        "--device", task["device"],
        "--no-progress",
    ]  # fmt: skip


def train_attempt(task: dict[str, Any]) -> dict[str, Any]:
    """One attempt at one run, in a Ray worker: check the shared storage, wait for the run's
    lease, train (resuming if started) in a subprocess. Returns {"outcome": done, ok,
    failed or stopped, ...}; raises RunProcessKilled for Ray to retry."""
    import ray

    host = socket.gethostname()
    sweep_dir, run_dir = Path(task["sweep_dir"]), Path(task["run_dir"])
    check_sweep_marker(sweep_dir, task["token"], host)
    if _finished_run(run_dir, task["total_steps"]):
        return {"outcome": "done", "host": host}
    run_dir.mkdir(parents=True, exist_ok=True)
    attempt = sum(e.get("event") == "start" for e in run_states.read_attempts(run_dir)) + 1
    node_id = ray.get_runtime_context().get_node_id()
    environment = {**os.environ, "OMP_NUM_THREADS": str(task["threads"]),
                   "MKL_NUM_THREADS": str(task["threads"])}  # fmt: skip
    while True:
        wait_until_free(run_dir)
        started = time.time()
        with open(task["log"], "ab") as log:
            process = subprocess.Popen(
                train_command(task), stdout=log, stderr=subprocess.STDOUT, env=environment,
                start_new_session=True,  # a Ctrl-C reaches it from the driver, not the terminal
            )  # fmt: skip
            run_states.record_attempt(run_dir, {
                "event": "start", "attempt": attempt, "node_id": node_id, "host": host,
                "pid": process.pid, "time": started,
            })  # fmt: skip
            code = _wait_for(process)
        if code != LEASE_HELD_EXIT_STATUS:
            break
        # Another process took the lease between our wait and the start: wait again.
    ended = time.time()
    if code == 0:
        outcome = "done"
    elif code == STOPPED_EXIT_STATUS:
        outcome = "stopped"
    elif code < 0 or code in (TERMINATED_EXIT_STATUS, KILLED_EXIT_STATUS):
        outcome = "killed"
        release_dead_owner(run_dir, process.pid)
    else:
        outcome = "failed"
    run_states.record_attempt(run_dir, {
        "event": "end", "attempt": attempt, "outcome": outcome, "exit_status": code,
        "time": ended,
    })  # fmt: skip
    if outcome == "killed":
        raise RunProcessKilled(f"{task['name']}: exit status {code} on {host}")
    return {"outcome": "ok" if outcome == "done" else outcome, "host": host,
            "exit_status": code, "seconds": ended - started}  # fmt: skip


def _wait_for(process: subprocess.Popen[bytes]) -> int:
    """The subprocess's exit status; a cancel (ray.cancel raises KeyboardInterrupt here)
    asks it to checkpoint and stop (SIGINT) and waits for that."""
    try:
        while True:
            try:
                return process.wait(timeout=1.0)  # wakes up to let a cancel in
            except subprocess.TimeoutExpired:
                continue
    except KeyboardInterrupt:
        process.send_signal(signal.SIGINT)
        return process.wait(timeout=STOP_WAIT_SECONDS)


def check_sweep_marker(sweep_dir: Path, token: str, host: str) -> None:
    """Fail on a node that does not see the driver's sweep directory (not shared storage):
    training there would go into a local directory lost with the node."""
    recorded = run_states.load_sweep_file(sweep_dir) if sweep_dir.is_dir() else None
    if recorded is None or recorded.get("token") != token:
        raise DqnlabError(
            f"node {host} does not see the sweep directory {sweep_dir} the driver created "
            f"({rundir.SWEEP_FILE} {'missing' if recorded is None else 'of another sweep'}): "
            "the sweep directory must be on storage every node mounts at the same path"
        )


def _finished_run(run_dir: Path, total_steps: int) -> bool:
    step = rundir.network_step(run_dir, "last") if rundir.is_run_dir(run_dir) else None
    return step is not None and step >= total_steps


def finished(run: PlannedRun) -> bool:
    """Whether the run is trained to its budget with exactly this configuration."""
    if not rundir.is_run_dir(run.run_dir) or rundir.load_run_config(run.run_dir) != run.config:
        return False
    return _finished_run(run.run_dir, run.config.total_steps)


# The driver ----------------------------------------------------------------------------


def run_sweep_on_ray(
    sweep: Sweep,
    resources: RunResources,
    *,
    device: str,
    max_retries: int = DEFAULT_MAX_RETRIES,
    echo: Callable[[str], Any] = print,
    poll_seconds: float = 1.0,
    summary_seconds: float = SUMMARY_SECONDS,
    live: bool = False,
) -> Sweep:
    """Train every unfinished run of `sweep` as a Ray task (the caller is connected to Ray
    and has checked the inputs), printing a line per change of a run's state and an overall
    line at least every `summary_seconds`; `live` (the output is a terminal): one table
    redrawn in place instead, with the lines that matter afterwards (a run finished, failed,
    stopped) printed above it. Ctrl-C cancels the tasks: each run writes a checkpoint
    first; then KeyboardInterrupt is raised again."""
    import ray

    token = write_sweep_file(sweep)
    logs = rundir.sweep_logs_dir(sweep.directory)
    logs.mkdir(parents=True, exist_ok=True)
    remote = ray.remote(train_attempt).options(
        num_cpus=resources.cpus, num_gpus=resources.gpus, memory=resources.memory_bytes or None,
        max_retries=max_retries, retry_exceptions=[RunProcessKilled],
        runtime_env={"env_vars": dict(WORKER_ENVIRONMENT)},
    )  # fmt: skip
    total = len(sweep.runs)
    pending: dict[Any, PlannedRun] = {}
    for index, run in enumerate(sweep.runs, 1):
        if finished(run):
            run.status = "done"
            echo(f"dqnlab: {run.name}: already finished, skipped")
            continue
        # The run's whole configuration as a preset file: the run resolves exactly it.
        config_path = logs / f"{run.name}.toml"
        config_path.write_text(config_to_toml(run.config))
        run.log = logs / f"{run.name}.log"
        task = {
            "name": run.name, "env": run.config.env, "config_path": str(config_path.absolute()),
            "run_dir": str(run.run_dir.absolute()), "log": str(run.log.absolute()),
            "sweep_dir": str(sweep.directory.absolute()), "token": token, "device": device,
            "threads": max(1, int(resources.cpus)), "total_steps": run.config.total_steps,
        }  # fmt: skip
        pending[remote.remote(task)] = run
        echo(f"dqnlab: [{index}/{total}] {run.name}: submitted (log: {run.log})")
    try:
        if live:
            with Live(auto_refresh=False) as screen:
                _follow(sweep, pending, _LiveTable(screen), poll_seconds)
        else:
            _follow(sweep, pending, _StateLines(echo, summary_seconds), poll_seconds)
    except KeyboardInterrupt:
        _stop(pending, echo)  # the live table has left the terminal: plain lines
        raise
    return sweep


class _Display(Protocol):
    def message(self, text: str) -> None: ...

    def update(self, statuses: list[run_states.RunStatus], last: bool) -> None: ...


def _follow(
    sweep: Sweep, pending: dict[Any, PlannedRun], display: _Display, poll_seconds: float
) -> None:
    """Until every task has returned: each returned task's outcome as a message, and every
    run's state (from its files) to the display after each poll."""
    import ray

    while pending:
        ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=poll_seconds)
        for reference in ready:
            _finish(pending.pop(reference), reference, display.message)
        display.update([_polled_status(run) for run in sweep.runs], last=not pending)


def _polled_status(run: PlannedRun) -> run_states.RunStatus:
    """The run's state from its files, corrected by what the driver knows: its task has
    returned (done, failed, stopped) or not yet (running)."""
    status = run_states.run_status(run.run_dir, planned_record(run))
    if run.status in ("done", "ok", "failed", "stopped"):
        status.state = {"ok": "done"}.get(run.status, run.status)
    elif status.state in ("done", "failed", "stopped"):
        status.state = "running"  # the task has not returned yet
    if status.state == "done":
        status.step = status.total_steps
    return status


class _StateLines:
    """A log's view of the sweep (a file, `ray job submit`, tests): a line per change of a
    run's state, and the overall line at least every `summary_seconds` and at the end."""

    def __init__(self, echo: Callable[[str], Any], summary_seconds: float) -> None:
        self.echo, self.summary_seconds = echo, summary_seconds
        self.states: dict[str, str] = {}
        self.last_summary = time.monotonic()

    def message(self, text: str) -> None:
        self.echo(text)

    def update(self, statuses: list[run_states.RunStatus], last: bool) -> None:
        for status in statuses:
            if self.states.get(status.name, "pending") == status.state:
                continue
            self.states[status.name] = status.state
            if status.state in ("running", "retrying"):
                self.echo(f"dqnlab: {status.name}: {status.state} on {status.node or '?'} "
                          f"(attempt {status.attempts}, step {status.step:,})")  # fmt: skip
        now = time.monotonic()
        if now - self.last_summary >= self.summary_seconds or last:
            self.last_summary = now
            self.echo("dqnlab: " + run_states.summary_line(statuses))


class _LiveTable:
    """A terminal's view of the sweep: `status.live_table` redrawn in place after each
    poll (about once a second), messages printed above it, where they stay in the
    scrollback."""

    def __init__(self, screen: Live) -> None:
        self.screen = screen

    def message(self, text: str) -> None:
        # A log's tail is plain text: brackets in it are not rich markup.
        self.screen.console.print(text, markup=False, highlight=False, emoji=False)

    def update(self, statuses: list[run_states.RunStatus], last: bool) -> None:
        self.screen.update(run_states.live_table(statuses), refresh=True)


def planned_record(run: PlannedRun) -> dict[str, Any]:
    """The run as sweep.json and `status.run_status` know it."""
    return {"name": run.name, "env": run.config.env, "seed": run.config.seed,
            "settings": run.settings, "total_steps": run.config.total_steps}  # fmt: skip


def _finish(run: PlannedRun, reference: Any, echo: Callable[[str], Any]) -> None:
    import ray

    try:
        result = ray.get(reference)
    except (ray.exceptions.RayError, DqnlabError) as error:
        run.status = "failed"
        cause = str(error).strip().splitlines()
        echo(f"dqnlab: {run.name}: FAILED ({cause[-1] if cause else type(error).__name__}); "
             f"see {run.log}" + _tail_text(run.log))  # fmt: skip
        return
    run.status, run.node = result["outcome"], result.get("host")
    run.seconds = result.get("seconds", 0.0)
    if run.status == "ok":
        echo(f"dqnlab: {run.name}: finished in {run.seconds:.0f} s on {run.node}")
    elif run.status == "done":
        echo(f"dqnlab: {run.name}: already finished, skipped")
    elif run.status == "stopped":
        echo(f"dqnlab: {run.name}: stopped after a checkpoint")
    else:
        echo(f"dqnlab: {run.name}: FAILED (exit {result.get('exit_status')}); see {run.log}"
             + _tail_text(run.log))  # fmt: skip


def _stop(pending: dict[Any, PlannedRun], echo: Callable[[str], Any]) -> None:
    """Ctrl-C: cancel every task (a running one asks its run to checkpoint and stop), and
    wait for the running ones to have done so."""
    import ray

    echo(f"dqnlab: stopping {len(pending)} runs (each writes a checkpoint first) ...")
    for reference in pending:
        ray.cancel(reference)
    deadline = time.monotonic() + STOP_WAIT_SECONDS
    remaining = list(pending)
    while remaining and time.monotonic() < deadline:
        _, remaining = ray.wait(remaining, num_returns=len(remaining), timeout=1.0)
    for run in pending.values():
        run.status = "stopped"


def _tail_text(path: Path | None, lines: int = 3) -> str:
    if path is None or not path.is_file():
        return ""
    text = path.read_text(errors="replace").strip().splitlines()
    return ("\n  " + "\n  ".join(text[-lines:])) if text else ""
