"""Periodic evaluations in the background (`periodic_eval = "background"`): the results of
a worker process are those of the same seeded evaluations played in the training process,
each a function of the run and its step alone, and a run killed with evaluations in flight
resumes to the same evaluations and best network."""

from __future__ import annotations

import dataclasses
import os
import signal
from pathlib import Path

import gymnasium as gym
import pytest
import torch

from dqnlab.config import Config, config_fingerprint, resolve_config
from dqnlab.errors import ConfigError, DqnlabError
from dqnlab.run import rundir
from dqnlab.run.background_eval import BackgroundEvaluations, evaluate_snapshot, evaluation_seed
from dqnlab.run.checkpoints import CheckpointStore
from dqnlab.run.rundir import prepare_run_dir
from dqnlab.run.train import TrainingLoop, train
from tests.run.test_resume import assert_identical, csv_rows

CPU = torch.device("cpu")
TIMING = ("wall_seconds", "frames_per_second")


def cartpole(**changes: object) -> Config:
    """Evaluations at steps 1000, 2000 and 3000; checkpoints every 250 steps."""
    settings = dict(
        env="CartPole-v1", seed=5, total_steps=3000, replay_start_steps=300,
        eval_period_steps=1000, eval_steps=300, replay_capacity=2000,
        checkpoint_period_steps=250, eval_networks_kept="all", mlp_hidden_sizes=(32,),
        periodic_eval="background",
    )  # fmt: skip
    return resolve_config("classic", {**settings, **changes})


def trained(run: Path, config: Config) -> Path:
    prepare_run_dir(run, force=False)
    train(config, run, CPU, progress=False, tensorboard=False)
    return run


def final_checkpoint(run: Path, config: Config) -> dict:
    loaded = CheckpointStore(run).latest(config_fingerprint(config))
    assert loaded is not None and loaded.step == config.total_steps
    return loaded.state


def assert_same_evaluations(reference: Path, other: Path, config: Config) -> None:
    """The same evaluations.csv (but timings), best network, kept networks and final state."""
    rows = csv_rows(reference / "evaluations.csv", TIMING)
    assert [int(row["step"]) for row in rows] == [1000, 2000, 3000]
    assert csv_rows(other / "evaluations.csv", TIMING) == rows
    for name in ("best", "worst", *(f"eval-{row['step']}" for row in rows)):
        path = (
            rundir.eval_network_path(reference, int(name[5:]))
            if name.startswith("eval-")
            else rundir.network_path(reference, name)
        )
        mine = rundir.load_network(path)
        theirs = rundir.load_network(other / path.relative_to(reference))
        assert (mine["step"], mine["eval_mean"]) == (theirs["step"], theirs["eval_mean"]), name
        assert_identical(mine["network"], theirs["network"], name)
    saved, saved_other = final_checkpoint(reference, config), final_checkpoint(other, config)
    assert saved["pending_evaluations"] == saved_other["pending_evaluations"] == []
    assert_identical(saved["run"], saved_other["run"], "run")
    # The inline evaluation's environment is unused (never reset, so never seeded).
    learner, learner_other = saved["learner"], saved_other["learner"]
    del learner["eval_env"], learner_other["eval_env"]
    assert_identical(learner, learner_other, "learner")


def test_a_worker_process_gives_the_evaluations_played_in_the_training_process(
    tmp_path: Path,
) -> None:
    config = cartpole()
    background = trained(tmp_path / "worker", config)
    here = trained(tmp_path / "here", dataclasses.replace(config, periodic_eval_workers=0))
    assert_same_evaluations(background, here, config)
    # Each row is the seeded evaluation of the network at its step: the last one is the
    # network training ended with, and playing each kept network again gives its row.
    last = rundir.load_network(rundir.network_path(background, "last"))
    assert_identical(rundir.load_network(rundir.eval_network_path(background, 3000))["network"],
                     last["network"])  # fmt: skip
    for row in csv_rows(background / "evaluations.csv", TIMING):
        step = int(row["step"])
        payload = rundir.load_network(rundir.eval_network_path(background, step))
        result = evaluate_snapshot(payload, evaluation_seed(config.seed, step))
        assert (str(result.mean), len(result.scores), result.steps) == (
            row["mean"], int(row["episodes"]), int(row["steps"]),
        )  # fmt: skip
    # Training does not share a generator with the evaluations any more: an inline run
    # learns from other draws.
    inline = trained(tmp_path / "inline", dataclasses.replace(config, periodic_eval="inline"))
    assert csv_rows(inline / "evaluations.csv", TIMING) != csv_rows(
        background / "evaluations.csv", TIMING
    )


def test_a_run_killed_with_evaluations_in_flight_resumes_to_the_same_ones(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = cartpole()
    reference = trained(tmp_path / "reference", config)
    run = tmp_path / "run"
    prepare_run_dir(run, force=False)

    # 1. No result comes back, and a stop request follows the second evaluation: the
    # stop's checkpoint holds both as pending.
    submit = BackgroundEvaluations._submit

    def submit_then_stop(self: BackgroundEvaluations, evaluation) -> None:  # noqa: ANN001
        submit(self, evaluation)
        if evaluation.step == 2000:
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(BackgroundEvaluations, "_submit", submit_then_stop)
    monkeypatch.setattr(BackgroundEvaluations, "record_done", lambda self, timeout=0.0: None)
    result = TrainingLoop(config, run, CPU, False, False, resume=False).run()
    assert result.interrupted == "SIGTERM" and result.steps == 2000
    loaded = CheckpointStore(run).latest(config_fingerprint(config))
    assert loaded is not None and loaded.step == 2000
    assert [p["step"] for p in loaded.state["pending_evaluations"]] == [1000, 2000]
    assert loaded.state["run"]["evaluations"] == []
    monkeypatch.undo()

    # 2. Resumed with the evaluations played in the training process (a setting a resume
    # may change): both are recorded (rows, best network), then the process dies before
    # its next checkpoint.
    def die(self: TrainingLoop, step: int) -> None:
        raise RuntimeError("killed")

    monkeypatch.setattr(TrainingLoop, "_checkpoint", die)
    here = dataclasses.replace(config, periodic_eval_workers=0)
    with pytest.raises(RuntimeError, match="killed"):
        TrainingLoop(here, run, CPU, False, False, resume=True).run()
    assert [row["step"] for row in csv_rows(run / "evaluations.csv", TIMING)] == ["1000", "2000"]
    assert rundir.network_path(run, "best").exists()
    monkeypatch.undo()

    # 3. Resumed again, to the end: what the uninterrupted run has, rows not repeated.
    train(config, run, CPU, progress=False, tensorboard=False, resume=True)
    assert_same_evaluations(reference, run, config)


def test_a_stop_while_waiting_at_the_end_leaves_them_to_the_resume(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = cartpole(total_steps=1000)
    run = tmp_path / "run"
    prepare_run_dir(run, force=False)

    def stopped(self: BackgroundEvaluations, is_stopped) -> bool:  # noqa: ANN001
        os.kill(os.getpid(), signal.SIGINT)
        return record_all(self, is_stopped)

    record_all = BackgroundEvaluations.record_all
    monkeypatch.setattr(BackgroundEvaluations, "record_done", lambda self, timeout=0.0: None)
    monkeypatch.setattr(BackgroundEvaluations, "record_all", stopped)
    result = TrainingLoop(config, run, CPU, False, False, resume=False).run()
    assert result.interrupted == "SIGINT" and result.evaluations == []
    monkeypatch.undo()
    result = TrainingLoop(config, run, CPU, False, False, resume=True).run()
    assert result.interrupted is None and [s for s, _ in result.evaluations] == [1000]
    assert final_checkpoint(run, config)["pending_evaluations"] == []


def test_a_worker_that_cannot_build_the_environment_says_so_at_the_start(tmp_path: Path) -> None:
    gym.register("OnlyInThisProcess-v0", entry_point="tests.helpers:BlinkEnv")
    try:
        config = cartpole(env="OnlyInThisProcess-v0")
        prepare_run_dir(tmp_path / "run", force=False)
        with pytest.raises(DqnlabError) as error:
            TrainingLoop(config, tmp_path / "run", CPU, False, False, resume=False)
    finally:
        gym.registry.pop("OnlyInThisProcess-v0")
    message = str(error.value)
    assert message.startswith("periodic_eval = 'background': evaluation worker 0 failed in its")
    assert "OnlyInThisProcess" in message and "\n" not in message


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"periodic_eval": "sometimes"}, "periodic_eval = 'sometimes' is not one of: inline, "),
        ({"periodic_eval_workers": -1}, "periodic_eval_workers = -1 must be zero or more"),
        (
            {"periodic_eval": "inline", "periodic_eval_workers": 2},
            "periodic_eval_workers = 2 is for periodic_eval = 'background'",
        ),
        ({"logger": "tensorboard+wandb"}, "periodic_eval = 'background' logs each evaluation"),
    ],
)
def test_bad_settings_say_which(changes: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message) as error:
        cartpole(**changes)
    assert "\n" not in str(error.value)
