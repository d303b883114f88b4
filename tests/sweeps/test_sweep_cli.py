"""`dqnlab sweep` as a user runs it (slow: each command starts or joins a Ray).

The default `--address local` on loopback only, stopped with Ctrl-C and carried on by the
same command; `--address auto` and `ray://` joining a running loopback cluster.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psutil
import pytest

from dqnlab.analysis.status import read_attempts, run_status
from dqnlab.run.lease import lease_is_live
from dqnlab.sweeps.cluster import start_loopback_cluster
from dqnlab.sweeps.grid import Sweep, parse_variation, plan_grid, planned_record
from tests.run.test_resume import assert_same_run
from tests.sweeps.ray_helpers import non_loopback_sockets, ray_processes

pytestmark = pytest.mark.slow

SETTINGS = {
    "replay_start_steps": 200, "replay_capacity": 2000, "eval_period_steps": 500,
    "eval_steps": 200, "checkpoint_period_steps": 100, "final_eval_episodes": 2,
}  # fmt: skip
STEPS = 1500
STOPPED_EXIT_STATUS = 130


def sweep_command(sweep_dir: Path, *options: str, vary: str = "discount=0.9,0.99") -> list[str]:
    return [
        sys.executable, "-m", "dqnlab", "sweep", "--env", "CartPole-v1", "--vary", vary,
        "--steps", str(STEPS), "--sweep-dir", str(sweep_dir), "--cpus-per-run", "1",
        "--memory-per-run", "1", "--no-report",
        *[f"--set={key}={value}" for key, value in SETTINGS.items()], *options,
    ]  # fmt: skip


def plan(sweep_dir: Path, vary: str = "discount=0.9,0.99") -> Sweep:
    return plan_grid(
        ["CartPole-v1"], [parse_variation(vary)], preset=None, overrides=SETTINGS, seeds=1,
        first_seed=0, steps=STEPS, sweep_dir=sweep_dir,
    )  # fmt: skip


def start_driver(command: list[str], log: Path, env: dict[str, str] | None = None) -> Any:
    """`dqnlab sweep` as a terminal starts it: its own process group, SIGINT not ignored
    (a shell's background job would ignore it, and Python would keep that)."""

    def as_foreground_job() -> None:
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    return subprocess.Popen(
        command, stdout=log.open("w"), stderr=subprocess.STDOUT, env=env,
        start_new_session=True, preexec_fn=as_foreground_job,
    )  # fmt: skip


def wait_until_training(sweep: Sweep, driver: Any, log: Path, step: int, runs: int) -> None:
    """Until `runs` of the sweep's runs train past `step`; the loopback rule checked on the
    driver's processes and Ray's meanwhile, while the runs train."""
    checked = False
    while driver.poll() is None:
        states = [run_status(run.run_dir, planned_record(run)) for run in sweep.runs]
        busy = [s for s in states if s.state == "running" and s.step >= step]
        if not checked and busy:
            assert ray_processes(driver.pid) and non_loopback_sockets(driver.pid) == []
            checked = True
        if len(busy) >= runs:
            return
        time.sleep(0.2)
    raise AssertionError(f"the sweep ended early ({driver.returncode}):\n{log.read_text()}")


def test_ctrl_c_of_a_local_sweep_stops_its_runs_at_a_checkpoint_and_the_command_carries_on(
    tmp_path: Path,
    trained_alone,  # noqa: ANN001
) -> None:
    sweep_dir, log = tmp_path / "sweep", tmp_path / "driver.log"
    command = sweep_command(sweep_dir)  # --address local, the default
    driver = start_driver(command, log)
    sweep = plan(sweep_dir)
    wait_until_training(sweep, driver, log, step=300, runs=2)
    processes = [psutil.Process(driver.pid), *psutil.Process(driver.pid).children(recursive=True)]
    os.killpg(driver.pid, signal.SIGINT)  # Ctrl-C: the terminal signals the whole group
    assert driver.wait(timeout=300) == STOPPED_EXIT_STATUS, log.read_text()
    output = log.read_text()
    assert "Run the same command again to carry on" in output, output
    _, alive = psutil.wait_procs(processes, timeout=30)
    assert alive == [], [process.info for process in alive]  # the local Ray stopped too
    for run in sweep.runs:
        status = run_status(run.run_dir, planned_record(run))
        assert status.state == "stopped" and 300 <= status.step < STEPS, status
        assert not lease_is_live(run.run_dir)
        ends = [e for e in read_attempts(run.run_dir) if e["event"] == "end"]
        assert [e["outcome"] for e in ends] == ["stopped"]

    again = subprocess.run(command, capture_output=True, text=True, timeout=900)
    assert again.returncode == 0, again.stdout + again.stderr
    for run in sweep.runs:
        assert run_status(run.run_dir, planned_record(run)).state == "done"
        config_path = sweep_dir / "logs" / f"{run.name}.toml"
        assert_same_run(trained_alone(config_path, "CartPole-v1"), run.run_dir)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@pytest.fixture(scope="module")
def running_cluster() -> Iterator[tuple[Any, int, dict[str, str]]]:
    """A loopback cluster started as `ray start` would leave one (its address written under
    Ray's temporary directory, here a fresh one), with a Ray Client server; the
    environment the drivers run in."""
    temporary = tempfile.mkdtemp(prefix="ray", dir="/tmp")  # short: Ray's socket paths
    environment = {key: value for key, value in os.environ.items() if key != "RAY_ADDRESS"}
    environment["RAY_TMPDIR"] = temporary
    client_port = free_port()
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("RAY_TMPDIR", temporary)
        patch.delenv("RAY_ADDRESS", raising=False)
        cluster = start_loopback_cluster(2, ray_client_server_port=client_port)
    try:
        yield cluster, client_port, environment
    finally:
        cluster.shutdown()
        shutil.rmtree(temporary, ignore_errors=True)


def test_auto_joins_the_running_loopback_cluster_and_reports_despite_a_failed_run(
    tmp_path: Path,
    running_cluster,  # noqa: ANN001
) -> None:
    """`--address auto` finds the cluster `ray start` would have left; one run of two fails
    (its directory holds something else); the other trains, the sweep reports it into
    SWEEP/report and then names the failed run with its log's tail, exit status 2."""
    cluster, _, environment = running_cluster
    sweep_dir, log = tmp_path / "sweep", tmp_path / "driver.log"
    sweep = plan(sweep_dir)
    blocked = sweep.runs[1].run_dir
    blocked.mkdir(parents=True)
    (blocked / "notes.txt").write_text("not a run")
    command = [
        part for part in sweep_command(sweep_dir, "--address", "auto") if part != "--no-report"
    ]
    driver = start_driver(command, log, environment)
    wait_until_training(sweep, driver, log, step=100, runs=1)
    assert driver.wait(timeout=600) == 2, log.read_text()
    output = log.read_text()
    assert f"{sweep.runs[1].name}: FAILED" in output and "already exists and is not empty" in output
    assert f"1 of 2 runs failed: {sweep.runs[1].name}; run the same command again" in output
    trained = sweep.runs[0]
    assert run_status(trained.run_dir, planned_record(trained)).state == "done"
    starts = [e for e in read_attempts(trained.run_dir) if e["event"] == "start"]
    assert [e["node_id"] for e in starts] == [cluster.head_node.node_id]  # not a Ray of its own
    results = (sweep_dir / "report" / "results.md").read_text()
    assert trained.name in results and sweep.runs[1].name not in results
    assert (blocked / "notes.txt").read_text() == "not a run"  # untouched


def test_ray_client_address_joins_the_running_loopback_cluster(
    tmp_path: Path,
    running_cluster,  # noqa: ANN001
) -> None:
    cluster, client_port, environment = running_cluster
    address = f"ray://127.0.0.1:{client_port}"
    sweep_dir, log = tmp_path / "sweep", tmp_path / "driver.log"
    driver = start_driver(
        sweep_command(sweep_dir, "--address", address, vary="discount=0.9"), log, environment
    )
    sweep = plan(sweep_dir, vary="discount=0.9")
    wait_until_training(sweep, driver, log, step=100, runs=1)
    assert driver.wait(timeout=600) == 0, log.read_text()
    (run,) = sweep.runs
    assert run_status(run.run_dir, planned_record(run)).state == "done"
    starts = [e for e in read_attempts(run.run_dir) if e["event"] == "start"]
    assert [e["node_id"] for e in starts] == [cluster.head_node.node_id]
