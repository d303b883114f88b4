"""scripts/compression_scan.py: the per-game scan of compressed frame sizes measures whole
chunks of each game (not their speed)."""

from __future__ import annotations

import pytest

from tests.scripts import load_script

compression_scan = load_script("compression_scan")


def test_the_compression_scan_measures_whole_chunks_of_each_game() -> None:
    rows = compression_scan.scan(["pong", "breakout"], steps=150, chunk_slots=100)
    assert [row["game"] for row in rows] == ["pong", "breakout"]
    for row in rows:
        assert row["frames_measured"] >= 200  # two whole chunks (and the slot after them)
        assert row["ratio"] == pytest.approx(84 * 84 / row["lz4_bytes_per_frame"], rel=0.01)
        assert row["ratio"] > 4.7
