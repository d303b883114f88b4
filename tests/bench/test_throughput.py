"""The benchmark command's figures are produced and consistent (not their speed)."""

from __future__ import annotations

import pytest
import torch

from dqnlab.bench.throughput import run_benchmark
from dqnlab.config import resolve_config
from dqnlab.run.lockstep import default_workers


def test_benchmark_figures_on_a_small_replay() -> None:
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


def test_compression_figures_compare_the_two_replays_on_the_games_frames(tmp_path) -> None:
    from dqnlab.bench.compression import measure_compression

    figures = measure_compression(
        "pong", fill_steps=2500, train_steps=12, device=torch.device("cpu"), rounds=1,
        scratch_dir=tmp_path, checkpoint_capacity=5000,
    )  # fmt: skip
    assert figures["compression_batches_identical"] is True
    # 2,500 slots are one chunk, compressed when full and reopened by the training steps.
    assert figures["compression_ratio"] > 4.7
    # The checkpoints are of 5,000 slots repeating the 2,500 filled ones.
    assert figures["compression_checkpoint_bytes_raw"] == 5000 * (84 * 84 + 10)
    assert (
        figures["compression_checkpoint_bytes_lz4"]
        < figures["compression_checkpoint_bytes_raw"] / 4
    )
    for name in ("raw", "lz4"):
        assert figures[f"compression_train_frames_per_second_{name}"] > 0
    assert figures["compression_sample_us"] > 0 and figures["compression_sample_us_raw"] > 0
    assert list(tmp_path.iterdir()) == []  # the checkpoints were removed


def test_the_compression_scan_measures_whole_chunks_of_each_game() -> None:
    from dqnlab.bench.compression import scan

    rows = scan(["pong", "breakout"], steps=150, chunk_slots=100)
    assert [row["game"] for row in rows] == ["pong", "breakout"]
    for row in rows:
        assert row["frames_measured"] >= 200  # two whole chunks (and the slot after them)
        assert row["ratio"] == pytest.approx(84 * 84 / row["lz4_bytes_per_frame"], rel=0.01)
        assert row["ratio"] > 4.7
