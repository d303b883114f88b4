"""Tiny real runs, trained once for all the report's tests."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from dqnlab.analysis.report import (
    Report,
    write_report,
)
from tests.analysis.report.common import (
    ATARI_TINY,
    BREAKOUT_SCORES,
    CARTPOLE_TINY,
    FEW_REPS,
    PONG_SCORES,
    must_not_evaluate,
    train_run,
    write_final_evaluation,
)


@pytest.fixture(scope="package")
def atari_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Pong seeds 0 (300 steps) and 1 (200 steps: a shorter budget, fewer evaluations),
    breakout seed 0; final evaluations written by hand."""
    root = tmp_path_factory.mktemp("atari")
    runs = {
        "pong-s0": train_run(
            root / "pong-s0", "nature", env="pong", seed=0, total_steps=300, **ATARI_TINY
        ),
        "pong-s1": train_run(
            root / "pong-s1", "nature", env="pong", seed=1, total_steps=200, **ATARI_TINY
        ),
        "breakout-s0": train_run(
            root / "breakout-s0", "nature", env="breakout", seed=0, total_steps=300, **ATARI_TINY
        ),
    }
    write_final_evaluation(runs["pong-s0"], PONG_SCORES[0])
    write_final_evaluation(runs["pong-s1"], PONG_SCORES[1])
    write_final_evaluation(runs["breakout-s0"], BREAKOUT_SCORES)
    return runs


@pytest.fixture(scope="package")
def atari_report(atari_runs: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Report:
    out = tmp_path_factory.mktemp("atari-report")
    return write_report(
        list(atari_runs.values()), out, evaluate_missing=must_not_evaluate, aggregate=FEW_REPS
    )


@pytest.fixture(scope="package")
def cartpole_sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A sweep directory: life_loss_terminal true with seeds 0 and 1, false with seed 0
    (CartPole ignores the setting, but it is a setting: it labels a configuration)."""
    sweep = tmp_path_factory.mktemp("cartpole-sweep")
    for terminal, seed in ((True, 0), (True, 1), (False, 0)):
        name = f"life_loss_terminal={str(terminal).lower()}-s{seed}"
        train_run(sweep / name, "classic", seed=seed, life_loss_terminal=terminal, **CARTPOLE_TINY)
    (sweep / "logs").mkdir()  # a sweep holds other folders too: not runs, skipped
    return sweep


@pytest.fixture
def cartpole_copy(cartpole_sweep: Path, tmp_path: Path) -> Path:
    """The sweep as it was trained, for a test that adds final evaluations to it."""
    return Path(shutil.copytree(cartpole_sweep, tmp_path / "sweep"))
