"""A run of several environments (`num_envs` = 3) killed at random moments and resumed
equals the uninterrupted run: weights, optimizer, replay streams, every random stream and
every environment's emulator state (test_resume.py does the same with one environment)."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.config import config_fingerprint
from dqnlab.run.checkpoints import CheckpointStore
from dqnlab.run.rundir import load_run_config
from tests.run.test_resume import (
    CARTPOLE,
    NESTED_DICT,
    PONG,
    RAINBOW_CARTPOLE,
    _frame_layout,
    assert_identical,
    csv_rows,
    dqnlab,
    finish,
    tensorboard_steps,
    train_killed_and_resumed,
    wait_for_checkpoint,
)

THREE = ["--set", "num_envs=3"]
VARIANTS = {
    # 3001 steps: the last advance steps one environment alone.
    "cartpole": [*CARTPOLE, *THREE, "--steps", "3001", "--set", "replay_capacity=2100"],
    "rainbow-cartpole": [*RAINBOW_CARTPOLE, *THREE, "--set", "replay_capacity=2100"],
    "pong": [*PONG, *THREE, "--set", "replay_capacity=600"],
    "nested-dict": [*NESTED_DICT, *THREE, "--set", "replay_capacity=2100"],
}


def final_state(run: Path) -> tuple[dict, dict]:
    config = load_run_config(run)
    replay = ReplayMemory(
        config.replay_capacity, *_frame_layout(config), config.history_length, 32, 0,
        streams=config.num_envs,
    )  # fmt: skip
    loaded = CheckpointStore(run).latest(config_fingerprint(config), into=replay.arrays)
    assert loaded is not None and loaded.step == config.total_steps
    return loaded.state, replay.arrays


def assert_same_run(reference: Path, resumed: Path) -> None:
    state_a, replay_a = final_state(reference)
    state_b, replay_b = final_state(resumed)
    assert len(state_a["learner"]["more_envs"]) == 2
    assert_identical(state_a["learner"], state_b["learner"], "learner")
    assert_identical(state_a["run"], state_b["run"], "run")
    assert_identical(replay_a, replay_b, "replay")
    timing = ("wall_seconds", "frames_per_second")
    for name in ("episodes.csv", "evaluations.csv"):
        assert csv_rows(reference / name, timing) == csv_rows(resumed / name, timing), name
    assert tensorboard_steps(resumed) == tensorboard_steps(reference)


# The fast suite keeps CartPole; Rainbow's parts, Pong's emulators (resumed with one
# environment in test_resume.py) and the nested Dict space (trained and resumed in
# tests/envs/test_spaces_pipeline.py) with three environments run under the slow marker,
# for CI's time.
SLOW_VARIANTS = ("rainbow-cartpole", "pong", "nested-dict")


@pytest.mark.parametrize(
    "name",
    [pytest.param(name, marks=pytest.mark.slow) if name in SLOW_VARIANTS else name
     for name in VARIANTS],
)  # fmt: skip
def test_three_environments_killed_and_resumed_are_bit_identical(tmp_path: Path, name) -> None:
    args = VARIANTS[name]
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    kills = train_killed_and_resumed(args, reference, resumed, most_kills=2)
    assert kills >= 1, "the run was too fast to be killed"
    assert_same_run(reference, resumed)


# Slow (CI's time): the stop signal's checkpoint and resume with one environment are
# test_resume.py's, and three environments killed and resumed the test above's.
@pytest.mark.slow
def test_a_stop_signal_checkpoints_three_environments_and_resumes(tmp_path: Path) -> None:
    args = VARIANTS["cartpole"]
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    code, stderr = finish(dqnlab("train", *args, "--run-dir", str(reference)))
    assert code == 0, stderr
    process = dqnlab("train", *args, "--run-dir", str(resumed))
    assert wait_for_checkpoint(resumed, process, after=0)
    process.send_signal(signal.SIGTERM)
    code, stderr = finish(process)
    assert code == 143, stderr
    stopped_at = int(stderr.split(" at step ")[1].split()[0])
    assert stopped_at % 3 == 0 and CheckpointStore(resumed).steps()[-1] == stopped_at
    code, stderr = finish(dqnlab("resume", str(resumed), "--no-progress", "--device", "cpu"))
    assert code == 0, stderr
    assert_same_run(reference, resumed)
