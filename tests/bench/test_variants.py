"""`dqnlab bench variants`: every variant's figures are produced, the ratios are the ratios
of the figures, and bad lists are refused in one line (not the speeds themselves)."""

from __future__ import annotations

import pytest
import torch

from dqnlab.bench import flops, variants
from dqnlab.bench.variants import FAMILY, measure_variants, parse_variants
from dqnlab.errors import ConfigError
from dqnlab.run.state import TIMED_PARTS


def test_every_variants_figures_and_their_ratios(monkeypatch) -> None:
    # A small tree for the full-replay figure: its size is a parameter, not what is tested.
    monkeypatch.setattr(variants, "FULL_REPLAY_SLOTS", 4096)
    monkeypatch.setattr(flops, "MATMUL_SIZE", 256)
    presets = ["nature", "double", "prioritized", "iqn"]
    figures = measure_variants(
        presets, "pong", steps=30, replay_capacity=1200, device=torch.device("cpu"),
        rounds=2, update_repeats=2,
    )  # fmt: skip
    for preset in presets:
        for figure in ("sample_us", "update_ms", "train_frames_per_second"):
            assert figures[f"{preset}_{figure}"] > 0, (preset, figure)
        assert len(figures[f"{preset}_train_frames_per_second_runs"]) == 2
        achieved = figures[f"{preset}_update_gflop"] / (figures[f"{preset}_update_ms"] / 1e3)
        assert figures[f"{preset}_update_gflop_per_s"] == pytest.approx(achieved)
        assert figures[f"{preset}_update_fraction_of_matmul"] == pytest.approx(
            achieved / figures[f"{preset}_matmul_gflop_per_s"]
        )
        assert figures[f"{preset}_train_ratio_vs_nature"] == pytest.approx(
            figures[f"{preset}_train_frames_per_second"] / figures["nature_train_frames_per_second"]
        )
        # One whole run: its total_steps at the training rate; each timed part's share.
        steps_per_second = figures[f"{preset}_train_frames_per_second"] / 4
        assert figures[f"{preset}_training_minutes_per_run"] == pytest.approx(
            50_000_000 / steps_per_second / 60
        )
        assert figures[f"{preset}_eval_minutes_per_10k_steps"] == pytest.approx(
            10_000 / (figures[f"{preset}_eval_frames_per_second"] / 4) / 60
        )
        split = [figures[f"{preset}_train_split_{part}"] for part in TIMED_PARTS + ("other",)]
        assert sum(split) == pytest.approx(1.0) and figures[f"{preset}_train_split_update"] > 0
    assert figures["prioritized_train_ratio_vs_double"] == pytest.approx(
        figures["prioritized_train_frames_per_second"] / figures["double_train_frames_per_second"]
    )
    assert figures["prioritized_1m_sample_and_update_us"] > 0
    # The double target's extra forward pass on the next states: F per transition more.
    forward = (figures["double_update_gflop"] - figures["nature_update_gflop"]) * 1e9 / 32
    assert forward == pytest.approx(18_692_096)  # the Nature CNN, 6 Pong actions
    assert figures["variants"] == ",".join(presets)
    # IQN's update runs its head at N = 64 fractions per state online and K + N' = 96 on the
    # next states: many times the Nature head's products, all counted.
    assert figures["iqn_update_gflop"] > 2 * figures["nature_update_gflop"]


def test_the_list_of_variants() -> None:
    assert parse_variants("all") == list(FAMILY)
    assert parse_variants("nature, rainbow") == ["nature", "rainbow"]
    for text in ("nature,rainbo", ""):
        with pytest.raises(ConfigError, match="not a shipped preset") as error:
            parse_variants(text)
        assert "\n" not in str(error.value)
