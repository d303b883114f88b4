"""A killed run resumes exactly: real processes, SIGKILL at random moments, bit-identical state.

Each test trains a short run uninterrupted and the same run killed (or stopped) several
times and resumed, then compares the final checkpoints: network weights, optimizer state,
every random stream, the replay memory, and the logs (no duplicate or missing rows).
"""

from __future__ import annotations

import csv
import os
import pickle
import random
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from ale_py import ALEState

from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.config import config_fingerprint, resolve_config
from dqnlab.envs.atari import AtariEnv
from dqnlab.errors import DqnlabError, EnvError, ResourceError
from dqnlab.run.checkpoints import CheckpointStore
from dqnlab.run.rundir import load_run_config, prepare_run_dir
from dqnlab.run.state import TrainingDiverged, TrainingState
from dqnlab.run.train import train
from tests.helpers import RunsCode

CARTPOLE = [
    "--env", "CartPole-v1", "--steps", "3000", "--seed", "5",
    "--set", "replay_start_steps=300", "--set", "eval_period_steps=1000",
    "--set", "eval_steps=300", "--set", "checkpoint_period_steps=100",
    "--set", "replay_capacity=2000", "--set", "digest_period_steps=20",
    "--no-progress", "--device", "cpu", "--preset", "classic",  # not tuned/CartPole-v1
]  # fmt: skip
# Every part of the family at once, as Rainbow composes them: priorities, the noise
# generator and n-step windows must come back exactly too; its periodic evaluations draw
# their noise from the same generator (eval_noise = "sampled", as dqn_zoo evaluates).
RAINBOW_CARTPOLE = [
    *CARTPOLE, "--set", "target=double", "--set", "dueling=true", "--set", "noisy=true",
    "--set", "eval_noise=sampled",
    "--set", "distributional=c51", "--set", "n_step=3", "--set", "replay_sampling=prioritized",
    "--set", "optimizer=adam", "--set", "learning_rate=0.0005", "--set", "loss_reduction=mean",
    "--set", "max_gradient_norm=10", "--set", "epsilon_start=0", "--set", "epsilon_end=0",
    "--set", "mlp_hidden_sizes=[64, 64]", "--set", "distributional_atoms=11",  # CI's time
]  # fmt: skip
PONG = [
    "--env", "pong", "--steps", "700", "--seed", "3",
    "--set", "replay_start_steps=150", "--set", "replay_capacity=500",
    "--set", "eval_period_steps=350", "--set", "eval_steps=100",
    "--set", "checkpoint_period_steps=50", "--set", "replay_compression=lz4",
    "--set", "digest_period_steps=10", "--no-progress", "--device", "cpu",
]  # fmt: skip


def dqnlab(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "dqnlab", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def finish(process: subprocess.Popen[str]) -> tuple[int, str]:
    _, stderr = process.communicate(timeout=600)
    return process.returncode, stderr


def train_killed_and_resumed(
    args: list[str], reference: Path, resumed: Path, most_kills: int, latest_kill: float = 0.6
) -> int:
    """Train `args` into `reference` left alone, and into `resumed` SIGKILLed up to
    `most_kills` times, each at a random moment up to `latest_kill` seconds after a new
    checkpoint, then resumed; returns the kills (fewer when the run finished first).
    No resumed process may say it left the killed run's course (run/digests.py): where
    one does, the failure names the step."""
    code, stderr = finish(dqnlab("train", *args, "--run-dir", str(reference)))
    assert code == 0, stderr
    rng = random.Random(len(args))
    process = dqnlab("train", *args, "--run-dir", str(resumed))
    kills, last_step, said = 0, 0, []
    while kills < most_kills:
        if not wait_for_checkpoint(resumed, process, after=last_step):
            break  # the run finished before the next kill
        time.sleep(rng.uniform(0.0, latest_kill))
        process.send_signal(signal.SIGKILL)
        said.append(finish(process)[1])
        kills += 1
        last_step = CheckpointStore(resumed).steps()[-1]
        process = dqnlab("resume", str(resumed), "--no-progress", "--device", "cpu")
    code, stderr = finish(process)
    assert code == 0, stderr
    departed = [text for text in [*said, stderr] if "not retracing" in text]
    assert not departed, departed[0]
    return kills


def wait_for_checkpoint(run: Path, process: subprocess.Popen[str], after: int) -> bool:
    """Wait until a checkpoint newer than step `after` exists; False if the run ended."""
    store = CheckpointStore(run)
    while process.poll() is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            steps = store.steps()
        if steps and steps[-1] > after:
            return True
        time.sleep(0.05)
    return False


def final_state(run: Path, total_steps: int | None = None) -> tuple[dict, dict[str, np.ndarray]]:
    """The newest checkpoint, at `total_steps` (the run's config's by default: a run resumed
    with a new budget keeps its first one there), and its replay arrays."""
    config = load_run_config(run)
    learner_replay = ReplayMemory(
        config.replay_capacity, *_frame_layout(config), config.history_length, 32, 0
    )
    loaded = CheckpointStore(run).latest(config_fingerprint(config), into=learner_replay.arrays)
    assert loaded is not None and loaded.step == (total_steps or config.total_steps)
    return loaded.state, learner_replay.arrays


def _frame_layout(config) -> tuple[tuple[int, ...], np.dtype]:
    if config.env == "CartPole-v1":
        return (4,), np.dtype(np.float32)
    if config.env.endswith(":EzDrift"):
        return (2,), np.dtype(np.float32)
    if config.env.endswith(":NestedDictEnv"):
        return (32,), np.dtype(np.uint8)  # rows of the packed Dict (tests/envs/test_spaces.py)
    return (84, 84), np.dtype(np.uint8)


def assert_identical(a, b, where: str = "state") -> None:
    """Every key of two states equal, bit for bit; a failure names every key that differs
    (the first alone would not say whether the weights, the replay or the streams did)."""
    found = differences(a, b, where)
    assert not found, f"{len(found)} differ: " + ", ".join(found)


def differences(a, b, where: str = "state") -> list[str]:
    if isinstance(a, dict):
        if a.keys() != b.keys():
            return [f"{where} (keys)"]
        return [found for key in a for found in differences(a[key], b[key], f"{where}.{key}")]
    if isinstance(a, (list, tuple)):
        if len(a) != len(b):
            return [f"{where} (length)"]
        return [
            found
            for i, (x, y) in enumerate(zip(a, b, strict=True))
            for found in differences(x, y, f"{where}[{i}]")
        ]
    if isinstance(a, torch.Tensor):
        return [] if torch.equal(a, b) else [where]
    if isinstance(a, np.ndarray):
        return [] if np.array_equal(a, b) else [where]
    if where.endswith("env.env") and a is not None and b is not None:  # a pickled Gymnasium env
        env_a, env_b = pickle.loads(a).unwrapped, pickle.loads(b).unwrapped
        if hasattr(env_a, "state"):  # CartPole
            same = np.array_equal(env_a.state, env_b.state)
        else:  # the cue games of tests/envs/space_envs.py: every attribute of the game
            plain = (bool, int, float, str, type(None))
            held = {k: v for k, v in vars(env_a).items() if isinstance(v, plain)}
            same = (env_a.t, env_a.cue) == (env_b.t, env_b.cue) and held == {
                k: vars(env_b)[k] for k in held
            }
        same = same and env_a.np_random.bit_generator.state == env_b.np_random.bit_generator.state
        return [] if same else [where]
    return [] if a == b else [where]


def csv_rows(path: Path, drop: tuple[str, ...]) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return [{k: v for k, v in row.items() if k not in drop} for row in csv.DictReader(handle)]


def tensorboard_steps(run: Path) -> dict[str, list[int]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    return {tag: [event.step for event in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def assert_same_run(reference: Path, resumed: Path) -> None:
    state_a, replay_a = final_state(reference)
    state_b, replay_b = final_state(resumed)
    assert state_a["learner"]["heldout"] is not None  # Nature Fig. 2's set, compared below
    assert_identical(state_a["learner"], state_b["learner"], "learner")
    assert_identical(state_a["run"], state_b["run"], "run")
    assert_identical(replay_a, replay_b, "replay")
    timing = ("wall_seconds", "frames_per_second")
    for name in ("episodes.csv", "evaluations.csv"):
        assert csv_rows(reference / name, timing) == csv_rows(resumed / name, timing), name
    evaluations = csv_rows(resumed / "evaluations.csv", timing)
    assert evaluations and all(
        row["heldout_max_q"] and row["heldout_td_error"] for row in evaluations
    )
    logged = tensorboard_steps(resumed)
    assert logged == tensorboard_steps(reference) and "eval/mean_score" in logged
    assert (
        logged["eval/heldout_max_q"] == logged["eval/mean_score"] == logged["eval/heldout_td_error"]
    )
    for tag, steps in logged.items():
        assert steps == sorted(steps) and len(steps) == len(set(steps)), tag  # no duplicates


# A structured observation (a nested Dict packed into rows: envs/spaces.py) with a history
# of two across episode starts, through the multi_input network.
NESTED_DICT = [
    "--env", "tests.envs.space_envs:NestedDictEnv", *CARTPOLE[2:],
    "--set", "history_length=2", "--set", "mlp_hidden_sizes=[32]", "--steps", "1500",
    "--set", "eval_period_steps=500",
]  # fmt: skip

# An environment whose pickle keeps only its constructor's arguments (gymnasium's EzPickle,
# as LunarLander's): the checkpoint keeps its episode, replayed at resume.
EZPICKLE = ["--env", "tests.envs.replayed_envs:EzDrift", *CARTPOLE[2:]]


@pytest.mark.parametrize(
    "args",
    # Under the slow marker, for CI's time: the nested Dict space (tests/envs/
    # test_spaces_pipeline.py trains and resumes every space), the family's parts at once
    # (each part's state round-trips in tests/algorithm/: prioritized, n-step, noisy, the
    # optimizers) and the EzPickle environment (tests/envs/test_generic_resume.py).
    [
        CARTPOLE,
        pytest.param(RAINBOW_CARTPOLE, marks=pytest.mark.slow),
        PONG,
        pytest.param(EZPICKLE, marks=pytest.mark.slow),
        pytest.param(NESTED_DICT, marks=pytest.mark.slow),
    ],
    ids=["cartpole", "rainbow-cartpole", "pong", "ezpickle", "nested-dict"],
)
def test_sigkill_at_random_moments_then_resume_is_bit_identical(tmp_path: Path, args) -> None:
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    kills = train_killed_and_resumed(args, reference, resumed, most_kills=3)
    assert kills >= 2, "the run was too fast to be killed twice"
    assert_same_run(reference, resumed)


@pytest.mark.parametrize(
    ("stop", "status"),
    # One handler serves both signals: SIGTERM's exit status under the slow marker (CI's time).
    [pytest.param(signal.SIGTERM, 143, marks=pytest.mark.slow), (signal.SIGINT, 130)],
)
def test_a_stop_signal_checkpoints_and_says_how_to_resume(tmp_path: Path, stop, status) -> None:
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    code, stderr = finish(dqnlab("train", *CARTPOLE, "--run-dir", str(reference)))
    assert code == 0, stderr
    process = dqnlab("train", *CARTPOLE, "--run-dir", str(resumed))
    assert wait_for_checkpoint(resumed, process, after=0)
    process.send_signal(stop)
    code, stderr = finish(process)
    assert code == status, stderr
    assert f"resume with: dqnlab resume {resumed}" in stderr
    stopped_at = int(stderr.split(" at step ")[1].split()[0])
    assert CheckpointStore(resumed).steps()[-1] == stopped_at  # the step it finished
    # `train` with the same settings on the same directory carries on too.
    code, stderr = finish(dqnlab("train", *CARTPOLE, "--run-dir", str(resumed)))
    assert code == 0, stderr
    assert_same_run(reference, resumed)


# Slow (CI's time): the store's fallback is test_checkpoints.py's
# (test_damaged_checkpoint_is_skipped_for_the_previous_one); this is it end to end.
@pytest.mark.slow
def test_a_corrupted_newest_checkpoint_falls_back_to_the_previous_one(tmp_path: Path) -> None:
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    code, stderr = finish(dqnlab("train", *CARTPOLE, "--run-dir", str(reference)))
    assert code == 0, stderr
    process = dqnlab("train", *CARTPOLE, "--run-dir", str(resumed))
    assert wait_for_checkpoint(resumed, process, after=200)
    process.send_signal(signal.SIGKILL)
    process.wait()
    newest = sorted((resumed / "checkpoints").glob("step-*"))[-1]
    state = newest / "state.pt"
    data = bytearray(state.read_bytes())
    data[len(data) // 2] ^= 0xFF
    state.write_bytes(bytes(data))
    code, stderr = finish(dqnlab("resume", str(resumed), "--no-progress", "--device", "cpu"))
    assert code == 0, stderr
    assert f"skipping checkpoint {newest}" in stderr
    assert_same_run(reference, resumed)


def test_resume_refuses_another_configuration(tmp_path: Path) -> None:
    run = tmp_path / "run"
    short = [*CARTPOLE[:3], "400", *CARTPOLE[4:]]
    code, stderr = finish(dqnlab("train", *short, "--run-dir", str(run)))
    assert code == 0, stderr
    config_file = run / "config.toml"
    config_file.write_text(config_file.read_text().replace("discount = 0.99", "discount = 0.9"))
    code, stderr = finish(dqnlab("resume", str(run), "--no-progress"))
    assert code == 2 and "another configuration" in stderr and "Traceback" not in stderr


def test_an_atari_run_resumes_without_unpickling_anything(tmp_path: Path, monkeypatch) -> None:
    config = resolve_config(
        "classic", env="pong", total_steps=100, replay_start_steps=50, eval_period_steps=100,
        eval_steps=30, checkpoint_period_steps=50, replay_capacity=200,
    )  # fmt: skip
    run = tmp_path / "run"
    prepare_run_dir(run, force=False)
    train(config, run, torch.device("cpu"), progress=False, tensorboard=False)
    saved, saved_replay = final_state(run)
    learner = TrainingState(config, torch.device("cpu"))

    def refuse(*args, **kwargs):
        raise AssertionError("resuming an Atari run unpickled something")

    for name in ("load", "loads", "Unpickler"):  # all that torch.load(weights_only=False) uses
        monkeypatch.setattr(pickle, name, refuse)
    loaded = CheckpointStore(run).latest(config_fingerprint(config), into=learner.replay.arrays)
    assert loaded is not None
    learner.load_state_dict(loaded.state["learner"])
    monkeypatch.undo()
    assert_identical(learner.state_dict(), saved["learner"], "learner")
    assert_identical(learner.replay.arrays, saved_replay, "replay")


def pong_after(steps: int) -> AtariEnv:
    env = AtariEnv("pong", seed=3, training=True)
    env.reset()
    for step in range(steps):
        env.step(step % env.num_actions)
    return env


def play_on(env: AtariEnv) -> tuple[list, bytes]:
    """What 30 more steps return, with a reset (no-ops from the env's RNG) halfway, and the
    emulator state after them."""
    played: list = []
    for step in range(30):
        if step == 15:
            played.append(env.reset().copy())
        observation, *outcome = env.step(step % env.num_actions)
        played.append((observation.copy(), *outcome))
    return played, env.ale.cloneState(include_rng=True).serialize()


def test_an_emulator_state_pickled_by_an_earlier_checkpoint_resumes_exactly() -> None:
    env = pong_after(40)
    state = env.state_dict()
    earlier = {key: value for key, value in state.items() if key != "ale_state"}
    earlier["ale"] = pickle.dumps(ALEState(state["ale_state"]))  # the layout before ale_state
    expected = play_on(env)
    for saved in (state, earlier):
        resumed = AtariEnv("pong", seed=99, training=True)
        resumed.load_state_dict(saved)
        assert_identical(play_on(resumed), expected, "played")


def test_a_crafted_emulator_state_is_refused_without_running_it(tmp_path: Path) -> None:
    marker = tmp_path / "marker"
    state = pong_after(0).state_dict()
    earlier = {key: value for key, value in state.items() if key != "ale_state"}
    earlier["ale"] = pickle.dumps(RunsCode(marker))
    env = AtariEnv("pong", seed=3, training=True)
    with pytest.raises(EnvError, match="builtins.exec is not an emulator state"):
        env.load_state_dict(earlier)
    with pytest.raises(EnvError, match="emulator state cannot be restored"):
        env.load_state_dict({**state, "ale_state": b"not an emulator state"})
    assert not marker.exists()


def small_config(**overrides):
    values = {"total_steps": 400, "replay_start_steps": 50, "eval_period_steps": 100,
              "eval_steps": 50, "checkpoint_period_steps": 50, "replay_capacity": 1000}  # fmt: skip
    values.update(overrides)
    return resolve_config("classic", env="CartPole-v1", **values)


def test_nan_stops_training_and_keeps_the_last_good_checkpoint(tmp_path: Path, monkeypatch) -> None:
    run = tmp_path / "run"
    prepare_run_dir(run, force=False)
    original = TrainingState.advance

    def advance(self):
        if self.steps == 237:  # poison the weights during step 238
            with torch.no_grad():
                next(self.agent.online.parameters()).fill_(float("nan"))
        return original(self)

    monkeypatch.setattr(TrainingState, "advance", advance)
    with pytest.raises(TrainingDiverged, match="at step 238"):
        train(small_config(), run, torch.device("cpu"), progress=False, tensorboard=False)
    store = CheckpointStore(run)
    assert store.steps()[-1] == 200
    loaded = store.latest(config_fingerprint(small_config()))
    weights = loaded.state["learner"]["agent"]["online"]
    assert all(torch.isfinite(tensor).all() for tensor in weights.values())
    best = torch.load(run / "checkpoints" / "best.pt", weights_only=True)
    assert all(torch.isfinite(tensor).all() for tensor in best["network"].values())


def test_disk_full_while_checkpointing(tmp_path: Path, monkeypatch) -> None:
    import errno

    from dqnlab.run import checkpoint_files

    calls = 0
    original = checkpoint_files.write_buffer

    def failing(handle, data):
        nonlocal calls
        calls += 1
        if calls > 40:  # the first checkpoints succeed, then the disk is full
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return original(handle, data)

    monkeypatch.setattr(checkpoint_files, "write_buffer", failing)
    run = tmp_path / "stop"
    prepare_run_dir(run, force=False)
    with pytest.raises(DqnlabError, match="No space left on device"):
        train(small_config(), run, torch.device("cpu"), progress=False, tensorboard=False)
    kept = CheckpointStore(run).steps()
    assert kept and not list((run / "checkpoints").glob(".*"))  # no partial files left
    loaded = CheckpointStore(run).latest(config_fingerprint(small_config()))
    assert loaded.step == kept[-1]

    calls = 0
    run = tmp_path / "continue"
    prepare_run_dir(run, force=False)
    config = small_config(on_checkpoint_error="continue")
    result = train(config, run, torch.device("cpu"), progress=False, tensorboard=False)
    assert result.steps == 400  # went on despite the failed checkpoints


def test_refuses_at_start_when_the_disk_cannot_hold_the_checkpoints(
    tmp_path: Path, monkeypatch
) -> None:
    import shutil
    from collections import namedtuple

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 1000, 1000))
    run = tmp_path / "run"
    prepare_run_dir(run, force=False)
    with pytest.raises(ResourceError, match="GiB of disk"):
        train(small_config(), run, torch.device("cpu"), progress=False, tensorboard=False)
