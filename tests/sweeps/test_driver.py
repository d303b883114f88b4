"""The sweep's driver following its runs: the live table redrawn in a terminal, a line per
change into a log (a fake `ray`: no cluster)."""

from __future__ import annotations

import io
import sys
import time
import types
from pathlib import Path
from typing import Any

import pytest
from rich.console import Console
from rich.live import Live

from dqnlab.analysis.status import record_attempt
from dqnlab.config import resolve_config
from dqnlab.run import rundir
from dqnlab.sweeps.driver import _follow, _LiveTable, _StateLines
from dqnlab.sweeps.grid import PlannedRun, Sweep, parse_variation, plan_grid


@pytest.fixture
def fake_ray(monkeypatch: pytest.MonkeyPatch) -> types.SimpleNamespace:
    """A `ray` whose first wait returns nothing and the second every task: one succeeded
    on node-a, the other raised."""

    class RayError(Exception):
        pass

    polls = iter([False, True])

    def wait(references: list[str], **_: Any) -> tuple[list[str], list[str]]:
        return (references, []) if next(polls) else ([], references)

    def get(reference: str) -> dict[str, Any]:
        if reference == "fails":
            raise RayError("the task's worker died\nnode lost")
        return {"outcome": "ok", "host": "node-a", "seconds": 3.0}

    ray = types.SimpleNamespace(wait=wait, get=get, exceptions=types.SimpleNamespace(
        RayError=RayError))  # fmt: skip
    monkeypatch.setitem(sys.modules, "ray", ray)
    return ray


def two_runs(tmp_path: Path) -> tuple[Sweep, dict[Any, PlannedRun]]:
    """Two tasks under way, the first run's attempt started (running) on node-a."""
    sweep = plan_grid(["CartPole-v1"], [parse_variation("discount=0.9,0.99")], preset=None,
                      overrides={}, seeds=1, first_seed=0, steps=1000,
                      sweep_dir=tmp_path)  # fmt: skip
    first = sweep.runs[0].run_dir
    first.mkdir()
    rundir.write_run_config(first, resolve_config("classic", env="CartPole-v1", total_steps=1000))
    record_attempt(first, {"event": "start", "attempt": 1, "host": "node-a", "pid": 1,
                           "time": time.time()})  # fmt: skip
    return sweep, {"succeeds": sweep.runs[0], "fails": sweep.runs[1]}


def test_the_driver_in_live_mode_redraws_the_table_and_prints_outcomes_above_it(
    tmp_path: Path, fake_ray: types.SimpleNamespace
) -> None:
    sweep, pending = two_runs(tmp_path)
    console = Console(file=io.StringIO(), width=140, force_terminal=True, color_system=None)
    with Live(console=console, auto_refresh=False) as screen:
        _follow(sweep, pending, _LiveTable(screen), poll_seconds=0.0)
    text = console.file.getvalue()  # type: ignore[attr-defined]
    assert "CartPole-v1-discount=0.9-s0: finished in 3 s on node-a" in text
    assert "CartPole-v1-discount=0.99-s0: FAILED (node lost)" in text
    assert "running" in text  # the first poll's table
    assert "50% of 2,000 steps, 1/2 runs done; 1 done, 1 failed" in text  # the last one
    assert [run.status for run in sweep.runs] == ["ok", "failed"]


def test_the_driver_into_a_log_prints_a_line_per_change_and_the_overall_line(
    tmp_path: Path, fake_ray: types.SimpleNamespace
) -> None:
    sweep, pending = two_runs(tmp_path)
    lines: list[str] = []
    _follow(sweep, pending, _StateLines(lines.append, 30.0), poll_seconds=0.0)
    assert lines[0] == "dqnlab: CartPole-v1-discount=0.9-s0: running on node-a (attempt 1, step 0)"
    assert lines[1] == "dqnlab: CartPole-v1-discount=0.9-s0: finished in 3 s on node-a"
    assert lines[2].startswith("dqnlab: CartPole-v1-discount=0.99-s0: FAILED (node lost)")
    assert lines[3:] == ["dqnlab: [##########..........] 50% of 2,000 steps, 1/2 runs done; "
                         "1 done, 1 failed"]  # fmt: skip
