"""The benchmark command's figures are produced and consistent (not their speed)."""

from __future__ import annotations

import torch

from dqnlab.bench import run_benchmark


def test_benchmark_figures_on_a_small_replay() -> None:
    figures = run_benchmark(
        "pong", steps=40, replay_capacity=3000, device=torch.device("cpu"), update_repeats=3
    )
    assert figures["replay_bytes_per_transition"] == 84 * 84 + 10
    # Every slot was written, so the replay is resident: at least its arrays' size.
    assert figures["replay_resident_bytes"] >= 0.95 * 3000 * (84 * 84 + 10)
    for name in ("sample_us", "update_ms", "train_frames_per_second", "eval_frames_per_second"):
        assert figures[name] > 0, name
    assert figures["device"] == "cpu" and figures["threads"] >= 1
