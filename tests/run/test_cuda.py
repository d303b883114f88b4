"""Runs on a CUDA device: `deterministic` makes a run repeat bit for bit and a resumed run
continue exactly (both skipped without CUDA; on an H200 on 2026-12-04, two same-seed runs
without it differed in every weight, and a resume failed on device tensors handed to
NumPy). The warning a resume without `deterministic` prints is checked everywhere."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from dqnlab.config import resolve_config
from dqnlab.run.determinism import resume_warning
from dqnlab.run.rundir import prepare_run_dir
from dqnlab.run.train import train
from tests.run.test_resume import assert_identical, final_state

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def _config(total_steps: int):
    # The Nature network on Pong (cuDNN's convolutions are the nondeterministic part),
    # with a short replay start and a short budget.
    return resolve_config(
        "nature", env="pong", total_steps=total_steps, replay_start_steps=100,
        replay_capacity=400, eval_period_steps=10_000, checkpoint_period_steps=10_000,
        heldout_transitions=0, final_eval_after_training=False,
    )  # fmt: skip


def _train(run: Path, total_steps: int, resume: bool = False) -> None:
    if not resume:
        prepare_run_dir(run, force=False)
    train(_config(total_steps), run, torch.device("cuda"), progress=False, tensorboard=False,
          resume=resume)  # fmt: skip


@CUDA
def test_two_runs_from_one_seed_are_bit_identical_on_cuda(tmp_path: Path) -> None:
    _train(tmp_path / "a", 300)
    _train(tmp_path / "b", 300)
    (state_a, replay_a), (state_b, replay_b) = (final_state(tmp_path / name) for name in "ab")
    assert_identical(state_a["learner"], state_b["learner"], "learner")
    assert_identical(replay_a, replay_b, "replay")


@CUDA
def test_a_resumed_cuda_run_ends_as_the_uninterrupted_one(tmp_path: Path) -> None:
    _train(tmp_path / "whole", 300)
    _train(tmp_path / "parts", 200)
    _train(tmp_path / "parts", 300, resume=True)
    (state_a, replay_a), (state_b, replay_b) = (
        final_state(tmp_path / "whole"), final_state(tmp_path / "parts", total_steps=300)
    )  # fmt: skip
    assert_identical(state_a["learner"], state_b["learner"], "learner")
    assert_identical(replay_a, replay_b, "replay")


def test_a_resume_without_deterministic_on_cuda_says_it_will_not_be_exact() -> None:
    config = resolve_config("nature", env="pong")
    cuda, cpu = torch.device("cuda"), torch.device("cpu")
    assert resume_warning(config, cuda) is None
    assert resume_warning(dataclasses.replace(config, deterministic=False), cpu) is None
    warning = resume_warning(dataclasses.replace(config, deterministic=False), cuda)
    assert warning is not None and "deterministic = false" in warning
    assert "not bit for bit" in warning
