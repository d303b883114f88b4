"""The driver of a sweep: the grid's runs (`grid.py`), each `dqnlab train` in its own run
directory (`worker.py`), submitted as Ray tasks on this machine or a cluster, followed, and
stopped on Ctrl-C. `dqnlab sweep` and `dqnlab ablate` both run here: there is one
scheduling code path, Ray's.

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

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from rich.live import Live

from dqnlab.analysis import status as run_states
from dqnlab.config import config_to_toml
from dqnlab.errors import DqnlabError
from dqnlab.run import rundir
from dqnlab.sweeps.grid import PlannedRun, Sweep, planned_record, write_sweep_file
from dqnlab.sweeps.resources import RunResources
from dqnlab.sweeps.worker import (
    STOP_WAIT_SECONDS,
    WORKER_ENVIRONMENT,
    RunProcessKilled,
    train_attempt,
    trained_to_budget,
)

DEFAULT_MAX_RETRIES = 3
SUMMARY_SECONDS = 30.0  # the live table's overall line, at least this often
# Every run's state is read from its files (its episodes.csv, its last network) at most this
# often, and whenever a task returns: read every second, a 26-game sweep's driver took 10%
# of a core from the runs it drives (2026-12-04, 2 cores).
STATUS_SECONDS = 5.0


def finished(run: PlannedRun) -> bool:
    """Whether the run is trained to its budget with exactly this configuration."""
    if not rundir.is_run_dir(run.run_dir) or rundir.load_run_config(run.run_dir) != run.config:
        return False
    return trained_to_budget(run.run_dir, run.config.total_steps)


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
    status_seconds: float = STATUS_SECONDS,
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
                _follow(sweep, pending, _LiveTable(screen), poll_seconds, status_seconds)
        else:
            display = _StateLines(echo, summary_seconds)
            _follow(sweep, pending, display, poll_seconds, status_seconds)
    except KeyboardInterrupt:
        _stop(pending, echo)  # the live table has left the terminal: plain lines
        raise
    return sweep


class _Display(Protocol):
    def message(self, text: str) -> None: ...

    def update(self, statuses: list[run_states.RunStatus], last: bool) -> None: ...


def _follow(
    sweep: Sweep,
    pending: dict[Any, PlannedRun],
    display: _Display,
    poll_seconds: float,
    status_seconds: float = 0.0,
) -> None:
    """Until every task has returned: each returned task's outcome as a message, and every
    run's state (from its files) to the display after the first poll, after a poll where
    a task returned, and otherwise at most every `status_seconds`."""
    import ray

    shown = -math.inf
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=poll_seconds)
        for reference in ready:
            _finish(pending.pop(reference), reference, display.message)
        now = time.monotonic()
        if ready or not pending or now - shown >= status_seconds:
            display.update([_polled_status(run) for run in sweep.runs], last=not pending)
            shown = now


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
            if status.state in ("running", "paused", "retrying"):
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
