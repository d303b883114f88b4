"""scripts/sweep_overhead.py: its arithmetic (worked out by hand), and its figures on the
smallest settings (slow: loopback Ray clusters, tiny CartPole runs; not their speed)."""

from __future__ import annotations

import json
from pathlib import Path

import psutil
import pytest

from dqnlab.sweeps.resources import RunResources
from tests.scripts import load_script

sweep_overhead = load_script("sweep_overhead")
overhead_figures = sweep_overhead.overhead_figures
run_sweep_benchmark = sweep_overhead.run_sweep_benchmark
runs_at_once = sweep_overhead.runs_at_once


def test_overhead_per_run_is_the_difference_of_the_walls_over_the_runs() -> None:
    figures = overhead_figures(
        by_hand=[(20.0, [9.0, 10.0]), (22.0, [10.0, 11.0])],
        on_ray=[(24.0, [10.0, 12.0]), (23.0, [11.0, 11.0])],
        runs=2,
        start_up_seconds=6.0,
    )
    assert figures["by_hand_seconds_runs"] == [20.0, 22.0]
    assert figures["sweep_seconds_runs"] == [24.0, 23.0]
    assert figures["overhead_per_run_seconds_runs"] == [2.0, 0.5]  # (24-20)/2, (23-22)/2
    assert figures["overhead_per_run_seconds"] == pytest.approx(1.25)
    assert figures["overhead_per_run_with_start_up_seconds"] == pytest.approx(1.25 + 6.0 / 2)
    assert figures["sweep_to_by_hand_ratio"] == pytest.approx(23.5 / 21.0)
    assert figures["by_hand_run_seconds"] == pytest.approx(10.0)
    assert figures["sweep_run_seconds"] == pytest.approx(11.0)


def test_runs_at_once_adds_what_each_node_holds() -> None:
    resources = RunResources(cpus=1, gpus=0, memory_bytes=1_500_000_000)
    nodes = [{"CPU": 2.0, "memory": 16e9}, {"CPU": 4.0, "memory": 2e9}, {"CPU": 0.0}]
    assert runs_at_once(resources, nodes) == 2 + 1 + 0  # CPUs, memory, nothing
    quarter_gpu = RunResources(cpus=1, gpus=0.25, memory_bytes=0)
    assert runs_at_once(quarter_gpu, [{"CPU": 8.0, "GPU": 1.0}, {"CPU": 8.0}]) == 4


def _own_raylets() -> list[psutil.Process]:
    children = psutil.Process().children(recursive=True)
    return [process for process in children if "raylet" in process.name()]


@pytest.mark.slow
def test_the_sweep_benchmark_gives_every_figure(tmp_path: Path) -> None:
    lines: list[str] = []
    figures = run_sweep_benchmark(
        tmp_path, runs=2, repeats=1, run_steps=300, node_loss_steps=800, echo=lines.append
    )
    json.dumps(figures)  # what --json writes
    assert _own_raylets() == []  # both clusters shut down
    assert figures["ray_start_seconds"] > 0 and figures["ray_first_task_seconds"] > 0
    assert 1 <= figures["runs_at_once"] <= 2
    assert len(figures["by_hand_seconds_runs"]) == len(figures["sweep_seconds_runs"]) == 1
    hand, sweep = figures["by_hand_seconds"], figures["sweep_seconds"]
    assert hand > 0 and sweep > 0
    assert figures["by_hand_run_seconds"] > 0 and figures["sweep_run_seconds"] > 0
    assert figures["overhead_per_run_seconds"] == pytest.approx((sweep - hand) / 2)
    start_up = figures["ray_start_seconds"] + figures["ray_first_task_seconds"]
    assert figures["overhead_per_run_with_start_up_seconds"] == pytest.approx(
        figures["overhead_per_run_seconds"] + start_up / 2
    )
    # The lost run: retried once on the other node, resumed from a checkpoint, trained
    # past it, and finished to its budget.
    assert figures["node_loss_to_lost_process_exit_seconds"] >= 0
    assert figures["node_loss_to_retry_start_seconds"] > 0
    assert figures["node_loss_to_retry_start_seconds"] < figures["node_loss_to_training_seconds"]
    assert figures["node_loss_lease_rule"] in ("released", "owner_gone", "expiry")
    period = figures["node_loss_checkpoint_period_steps"]
    assert period <= figures["node_loss_resumed_step"] < figures["node_loss_step_seen"]
    assert figures["node_loss_attempts"] == 2
    assert figures["node_loss_final_step"] == figures["node_loss_total_steps"] == 800
