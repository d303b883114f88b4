"""The compressed replay's figures against the raw replay's on a game's frames (not their
speed); the per-game scan is scripts/compression_scan.py's (tests/scripts)."""

from __future__ import annotations

import torch

from dqnlab.bench.compression import measure_compression


def test_compression_figures_compare_the_two_replays_on_the_games_frames(tmp_path) -> None:
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
