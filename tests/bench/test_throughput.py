"""The benchmark's throughput and memory figures are produced and consistent (not their speed)."""

from __future__ import annotations

import pytest
import torch

from dqnlab.bench import flops
from dqnlab.bench.throughput import run_benchmark
from dqnlab.config import resolve_config
from dqnlab.run.lockstep import default_workers


def test_benchmark_figures_on_a_small_replay(monkeypatch) -> None:
    # A small matrix multiply: its size is a parameter, not what is tested.
    monkeypatch.setattr(flops, "MATMUL_SIZE", 256)
    figures = run_benchmark(
        "pong", steps=40, replay_capacity=3000, device=torch.device("cpu"), update_repeats=3
    )
    assert figures["replay_bytes_per_transition"] == 84 * 84 + 10
    # Every slot was written, so the process holds at least the replay's arrays. (The
    # growth measured can be smaller than the arrays in a process that freed memory before.)
    assert figures["peak_resident_bytes"] >= 3000 * (84 * 84 + 10)
    assert figures["replay_resident_bytes"] <= 1.05 * 3000 * (84 * 84 + 10) + 2**20
    for name in (
        "sample_us",
        "update_ms",
        "train_frames_per_second",
        "eval_frames_per_second",
        "eval_frames_per_second_single",
    ):
        assert figures[name] > 0, name
    assert figures["device"] == "cpu" and figures["threads"] >= 1
    # The update's FLOPs (bench/flops.py, Nature CNN, 6 Pong actions), its GFLOP/s in the
    # update time measured, against the matrix multiply's in the same run.
    assert figures["update_gflop"] == pytest.approx(32 * (4 * 18_692_096 - 6_553_600) / 1e9)
    achieved = figures["update_gflop"] / (figures["update_ms"] / 1e3)
    assert figures["update_gflop_per_s"] == pytest.approx(achieved)
    assert figures["matmul_size"] == 256 and figures["matmul_threads"] == figures["threads"]
    assert figures["update_fraction_of_matmul"] == pytest.approx(
        achieved / figures["matmul_gflop_per_s"]
    )
    # The final evaluation's games, all at once (30 in the nature preset), on every core.
    assert figures["eval_envs"] == 30
    assert figures["eval_workers"] == default_workers(resolve_config("nature", env="pong"))


def test_benchmark_with_the_peer_alternates_and_reports_the_ratio() -> None:
    pytest.importorskip("stable_baselines3")
    figures = run_benchmark(
        "pong", steps=40, replay_capacity=3000, device=torch.device("cpu"), update_repeats=2,
        peers=True, peer_learning_starts=100,
    )  # fmt: skip
    assert len(figures["train_frames_per_second_runs"]) == 2
    assert len(figures["peer_train_frames_per_second_runs"]) == 2
    ratio = figures["train_frames_per_second"] / figures["peer_train_frames_per_second"]
    assert figures["train_ratio_vs_peer"] == pytest.approx(ratio)
    assert figures["peer"] == "stable-baselines3"
