"""Learning tests (slow, `make test-slow`): the classic preset solves CartPole-v1.

Solved means the run's best network scores a mean of at least 475 over 20 evaluation
games (the Gymnasium threshold), within the preset's budget of at most 100k steps.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from dqnlab.config import resolve_config
from dqnlab.run.evaluate import final_evaluation
from dqnlab.run.rundir import prepare_run_dir
from dqnlab.run.train import train


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_classic_preset_solves_cartpole(tmp_path: Path, seed: int) -> None:
    config = resolve_config("classic", env="CartPole-v1", seed=seed)
    assert config.total_steps <= 100_000
    run = tmp_path / f"cartpole-{seed}"
    prepare_run_dir(run, force=False)
    trained = train(config, run, torch.device("cpu"), progress=False, tensorboard=False)
    result, _ = final_evaluation(run, "best", 20, seed=1000 + seed, device=torch.device("cpu"))
    first_solved = next((step for step, mean in trained.evaluations if mean >= 475), None)
    print(f"seed {seed}: first periodic evaluation >= 475 at step {first_solved}; "
          f"final 20 games {result.mean:.1f} ± {result.std:.1f}")  # fmt: skip
    assert len(result.scores) == 20
    assert result.mean >= 475
