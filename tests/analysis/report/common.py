"""Constants, tiny runs and helpers shared by the report's tests."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from dqnlab.analysis.report import (
    ALL_EQUAL,
    AggregateSettings,
    Report,
    final_network_evaluator,
)
from dqnlab.config import resolve_config
from dqnlab.run import rundir
from dqnlab.run.rundir import prepare_run_dir, save_final_evaluation
from dqnlab.run.train import train

# Rows of data/atari_scores.csv: random, dqn_zoo human, Nature human, Nature DQN (± s.d.).
PONG = {"random": -20.7, "human": 14.6, "human_nature": 9.3, "dqn": 18.9, "dqn_std": 1.3}
BREAKOUT = {"random": 1.7, "human": 30.5, "human_nature": 31.8, "dqn": 401.2, "dqn_std": 26.9}

ATARI_TINY = {
    "replay_start_steps": 100,
    "replay_capacity": 1000,
    "batch_size": 8,
    "eval_period_steps": 100,
    "eval_steps": 100,
    "final_eval_episodes": 1,
    "final_eval_max_episode_frames": 400,
    "eval_networks_kept": "best_and_worst",
    "checkpoints_kept": 1,
}
CARTPOLE_TINY = {
    "env": "CartPole-v1",
    "total_steps": 600,
    "replay_start_steps": 100,
    "replay_capacity": 1000,
    "eval_period_steps": 200,
    "eval_steps": 200,
    "final_eval_max_episode_frames": 50,
    "eval_networks_kept": "best_and_worst",
    "checkpoints_kept": 1,
}
# Hand-written final evaluations: pong seeds 0 and 1, breakout seed 0.
PONG_SCORES = {0: [-21.0, -19.0], 1: [-10.0, -12.0]}
BREAKOUT_SCORES = [10.0, 20.0, 30.0]
# A small bootstrap for the aggregates across games of reports of two games: CI has minutes.
FEW_REPS = AggregateSettings(bootstrap_repetitions=200)


def train_run(run_dir: Path, preset: str, **settings: Any) -> Path:
    config = resolve_config(preset, **settings)
    prepare_run_dir(run_dir, force=False)
    train(config, run_dir, torch.device("cpu"), progress=False, tensorboard=False)
    return run_dir


def write_final_evaluation(run_dir: Path, scores: list[float]) -> None:
    """A final evaluation with known scores, of the run's real best network."""
    best = run_dir / "checkpoints" / "best.pt"
    save_final_evaluation(
        run_dir,
        {
            "env": run_dir.name,
            "checkpoint": str(best),
            "checkpoint_step": rundir.load_network(best)["step"],
            "seed": 12345,
            "episodes": len(scores),
            "epsilon": 0.05,
            "max_episode_frames": 18000,
            "scores": scores,
            "mean": float(np.mean(scores)),
            "std": float(np.std(scores)),
            "frames": 0,
            "frames_per_second": 0.0,
        },
    )


def must_not_evaluate(run_dir: Path) -> dict[str, Any]:
    pytest.fail(f"{run_dir} has a final evaluation; none should be played")


class CountingEvaluator:
    """The report's default evaluator (2 games), counting its calls per run."""

    def __init__(self) -> None:
        self.calls: list[Path] = []
        self.evaluate = final_network_evaluator(torch.device("cpu"), episodes=2)

    def __call__(self, run_dir: Path) -> dict[str, Any]:
        self.calls.append(run_dir)
        return self.evaluate(run_dir)


def hns(score: float, game: dict[str, float], baseline: str) -> float:
    return 100 * (score - game["random"]) / (game[baseline] - game["random"])


def row_of(report: Report, game: str, configuration: str = ALL_EQUAL) -> Any:
    (row,) = [r for r in report.rows if r.game == game and r.configuration == configuration]
    return row
