"""`dqnlab status`: a sweep's runs in each state, from the run directories alone; and the
same columns and overall bar in the live table `dqnlab sweep` draws with rich."""

from __future__ import annotations

import dataclasses
import io
import json
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import psutil
from rich.console import Console

from dqnlab.analysis.status import (
    COLUMNS,
    RunStatus,
    collect_status,
    estimate_seconds_left,
    format_status_table,
    live_table,
    record_attempt,
    run_status,
    status_json,
)
from dqnlab.config import resolve_config
from dqnlab.run import rundir
from dqnlab.run.lease import LeaseRecord, RunLease, boot_id
from dqnlab.run.rundir import lease_path
from dqnlab.sweeps.grid import parse_variation, plan_grid, write_sweep_file

EPISODES = "step,frames,episode,score,steps,epsilon,wall_seconds\n"
EVALUATIONS = "step,frames,mean\n"


def make_sweep(sweep_dir: Path):  # noqa: ANN201
    sweep = plan_grid(
        ["CartPole-v1"], [parse_variation("discount=0.9,0.99")], preset=None, overrides={},
        seeds=3, first_seed=0, steps=1000, sweep_dir=sweep_dir,
    )  # fmt: skip
    write_sweep_file(sweep)
    return sweep


def started(run_dir: Path, attempt: int, outcome: str | None, step: int = 0) -> None:
    run_dir.mkdir(parents=True, exist_ok=True)
    rundir.write_run_config(run_dir, resolve_config("classic", env="CartPole-v1", total_steps=1000))
    record_attempt(run_dir, {"event": "start", "attempt": attempt, "host": "node-a",
                             "pid": 1, "time": time.time() - 1000})  # fmt: skip
    if outcome:
        record_attempt(run_dir, {"event": "end", "attempt": attempt, "outcome": outcome})
    rows = "".join(
        f"{s},{4 * s},{s // 100},10,100,0.5,{s / 100}\n" for s in range(100, step + 1, 100)
    )
    rundir.episodes_path(run_dir).write_text(EPISODES + rows)
    rundir.evaluations_path(run_dir).write_text(
        EVALUATIONS + (f"{step},{4 * step},12.5\n" if step else "")
    )


def test_status_of_a_sweep_in_each_state(tmp_path: Path) -> None:
    sweep = make_sweep(tmp_path / "sweep")
    runs = [run.run_dir for run in sweep.runs]
    started(runs[0], 1, "done", 1000)
    started(runs[1], 1, None, 500)
    RunLease(runs[1]).acquire()  # a process holds it: running
    started(runs[2], 1, "killed", 300)
    started(runs[2], 2, None, 300)  # its process died without an end: Ray retries it
    started(runs[3], 1, "failed", 100)
    started(runs[4], 1, "stopped", 200)
    statuses = collect_status(sweep.directory)
    assert [s.state for s in statuses] == ["done", "running", "retrying", "failed", "stopped",
                                           "pending"]  # fmt: skip
    assert statuses[1].frames_per_second == 400  # 4 frames a step, 100 steps a second
    record = status_json(statuses)
    assert record["done"] == 1 and record["total"] == 6
    first = record["runs"][0]
    assert first == {"name": "CartPole-v1-discount=0.9-s0", "env": "CartPole-v1", "seed": 0,
                     "settings": {"discount": 0.9}, "state": "done", "step": 1000,
                     "total_steps": 1000, "last_eval_mean": 12.5, "attempts": 1}  # fmt: skip
    assert [r["attempts"] for r in record["runs"]] == [1, 1, 2, 1, 1, 0]


def test_the_time_left_counts_learning_speed_only_and_every_running_run(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    config = resolve_config("classic", env="CartPole-v1", total_steps=3000, replay_start_steps=400)
    rundir.write_run_config(run, config)
    # The replay start at 1,000 steps a second (no updates), then learning at 100.
    seconds = {step: step / 1000 for step in range(100, 401, 100)}
    seconds |= {step: 0.4 + (step - 400) / 100 for step in range(500, 1001, 100)}
    rows = "".join(f"{s},{4 * s},{s // 100},10,100,0.5,{t}\n" for s, t in seconds.items())
    rundir.episodes_path(run).write_text(EPISODES + rows)
    RunLease(run).acquire()
    status = run_status(run)
    assert status.state == "running" and status.steps_per_second == 100
    # A second run, just started: no speed yet, but it runs beside the first, at its pace.
    starting = dataclasses.replace(status, name="other", step=0, steps_per_second=None)
    assert estimate_seconds_left([status, starting]) == (2000 + 3000) / (2 * 100)


def test_a_run_whose_process_lives_but_renews_no_lease_is_paused_not_retrying(
    tmp_path: Path,
) -> None:
    """A training stopped with SIGSTOP (to time something beside it) keeps its process but
    lets its lease expire: `paused`, not `retrying` (its process may still carry on);
    once the process is gone, Ray's retry is what comes."""
    sweep = make_sweep(tmp_path / "sweep")
    run = sweep.runs[0].run_dir
    started(run, 1, None, 300)
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        expired = LeaseRecord(
            "token", socket.gethostname(), sleeper.pid, time.time() - 3600, False, boot_id(),
            psutil.Process(sleeper.pid).create_time(),
        )  # fmt: skip
        lease_path(run).write_text(json.dumps(dataclasses.asdict(expired)))
        assert collect_status(sweep.directory)[0].state == "paused"
    finally:
        sleeper.kill()
        sleeper.wait()
    assert collect_status(sweep.directory)[0].state == "retrying"


def test_the_status_command_on_a_sweep_and_on_one_run(tmp_path: Path) -> None:
    sweep = make_sweep(tmp_path / "sweep")
    started(sweep.runs[0].run_dir, 1, "done", 1000)
    out = tmp_path / "status.json"
    result = subprocess.run(
        [sys.executable, "-m", "dqnlab", "status", str(sweep.directory), "--json", str(out)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    assert "5 pending, 1 done" in result.stdout
    assert json.loads(out.read_text())["done"] == 1
    one = collect_status(sweep.runs[0].run_dir)
    assert [s.state for s in one] == ["done"]


def test_an_atari_run_under_way_gets_its_on_track_verdict(tmp_path: Path) -> None:
    run_dir = tmp_path / "pong"
    run_dir.mkdir()
    rundir.write_run_config(run_dir, resolve_config("nature", env="pong", total_steps=10**7))
    # Dopamine's pong runs score -20.6 to -20.2 in the first 1M frames: -15 is above them.
    rows = "".join(f"{s},{4 * s},{n},-15,{s},1.0,{s / 300}\n" for n, s in enumerate((900, 1800), 1))
    rundir.episodes_path(run_dir).write_text(EPISODES + rows)
    (status,) = collect_status(run_dir)
    assert status.on_track is not None and status.on_track.verdict == "above the range"
    assert status.on_track.games == 2 and status.on_track.score == -15.0
    record = status_json([status])["runs"][0]
    assert record["on_track"]["verdict"] == "above the range"
    assert record["on_track"]["window_start_frames"] == 0
    lines = format_status_table([status])
    assert "above the range" in lines[-1] and "Dopamine DQN" in lines[-1]  # the run's agent
    assert "on track?" in lines[-2] and record["on_track"]["reference"] == "dqn"


def test_each_variant_run_under_way_is_set_beside_its_own_agents_curve(tmp_path: Path) -> None:
    rows = "".join(f"{s},{4 * s},{n},-15,{s},1.0,{s / 300}\n" for n, s in enumerate((900, 1800), 1))
    for preset in ("c51", "double"):
        run_dir = tmp_path / preset
        run_dir.mkdir()
        rundir.write_run_config(run_dir, resolve_config(preset, env="pong", total_steps=10**7))
        rundir.episodes_path(run_dir).write_text(EPISODES + rows)
    c51, double = collect_status(tmp_path)
    assert c51.on_track is not None and c51.on_track.reference == "c51"
    assert c51.on_track.verdict is not None
    records = {record["name"]: record["on_track"] for record in status_json([c51, double])["runs"]}
    assert records["c51"]["reference"] == "c51" and records["c51"]["why_none"] is None
    assert records["double"]["reference"] is None and records["double"]["verdict"] is None
    why = "Dopamine publishes no curve for DQN + double Q-learning"
    assert records["double"]["why_none"] == why
    lines = format_status_table([c51, double])
    assert "Dopamine C51" in lines[-2] and lines[-1].endswith(why)


# The live table of `dqnlab sweep` and the table of `dqnlab status` -----------------------


def one_in_each_state() -> list[RunStatus]:
    def run(state: str, step: int, **figures: Any) -> RunStatus:
        return RunStatus(f"CartPole-v1-{state}-s0", "CartPole-v1", 0, {}, state, step, 3000,
                         **figures)  # fmt: skip

    return [
        run("done", 3000, last_eval_mean=12.5, attempts=1, node="node-a"),
        run("running", 1500, last_eval_mean=9.25, attempts=2, node="node-b",
            frames_per_second=400.0, steps_per_second=100.0),
        run("retrying", 300, attempts=2, node="node-c"),
        run("failed", 100, attempts=1, node="node-a"),
        run("stopped", 200, attempts=1, node="node-a"),
        run("pending", 0),
    ]  # fmt: skip


def rendered(renderable: Any) -> str:
    console = Console(file=io.StringIO(), width=180, color_system=None)
    console.print(renderable)
    return console.file.getvalue()  # type: ignore[attr-defined]


def test_the_live_table_shows_each_runs_figures_and_the_overall_bar() -> None:
    statuses = one_in_each_state()
    text = rendered(live_table(statuses))
    lines = text.splitlines()
    header = next(line for line in lines if "frames/s" in line)
    assert header.split() == ["run", "node", "state", "step", "frames/s", "last", "eval",
                              "attempts"]  # fmt: skip
    running = next(line for line in lines if "CartPole-v1-running-s0" in line)
    assert running.split()[1:] == ["node-b", "running", "1,500", "/", "3,000", "400", "9.25", "2"]
    failed = next(line for line in lines if "CartPole-v1-failed-s0" in line)
    assert failed.split()[1:] == ["node-a", "failed", "100", "/", "3,000", "-", "-", "1"]
    # 5,100 of 18,000 steps; 10,000 left (not done or failed) at the running run's 100/s.
    bar = lines[0]
    assert "28% of 18,000 steps, 1/6 runs done" in bar and "about 100 s left" in bar
    assert "1 pending, 1 running, 1 retrying, 1 stopped, 1 done, 1 failed" in bar


def test_dqnlab_status_prints_the_same_cells_and_bar_as_the_live_table() -> None:
    statuses = one_in_each_state()
    plain = format_status_table(statuses)
    live = rendered(live_table(statuses)).splitlines()
    for status in statuses:
        cells = [column.cell(status) for column in COLUMNS]
        plain_row = next(line for line in plain if line.startswith(status.name + " "))
        live_row = next(line for line in live if status.name in line)
        assert plain_row.split() == live_row.split() == " ".join(cells).split()
    assert plain[-1].startswith("[#####...............] 28% of 18,000 steps, 1/6 runs done")
    assert plain[-1].split("] ", 1)[1] in live[0]
