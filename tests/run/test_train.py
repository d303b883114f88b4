"""The training loop: when updates and target copies happen, what a run directory holds."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import torch

from dqnlab.algorithm.agent import Agent
from dqnlab.config import resolve_config
from dqnlab.run import rundir
from dqnlab.run.checkpoints import CheckpointStore
from dqnlab.run.rundir import (
    eval_network_path,
    keep_evaluated_network,
    load_run_config,
    prepare_run_dir,
)
from dqnlab.run.train import STOPPED_BY_HOOK, train


def test_update_and_target_copy_timing(tmp_path: Path, monkeypatch) -> None:
    steps_taken = 0
    update_steps: list[int] = []
    sync_steps: list[int] = []
    original_act, original_update = Agent.act, Agent.update

    def act(self, observation, epsilon, training=False):
        nonlocal steps_taken
        steps_taken += 1
        return original_act(self, observation, epsilon, training)

    def update(self, batch):
        update_steps.append(steps_taken)
        return original_update(self, batch)

    monkeypatch.setattr(Agent, "act", act)
    monkeypatch.setattr(Agent, "update", update)
    monkeypatch.setattr(Agent, "sync_target", lambda self: sync_steps.append(steps_taken))
    config = resolve_config(
        "classic", env="CartPole-v1", total_steps=200, replay_start_steps=100,
        update_period_steps=4, target_update_steps=40, eval_period_steps=1000,
    )  # fmt: skip
    prepare_run_dir(tmp_path / "run", force=False)
    train(config, tmp_path / "run", torch.device("cpu"), progress=False, tensorboard=False)
    # Learning starts after replay start, every 4th step: 104, 108, ..., 200.
    assert update_steps == list(range(104, 201, 4))
    # Copies every 40 agent steps, counted from the first step, as Lua's target_q.
    assert sync_steps == [40, 80, 120, 160, 200]


def test_run_directory_contents(tmp_path: Path) -> None:
    run = tmp_path / "run"
    config = resolve_config(
        "classic", env="CartPole-v1", total_steps=1200, replay_start_steps=200,
        eval_period_steps=400, eval_steps=300, seed=3, eval_networks_kept="all",
    )  # fmt: skip
    prepare_run_dir(run, force=False)
    result = train(config, run, torch.device("cpu"), progress=False)
    assert load_run_config(run) == config  # the resolved config is saved and reads back
    with (run / "evaluations.csv").open() as handle:
        evaluations = list(csv.DictReader(handle))
    assert [int(row["step"]) for row in evaluations] == [400, 800, 1200]
    best = max(float(row["mean"]) for row in evaluations)
    assert result.best_eval_mean == best
    assert float(evaluations[-1]["best_mean"]) == best
    with (run / "episodes.csv").open() as handle:
        episodes = list(csv.DictReader(handle))
    assert sum(int(row["steps"]) for row in episodes) <= 1200
    assert all(float(row["score"]) == int(row["steps"]) for row in episodes)  # +1 per step
    saved = rundir.load_network(run / "checkpoints" / "best.pt")
    assert saved["eval_mean"] == best and saved["config"]["seed"] == 3
    assert int(saved["step"]) in (400, 800, 1200)
    last = rundir.load_network(run / "checkpoints" / "last.pt")
    assert last["step"] == 1200 and "network" in last
    # The whole training state at every evaluation, the last two kept.
    assert CheckpointStore(run).steps() == [800, 1200]
    assert any((run / "tensorboard").iterdir())
    # The network of every evaluation is kept (eval_networks_kept = "all"), and worst.pt.
    for row in evaluations:
        kept = rundir.load_network(eval_network_path(run, int(row["step"])))
        assert kept["step"] == int(row["step"]) and kept["eval_mean"] == float(row["mean"])
    means = [(float(row["mean"]), int(row["step"])) for row in evaluations]
    worst_mean = min(mean for mean, _ in means)
    worst_step = max(step for mean, step in means if mean == worst_mean)  # ties: the later
    worst = rundir.load_network(run / "checkpoints" / "worst.pt")
    assert (worst["eval_mean"], worst["step"]) == (worst_mean, worst_step)
    assert not math.isnan(result.best_eval_mean)


def test_worst_network_is_chosen_after_the_first_quarter(tmp_path: Path) -> None:
    config = resolve_config("classic", env="CartPole-v1", total_steps=1000,
                            eval_networks_kept="best_and_worst")  # fmt: skip
    worst = tmp_path / "checkpoints" / "worst.pt"
    history: list[tuple[int, float]] = []
    for step, mean in [(100, 5.0), (250, 50.0), (500, 80.0), (750, 20.0), (1000, 20.0)]:
        keep_evaluated_network(tmp_path, config, history, step, mean, {"step": step})
        history.append((step, mean))
        if step == 100:  # before the quarter: the early, untrained network never counts
            assert not worst.exists()
    assert rundir.load_network(worst)["step"] == 1000  # 20.0 at 750 and 1000: the later
    assert not (tmp_path / "checkpoints" / "evals").exists()  # only best and worst kept


def test_replay_frames_on_the_device_train_and_resume_the_same(tmp_path: Path) -> None:
    """replay_storage = device (the GPU's code path, here with the CPU as the device)
    learns exactly what host memory learns, also across a resume, which must copy the
    loaded frames to the device."""
    settings = {
        "env": "breakout", "replay_start_steps": 100, "replay_capacity": 500, "batch_size": 8,
        "eval_period_steps": 150, "eval_steps": 50, "checkpoints_kept": 1,
    }  # fmt: skip

    def weights(run: str, storage: str, steps: list[int]) -> list[torch.Tensor]:
        for n, total in enumerate(steps):
            config = resolve_config("nature", replay_storage=storage, total_steps=total, **settings)
            if n == 0:
                prepare_run_dir(tmp_path / run, force=False)
            train(config, tmp_path / run, torch.device("cpu"), progress=False,
                  tensorboard=False, resume=n > 0)  # fmt: skip
        return list(
            rundir.load_network(tmp_path / run / "checkpoints" / "last.pt")["network"].values()
        )

    def same(a: list[torch.Tensor], b: list[torch.Tensor]) -> bool:
        return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))

    host = weights("host", "host", [600])
    assert not same(host, weights("short", "host", [450]))  # the last steps change them
    assert same(host, weights("device", "device", [600]))
    assert same(host, weights("resumed", "device", [300, 600]))


def test_a_stop_request_delivered_twice_is_one_request(monkeypatch) -> None:  # noqa: ANN001
    """SIGTERM to a process group that a parent also forwards (`timeout make train`) arrives
    twice at once: still a stop after a checkpoint; a second request a second later stops
    at once."""
    import os
    import signal

    from dqnlab.run.train import StopRequests

    clock = [100.0]
    monkeypatch.setattr("dqnlab.run.train.time.monotonic", lambda: clock[0])
    with StopRequests() as requests:
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGTERM)
        assert requests.signal_name == "SIGTERM"
        clock[0] += StopRequests.SAME_REQUEST_SECONDS
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)


def test_the_training_hook_stops_a_real_run_after_a_checkpoint(tmp_path: Path) -> None:
    config = resolve_config(
        "classic",
        env="CartPole-v1",
        total_steps=300,
        eval_period_steps=100,
        eval_steps=50,
        replay_start_steps=50,
        heldout_transitions=50,
    )
    prepare_run_dir(tmp_path / "run", force=False)
    told: list[tuple[int, float]] = []
    result = train(
        config,
        tmp_path / "run",
        torch.device("cpu"),
        progress=False,
        tensorboard=False,
        on_evaluation=lambda step, mean: told.append((step, mean)) or step >= 200,
    )
    assert [step for step, _ in told] == [100, 200] and result.steps == 200
    assert result.interrupted == STOPPED_BY_HOOK
