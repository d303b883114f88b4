"""The Atari 100k presets resume exactly: a `der` run (noise, priorities, 20-step returns)
and a `drq_epsilon` run (the augmentation's draws) killed at random moments and resumed
end bit-identical to the same runs left alone, on a tiny replay."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.run.test_resume import assert_same_run, train_killed_and_resumed

# Short runs of the presets on Pong: periodic evaluations and held-out transitions back on
# so that `assert_same_run` compares them too; no final evaluation (nothing to resume);
# minibatches of 8 (what is tested is the resume, not the presets' batch size).
TINY = [
    "--env", "pong", "--steps", "300", "--seed", "4", "--set", "batch_size=8",
    "--set", "replay_start_steps=100", "--set", "replay_capacity=300",
    "--set", "eval_period_steps=150", "--set", "eval_steps=50",
    "--set", "checkpoint_period_steps=40",
    "--set", "final_eval_after_training=false", "--set", "heldout_transitions=50",
    "--no-progress", "--device", "cpu",
]  # fmt: skip


# Both under the slow marker, for CI's time: the augmentation's state round-trips in
# tests/algorithm/test_augmentation.py, Rainbow's parts in tests/algorithm/.
@pytest.mark.slow
@pytest.mark.parametrize("preset", ["der", "drq_epsilon"])
def test_an_atari100k_preset_killed_and_resumed_is_bit_identical(tmp_path: Path, preset) -> None:
    args = [*TINY, "--preset", preset]
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    kills = train_killed_and_resumed(args, reference, resumed, most_kills=2)
    assert kills >= 2, "the run was too fast to be killed twice"
    assert_same_run(reference, resumed)
