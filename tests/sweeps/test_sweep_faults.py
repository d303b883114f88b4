"""Sweeps surviving faults on a Ray cluster of three nodes on 127.0.0.1 (slow: minutes).

A head that only schedules and two worker nodes whose memory holds one run each: a node
removed while a run trains on it, and the driver killed with SIGKILL and started again.
Each run must end bit-identical to the same run trained alone (tests/run/test_resume.py's
comparison), and no node may ever hold two runs at once.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from dqnlab.analysis.status import read_attempts, run_status
from dqnlab.sweeps.driver import run_sweep_on_ray
from dqnlab.sweeps.grid import PlannedRun, Sweep, parse_variation, plan_grid, planned_record
from dqnlab.sweeps.resources import RunResources
from tests.run.test_resume import assert_same_run
from tests.sweeps.ray_helpers import loopback_ray, non_loopback_sockets, ray_processes

pytestmark = pytest.mark.slow

NODE_MEMORY = 3_000_000_000
RUN_MEMORY = 2_000_000_000  # one run fits a node, two do not
SETTINGS = {
    "replay_start_steps": 200, "replay_capacity": 2000, "eval_period_steps": 500,
    "eval_steps": 200, "checkpoint_period_steps": 100, "final_eval_episodes": 2,
}  # fmt: skip
STEPS = 1500


def worker_node() -> dict[str, Any]:
    return {"num_cpus": 2, "memory": NODE_MEMORY}


@pytest.fixture(scope="module")
def ray_cluster():  # noqa: ANN201
    with loopback_ray(0, [worker_node(), worker_node()]) as cluster:
        yield cluster


def plan(sweep_dir: Path, seeds: int) -> Sweep:
    return plan_grid(
        ["CartPole-v1"], [parse_variation("discount=0.9,0.99")], preset=None,
        overrides=SETTINGS, seeds=seeds, first_seed=0, steps=STEPS, sweep_dir=sweep_dir,
    )  # fmt: skip


def attempts_by_node(sweep: Sweep) -> dict[str, list[tuple[float, float]]]:
    """(start, end) of every attempt by node; an attempt cut by its node's loss ends at inf."""
    intervals: dict[str, list[tuple[float, float]]] = {}
    for run in sweep.runs:
        events = read_attempts(run.run_dir)
        ends = {e["attempt"]: e["time"] for e in events if e["event"] == "end"}
        for start in (e for e in events if e["event"] == "start"):
            interval = (start["time"], ends.get(start["attempt"], float("inf")))
            intervals.setdefault(start["node_id"], []).append(interval)
    return intervals


def assert_one_run_per_node(sweep: Sweep) -> None:
    for node, intervals in attempts_by_node(sweep).items():
        intervals.sort()
        for (_, end), (next_start, _) in zip(intervals, intervals[1:], strict=False):
            assert next_start >= end, f"two runs at once on node {node}"


def test_a_lost_node_s_run_is_retried_elsewhere_and_ends_identical(
    tmp_path: Path,
    ray_cluster,
    trained_alone,  # noqa: ANN001
) -> None:
    sweep = plan(tmp_path / "sweep", seeds=2)
    resources = RunResources(cpus=1, gpus=0, memory_bytes=RUN_MEMORY)
    lines: list[str] = []
    driver = threading.Thread(
        target=run_sweep_on_ray, args=(sweep, resources),
        kwargs={"device": "cpu", "echo": lines.append, "poll_seconds": 0.2},
    )  # fmt: skip
    driver.start()
    try:
        check_node_loss(sweep, driver, ray_cluster, lines, trained_alone)
    finally:
        driver.join(timeout=900)  # never leave a driver thread behind the cluster's shutdown


def check_node_loss(
    sweep: Sweep, driver: threading.Thread, ray_cluster, lines, trained_alone
) -> None:  # noqa: ANN001
    victim, sockets_checked = None, False
    while victim is None and driver.is_alive():
        for run in sweep.runs:
            status = run_status(run.run_dir, planned_record(run))
            if status.state == "running" and status.step >= 400:
                victim = run
                break
        time.sleep(0.2)
    assert victim is not None, lines
    assert ray_processes() and non_loopback_sockets() == []  # while runs train
    sockets_checked = True
    node_id = [e for e in read_attempts(victim.run_dir) if e["event"] == "start"][-1]["node_id"]
    lost = next(node for node in ray_cluster.worker_nodes if node.node_id == node_id)
    lost_at = time.time()
    ray_cluster.remove_node(lost, allow_graceful=False)
    driver.join(timeout=900)
    assert not driver.is_alive() and sockets_checked
    assert [run.status for run in sweep.runs] == ["ok"] * 4, lines
    starts = [e for e in read_attempts(victim.run_dir) if e["event"] == "start"]
    assert len(starts) >= 2 and starts[-1]["node_id"] != node_id
    # The lost attempt's process was not SIGKILLed with its worker: it got SIGTERM, wrote
    # its stop checkpoint and left, and the retry carried on from there.
    assert victim.log is not None and "stopped by SIGTERM at step" in victim.log.read_text()
    print(f"node lost to its run training again: {starts[-1]['time'] - lost_at:.1f} s")
    for run in sweep.runs:
        assert_same_run(trained_alone(run.log.with_suffix(".toml"), "CartPole-v1"), run.run_dir)
    assert_one_run_per_node(sweep)
    ray_cluster.add_node(node_ip_address="127.0.0.1", **worker_node())  # for the next test


def test_a_killed_driver_run_again_carries_on(tmp_path: Path, ray_cluster, trained_alone) -> None:  # noqa: ANN001
    """Four runs on two nodes: the driver is killed once a run has finished and one of the
    second pair trains; the same command again skips the finished runs (their files
    untouched), resumes the others, and every run equals the same run trained alone."""
    sweep_dir = tmp_path / "sweep"
    command = [
        sys.executable, "-m", "dqnlab", "sweep", "--env", "CartPole-v1", "--seeds", "2",
        "--vary", "discount=0.9,0.99", "--steps", str(STEPS), "--sweep-dir", str(sweep_dir),
        "--address", ray_cluster.address, "--cpus-per-run", "1", "--memory-per-run", "2",
        "--no-report", *[f"--set={key}={value}" for key, value in SETTINGS.items()],
    ]  # fmt: skip
    driver = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    sweep = plan(sweep_dir, seeds=2)
    done: list[PlannedRun] = []
    while driver.poll() is None:
        states = [run_status(run.run_dir, planned_record(run)) for run in sweep.runs]
        done = [run for run, s in zip(sweep.runs, states, strict=True) if s.state == "done"]
        if done and any(s.state == "running" and s.step >= 300 for s in states):
            break
        time.sleep(0.2)
    assert driver.poll() is None and done, driver.stdout.read() if driver.stdout else ""
    kept = {path: path.stat().st_mtime_ns for run in done for path in run.run_dir.rglob("*")}
    driver.send_signal(signal.SIGKILL)
    driver.wait()
    again = subprocess.run(command, capture_output=True, text=True, timeout=900)
    assert again.returncode == 0, again.stdout + again.stderr
    for run in done:
        assert f"{run.name}: already finished, skipped" in again.stdout
    assert {path: path.stat().st_mtime_ns for path in kept} == kept  # not trained again
    for run in sweep.runs:
        config_path = sweep_dir / "logs" / f"{run.name}.toml"
        assert_same_run(trained_alone(config_path, "CartPole-v1"), run.run_dir)


def test_gpu_fractions_share_a_gpu_and_whole_gpus_do_not(tmp_path: Path, ray_cluster) -> None:  # noqa: ANN001
    """A node declaring one GPU (Ray's GPUs are counted, not probed; the runs train on the
    CPU): runs asking 0.5 GPU train on it two at a time, runs asking 1 GPU one at a time,
    and none goes to the nodes without a GPU."""
    gpu_node = ray_cluster.add_node(
        node_ip_address="127.0.0.1", num_cpus=2, num_gpus=1, memory=2 * NODE_MEMORY
    )
    try:
        for gpus, overlapping in ((0.5, True), (1.0, False)):
            sweep = plan_grid(
                ["CartPole-v1"], [parse_variation("discount=0.9,0.99")], preset=None,
                overrides=SETTINGS, seeds=1, first_seed=0, steps=600,
                sweep_dir=tmp_path / f"gpus-{gpus}",
            )  # fmt: skip
            resources = RunResources(cpus=1, gpus=gpus, memory_bytes=RUN_MEMORY)
            run_sweep_on_ray(sweep, resources, device="cpu", echo=lambda _: None, poll_seconds=0.2)
            assert [run.status for run in sweep.runs] == ["ok", "ok"]
            intervals = attempts_by_node(sweep)
            assert list(intervals) == [gpu_node.node_id]
            (first, first_end), (second, _) = sorted(intervals[gpu_node.node_id])
            assert (second < first_end) == overlapping, (gpus, intervals)
    finally:
        ray_cluster.remove_node(gpu_node)
