"""The `threads` setting: the CPU's arithmetic depends on the thread count, so a run records
its count in every checkpoint and a resume takes it back (or says it will not be exact);
and a warning when the cores are already busy."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from dqnlab.config import Config, resolve_config
from dqnlab.errors import ConfigError
from dqnlab.run import determinism
from dqnlab.run.determinism import busy_cores_warning, resume_threads
from tests.run.test_resume import (
    CARTPOLE,
    assert_identical,
    final_state,
    finish,
    wait_for_checkpoint,
)

CPU = torch.device("cpu")


@pytest.fixture(autouse=True)
def _restore_threads() -> Iterator[None]:
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def _config(threads: int, total_steps: int) -> Config:
    # The classic preset's MLP of 256 x 256 at batch 64: large enough for the matrix
    # products to split across threads (a tiny network gives the same bits at any count).
    return resolve_config(
        "classic", env="CartPole-v1", seed=5, total_steps=total_steps, threads=threads,
        replay_start_steps=100, eval_period_steps=1000, eval_steps=100,
        checkpoint_period_steps=100, final_eval_after_training=False,
    )  # fmt: skip


def _dqnlab(threads: int, *args: str) -> subprocess.Popen[str]:
    """`dqnlab` in a process whose PyTorch default is `threads` (OMP_NUM_THREADS)."""
    return subprocess.Popen(
        [sys.executable, "-m", "dqnlab", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "OMP_NUM_THREADS": str(threads)},
    )  # fmt: skip


def test_a_resume_takes_back_the_thread_count_the_run_trained_with(tmp_path: Path) -> None:
    """Trained in a process of one thread (`threads = 0`: the default there), killed, and
    resumed in a process of two: the resume sets one thread again and ends where the run
    left alone ends (with two threads its updates give other bits on this CPU)."""
    args = [*CARTPOLE[: CARTPOLE.index("--steps")], "--steps", "1000",
            *CARTPOLE[CARTPOLE.index("--steps") + 2 :]]  # fmt: skip
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    code, stderr = finish(_dqnlab(1, "train", *args, "--run-dir", str(reference)))
    assert code == 0, stderr
    process = _dqnlab(1, "train", *args, "--run-dir", str(resumed))
    assert wait_for_checkpoint(resumed, process, after=300), "the run ended before a kill"
    process.send_signal(signal.SIGKILL)
    process.wait()
    code, stderr = finish(_dqnlab(2, "resume", str(resumed), "--no-progress", "--device", "cpu"))
    assert code == 0, stderr
    assert "resuming with the 1 PyTorch thread(s) the run trained with" in stderr
    state, replay = final_state(reference)
    state_resumed, replay_resumed = final_state(resumed)
    assert state_resumed["threads"] == 1
    assert_identical(state["learner"], state_resumed["learner"], "learner")
    assert_identical(replay, replay_resumed, "replay")


def test_a_count_set_otherwise_at_resume_wins_and_says_it_will_not_be_exact() -> None:
    torch.set_num_threads(2)
    said = resume_threads(_config(threads=2, total_steps=600), CPU, trained_with=1)
    assert said is not None and "not bit for bit" in said
    assert torch.get_num_threads() == 2
    said = resume_threads(_config(threads=0, total_steps=600), CPU, trained_with=1)
    assert said is not None and "resuming with the 1" in said
    assert torch.get_num_threads() == 1
    # Nothing to say: the same count, or a checkpoint from before the count was recorded.
    assert resume_threads(_config(threads=0, total_steps=600), CPU, trained_with=1) is None
    assert resume_threads(_config(threads=0, total_steps=600), CPU, trained_with=None) is None


def test_busy_cores_are_warned_of_only_for_several_threads_on_the_cpu(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(determinism, "usable_cores", lambda: 2)
    monkeypatch.setattr(determinism.os, "getloadavg", lambda: (2.1, 2.0, 1.0))
    warning = busy_cores_warning(2, CPU)
    assert warning is not None and "2.1 on 2 cores" in warning and "threads=1" in warning
    assert busy_cores_warning(1, CPU) is None
    assert busy_cores_warning(2, torch.device("cuda")) is None
    monkeypatch.setattr(determinism.os, "getloadavg", lambda: (0.3, 0.5, 1.0))
    assert busy_cores_warning(2, CPU) is None


def test_threads_below_zero_is_refused_in_one_line() -> None:
    with pytest.raises(ConfigError, match="threads = -1 must be zero or more"):
        _config(threads=-1, total_steps=600)
