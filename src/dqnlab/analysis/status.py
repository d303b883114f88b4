"""Where a sweep's runs stand, read from their run directories alone (no Ray), so that
`dqnlab status` works from any machine that sees the storage, and the sweep's live table
shows the same: both draw the columns of `COLUMNS` and the overall bar of `sweep_progress`.

A run's state:
    pending    nothing trained yet (no attempt started)
    running    a process holds the run's lease (`lease.RunLease`)
    paused     its process still exists on this machine but no longer renews the lease
               (stopped with SIGSTOP, or hung); once the lease has expired, an attempt
               that starts anyway takes it over, and the paused process stops at its
               next checkpoint (LeaseLost)
    retrying   an attempt ended without finishing (killed, node lost) and the run is
               not held: Ray starts it again
    stopped    stopped by a request (Ctrl-C) after a checkpoint: the same command carries on
    done       trained to its budget
    failed     an attempt failed for a reason retrying does not cure (its log says which)
"""

from __future__ import annotations

import csv
import io
import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from rich import box
from rich.console import Group, RenderableType
from rich.progress_bar import ProgressBar
from rich.table import Table
from rich.text import Text

from dqnlab.analysis.report.reference import (
    AGENTS,
    REFERENCE_PROTOCOL,
    WINDOW_FRAMES,
    OnTrackRow,
    ReferenceMatch,
    load_references,
    on_track_row,
    reference_agent,
    reference_curve,
)
from dqnlab.envs import is_atari
from dqnlab.errors import DqnlabError
from dqnlab.run import rundir
from dqnlab.run.lease import LEASE_SECONDS, TAKEOVER_GRACE_SECONDS, lease_is_live, read_lease

STATES = ("pending", "running", "paused", "retrying", "stopped", "done", "failed")
TAIL_BYTES = 8192  # enough of a CSV's end for its last rows
# An attempt that started this recently and holds no lease yet is starting up, not lost.
STARTING_SECONDS = LEASE_SECONDS + TAKEOVER_GRACE_SECONDS
RATE_ROWS = 10  # frames/s over the last rows of episodes.csv
NODE_WIDTH = 14  # a node's name in the table, cut to this
TEXT_BAR_WIDTH, BAR_WIDTH = 20, 30  # the overall bar's characters: as text, live
STATE_STYLES = {
    "paused": "yellow", "retrying": "yellow", "stopped": "yellow", "done": "dim",
    "failed": "bold red",
}  # fmt: skip


@dataclass
class RunStatus:
    name: str
    env: str
    seed: int
    settings: dict[str, Any]
    state: str
    step: int
    total_steps: int
    last_eval_mean: float | None = None
    attempts: int = 0
    frames_per_second: float | None = None  # of a running run
    steps_per_second: float | None = None  # of a running run once it learns (the time left)
    node: str | None = None  # host of the latest attempt
    started_at: float | None = None  # wall-clock start of the latest attempt
    log_tail: str = field(default="", repr=False)
    on_track: OnTrackRow | None = field(default=None, repr=False)  # Atari runs under way

    def json_fields(self) -> dict[str, Any]:
        keys = ("name", "env", "seed", "settings", "state", "step", "total_steps")
        record = {key: asdict(self)[key] for key in keys}
        record["last_eval_mean"] = self.last_eval_mean
        record["attempts"] = self.attempts
        row = self.on_track
        if row is not None:
            record["on_track"] = {
                "window_start_frames": None if row.window is None else row.window * WINDOW_FRAMES,
                "games": row.games,
                "score": row.score,
                "reference_mean": row.reference_mean,
                "reference_low": row.reference_low,
                "reference_high": row.reference_high,
                "verdict": row.verdict,
                "reference": row.reference,  # the agent compared with, a key of AGENTS
                "why_none": row.why_none,
            }
        return record


def read_attempts(run_dir: Path) -> list[dict[str, Any]]:
    """The run's attempt events (one JSON object a line), oldest first."""
    path = rundir.attempts_path(run_dir)
    if not path.is_file():
        return []
    events = []
    for line in path.read_text().splitlines():
        try:
            events.append(json.loads(line))
        except json.JSONDecodeError:
            continue  # a line cut by a crash
    return events


def record_attempt(run_dir: Path, event: dict[str, Any]) -> None:
    """Append one event to the run's attempts file (a line written in one call)."""
    with rundir.attempts_path(run_dir).open("a") as handle:
        handle.write(json.dumps(event) + "\n")


def _tail_rows(path: Path) -> list[dict[str, str]]:
    if not path.is_file():
        return []
    with path.open("rb") as handle:
        header = handle.readline().decode(errors="replace")
        size = handle.seek(0, io.SEEK_END)
        handle.seek(max(len(header), size - TAIL_BYTES))
        tail = handle.read().decode(errors="replace")
    lines = tail.splitlines()
    if size - TAIL_BYTES > len(header):
        lines = lines[1:]  # the first line read may be cut
    rows = list(csv.DictReader([header, *lines]))
    return [row for row in rows if None not in row.values()]


def _number(text: str | None) -> float | None:
    try:
        value = float(text) if text not in (None, "") else None
    except ValueError:
        return None
    return value if value is None or math.isfinite(value) else None


def run_status(run_dir: Path, planned: dict[str, Any] | None = None) -> RunStatus:
    """The state of one run, from its files; `planned` (a run of sweep.json) fills in a
    run that has not started."""
    planned = planned or {}
    learning_from = 0  # the step learning starts at: the replay start plays much faster
    if rundir.is_run_dir(run_dir):
        config = rundir.load_run_config(run_dir)
        env, seed, total = config.env, config.seed, config.total_steps
        learning_from = config.replay_start_steps
    else:
        env, seed, total = planned["env"], planned["seed"], planned["total_steps"]
    status = RunStatus(
        planned.get("name", run_dir.name), env, seed, planned.get("settings", {}),
        "pending", 0, total,
    )  # fmt: skip
    if not run_dir.is_dir():
        return status
    episodes = _tail_rows(rundir.episodes_path(run_dir))
    evaluations = _tail_rows(rundir.evaluations_path(run_dir))
    if episodes:
        status.step = int(_number(episodes[-1].get("step")) or 0)
    if evaluations:
        status.last_eval_mean = _number(evaluations[-1].get("mean"))
        status.step = max(status.step, int(_number(evaluations[-1].get("step")) or 0))
    events = read_attempts(run_dir)
    starts = [event for event in events if event.get("event") == "start"]
    ends = [event for event in events if event.get("event") == "end"]
    status.attempts = len(starts)
    if starts:
        status.node, status.started_at = starts[-1].get("host"), starts[-1].get("time")
    last_end = None  # the end of the latest attempt, if it ended
    if ends and (not starts or ends[-1]["attempt"] >= starts[-1]["attempt"]):
        last_end = ends[-1]
    if lease_is_live(run_dir):
        status.state = "running"
        status.frames_per_second = _rate(episodes, "frames")
        learning = [row for row in episodes if (_number(row.get("step")) or 0) >= learning_from]
        status.steps_per_second = _rate(learning, "step")
    elif last_end is not None and last_end.get("outcome") in ("done", "failed", "stopped"):
        status.state = last_end["outcome"]
    elif rundir.trained_to_budget(run_dir, total):
        status.state = "done"
    elif starts and last_end is None and time.time() - (status.started_at or 0) < STARTING_SECONDS:
        status.state = "running"  # started, not holding its lease yet
    elif (
        (lease := read_lease(run_dir))
        and not lease.released
        and lease.owner_alive_on_this_machine()
    ):
        status.state = "paused"
    elif starts or status.step > 0:
        status.state = "retrying" if starts else "stopped"
    if status.state == "done":
        status.step = total
    return status


def _rate(rows: list[dict[str, str]], column: str) -> float | None:
    """Training `column` (frames, step) per second over the last rows of this session
    (wall_seconds restarts at a resume, so a window that spans one is not used)."""
    if len(rows) < 2:
        return None
    first, last = rows[max(0, len(rows) - RATE_ROWS)], rows[-1]
    seconds = (_number(last.get("wall_seconds")) or 0) - (_number(first.get("wall_seconds")) or 0)
    amount = (_number(last.get(column)) or 0) - (_number(first.get(column)) or 0)
    return amount / seconds if seconds > 0 and amount > 0 else None


def load_sweep_file(sweep_dir: Path) -> dict[str, Any] | None:
    return rundir.read_json_file(rundir.sweep_file_path(sweep_dir))


def collect_status(path: Path) -> list[RunStatus]:
    """Every run of a sweep directory (the grid of its sweep.json, else its run
    directories), or the one run of a run directory, with the on-track verdict of each
    Atari run that has started, against its own agent's curve (`report.reference`)."""
    statuses = _collect_status(path)
    run_dirs = {status.name: path if rundir.is_run_dir(path) else path / status.name
                for status in statuses}  # fmt: skip
    configs = {name: rundir.load_run_config(run_dir)
               for name, run_dir in run_dirs.items() if rundir.is_run_dir(run_dir)}  # fmt: skip
    references = load_references(configs.values())
    for status in statuses:
        if is_atari(status.env) and status.state != "pending":
            config = configs.get(status.name)
            # An attempt starts before the run writes its config: it has trained nothing.
            match = ReferenceMatch(None, "no training game has ended yet")
            if config is not None:
                match = reference_agent(config)
            status.on_track = on_track_row(
                run_dirs[status.name],
                status.env,
                "",
                match,
                None if config is None else reference_curve(references, config),
                steps=status.step,
                finished=status.state == "done",
                last_eval_mean=status.last_eval_mean,
            )
    return statuses


def _collect_status(path: Path) -> list[RunStatus]:
    if rundir.is_run_dir(path):
        return [run_status(path)]
    if not path.is_dir():
        raise DqnlabError(f"{path} is neither a run directory nor a sweep directory")
    sweep = load_sweep_file(path)
    if sweep is not None:
        return [run_status(path / run["name"], run) for run in sweep["runs"]]
    runs = sorted(child for child in path.iterdir() if rundir.is_run_dir(child))
    if not runs:
        raise DqnlabError(f"{path} holds no runs (no sweep.json, no run directories)")
    return [run_status(child) for child in runs]


def status_json(statuses: list[RunStatus]) -> dict[str, Any]:
    return {
        "runs": [status.json_fields() for status in statuses],
        "done": sum(status.state == "done" for status in statuses),
        "total": len(statuses),
    }


@dataclass(frozen=True)
class Column:
    """A column of the status table, the same in `dqnlab status` and the sweep's live
    table: its header, its alignment and the text of a run's cell."""

    header: str
    justify: Literal["left", "right"]
    cell: Callable[[RunStatus], str]


def _frames_per_second_text(status: RunStatus) -> str:
    return f"{status.frames_per_second:.0f}" if status.frames_per_second else "-"


def _evaluation_text(status: RunStatus) -> str:
    return "-" if status.last_eval_mean is None else f"{status.last_eval_mean:.2f}"


COLUMNS = (
    Column("run", "left", lambda status: status.name),
    Column("node", "left", lambda status: (status.node or "-")[:NODE_WIDTH]),
    Column("state", "left", lambda status: status.state),
    Column("step", "right", lambda status: f"{status.step:,} / {status.total_steps:,}"),
    Column("frames/s", "right", _frames_per_second_text),
    Column("last eval", "right", _evaluation_text),
    Column("attempts", "right", lambda status: str(status.attempts)),
)


def format_status_table(statuses: list[RunStatus]) -> list[str]:
    """One line per run (`COLUMNS`), then the overall line, then the on-track verdicts."""
    rows = [[column.header for column in COLUMNS]]
    rows += [[column.cell(status) for column in COLUMNS] for status in statuses]
    widths = [max(len(row[index]) for row in rows) for index in range(len(COLUMNS))]
    lines = [
        "  ".join(text.ljust(width) if column.justify == "left" else text.rjust(width)
                  for column, text, width in zip(COLUMNS, row, widths, strict=True)).rstrip()
        for row in rows
    ]  # fmt: skip
    lines.append(summary_line(statuses))
    on_track = [(status.name, status.on_track) for status in statuses if status.on_track]
    if on_track:
        lines.append(
            "on track? the latest 1M-frame window of training games against Dopamine's "
            f"curve of each run's agent; its {REFERENCE_PROTOCOL}:"
        )
        for name, row in on_track:
            lines.append(f"{name:{widths[0]}s}  {_on_track_text(row)}")
    return lines


def _on_track_text(row: OnTrackRow) -> str:
    if row.window is None or row.score is None:
        return row.why_none or "-"
    text = f"{row.window}-{row.window + 1}M frames: {row.score:.1f} over {row.games} games"
    if row.verdict is None:
        return f"{text}; {row.why_none}"
    name = AGENTS[row.reference].name if row.reference is not None else "reference"
    return (f"{text}; {name} {row.reference_mean:.1f} ({row.reference_low:.1f} to "
            f"{row.reference_high:.1f}): {row.verdict}")  # fmt: skip


def live_table(statuses: list[RunStatus]) -> RenderableType:
    """The sweep's live table (rich): the overall bar on top, where a grid taller than the
    terminal does not cut it off, then a row per run (`COLUMNS`)."""
    progress = sweep_progress(statuses)
    bar = Table.grid(padding=(0, 1))
    bar.add_row(
        ProgressBar(total=progress.all_steps, completed=progress.done_steps, width=BAR_WIDTH),
        Text(summary_text(progress)),
    )
    table = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False)
    for column in COLUMNS:
        table.add_column(column.header, justify=column.justify, no_wrap=True)
    for status in statuses:
        table.add_row(*(Text(column.cell(status)) for column in COLUMNS),
                      style=STATE_STYLES.get(status.state))  # fmt: skip
    return Group(bar, table)


@dataclass(frozen=True)
class SweepProgress:
    """The overall bar's figures."""

    done_steps: int
    all_steps: int
    runs_done: int
    runs: int
    counts: dict[str, int]  # runs in each state
    seconds_left: float | None


def sweep_progress(statuses: list[RunStatus]) -> SweepProgress:
    counts = {state: sum(status.state == state for status in statuses) for state in STATES}
    return SweepProgress(
        done_steps=sum(status.step for status in statuses),
        all_steps=sum(status.total_steps for status in statuses) or 1,
        runs_done=counts["done"],
        runs=len(statuses),
        counts=counts,
        seconds_left=estimate_seconds_left(statuses),
    )


def estimate_seconds_left(statuses: list[RunStatus]) -> float | None:
    """Steps left over the sweep's steps per second: as many runs as are running now, each
    at the mean learning speed of those that have one (`steps_per_second`, measured once
    learning runs: a run still in its replay start or its first games has none yet)."""
    running = [s for s in statuses if s.state == "running"]
    rates = [s.steps_per_second for s in running if s.steps_per_second]
    if not rates:
        return None
    left = sum(s.total_steps - s.step for s in statuses if s.state not in ("done", "failed"))
    return left / (sum(rates) / len(rates) * len(running))


def summary_text(progress: SweepProgress) -> str:
    """The overall bar's words: steps done of all, runs done, runs by state, time left."""
    percent = 100 * progress.done_steps / progress.all_steps
    parts = [f"{count} {state}" for state, count in progress.counts.items() if count]
    text = (f"{percent:.0f}% of {progress.all_steps:,} steps, {progress.runs_done}/"
            f"{progress.runs} runs done; " + ", ".join(parts))  # fmt: skip
    if progress.seconds_left is not None:
        text += f"; about {_duration(progress.seconds_left)} left"
    return text


def summary_line(statuses: list[RunStatus]) -> str:
    """The overall bar as text: [####......] and `summary_text`."""
    progress = sweep_progress(statuses)
    filled = int(TEXT_BAR_WIDTH * progress.done_steps / progress.all_steps)
    return f"[{'#' * filled}{'.' * (TEXT_BAR_WIDTH - filled)}] {summary_text(progress)}"


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"
