"""`dqnlab bench envs`: one set of figures per number of environments."""

from __future__ import annotations

from typing import Any

import pytest
import torch

from dqnlab.bench import flops, peers, vector
from dqnlab.bench.measure import measure_training
from dqnlab.bench.table import format_table
from dqnlab.bench.vector import measure_num_envs, parse_concurrency, parse_counts
from dqnlab.errors import ConfigError


@pytest.fixture(autouse=True)
def small_matmul(monkeypatch: pytest.MonkeyPatch) -> None:
    # A small matrix multiply and update replay: their sizes are parameters, not tested.
    monkeypatch.setattr(flops, "MATMUL_SIZE", 256)
    monkeypatch.setattr(vector, "UPDATE_REPLAY_SLOTS", 300)


def test_each_count_gets_its_training_figures() -> None:
    figures = measure_num_envs(
        [2, 1], env="pong", steps=12, replay_capacity=600, device=torch.device("cpu"), rounds=1
    )
    for count in (1, 2):
        assert figures[f"num_envs_{count}_train_frames_per_second"] > 0
        assert len(figures[f"num_envs_{count}_train_frames_per_second_runs"]) == 1
        assert 0 <= figures[f"num_envs_{count}_share_env"] <= 1
    assert figures["num_envs_1_ratio_vs_1"] == 1.0
    # The update against the matrix multiply, timed in the same command (Pong: 6 actions).
    assert figures["update_gflop"] == pytest.approx(32 * (4 * 18_692_096 - 6_553_600) / 1e9)
    achieved = figures["update_gflop"] / (figures["update_ms"] / 1e3)
    assert figures["update_fraction_of_matmul"] == pytest.approx(
        achieved / figures["matmul_gflop_per_s"]
    )
    assert "num_envs_1_ratio_vs_sb3" not in figures  # no peers asked for


def test_the_peers_take_turns_and_every_row_gets_its_ratio_to_them(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls: list[tuple[Any, ...]] = []

    def fake_sb3(*args: Any, **kwargs: Any) -> dict[str, Any]:
        calls.append(args)
        return {"peer": "stable-baselines3", "peer_version": "9.9",
                "peer_train_frames_per_second": 100.0 * len(calls)}  # fmt: skip

    monkeypatch.setattr(peers, "run_sb3_dqn", fake_sb3)
    figures = measure_num_envs(
        [1, 2], env="pong", steps=8, replay_capacity=600, device=torch.device("cpu"),
        rounds=2, peers=True,
    )  # fmt: skip
    assert len(calls) == 2  # once per round
    assert figures["sb3_train_frames_per_second_runs"] == [100.0, 200.0]
    assert figures["sb3_train_frames_per_second"] == 150.0
    for count in (1, 2):
        ours = figures[f"num_envs_{count}_train_frames_per_second"]
        assert figures[f"num_envs_{count}_ratio_vs_sb3"] == pytest.approx(ours / 150.0)
    table = format_table(figures)
    assert "| Stable-Baselines3 9.9 | 150.0 | 100.0, 200.0 | | |" in table
    assert "| dqnlab, num_envs 2 |" in table
    ratio = figures["num_envs_1_ratio_vs_sb3"]
    verdict = "met" if ratio >= 1.8 else "NOT met"
    assert f"against SB3: {ratio:.2f}× (target ≥ 1.8×: {verdict})" in table
    assert "CleanRL" not in table


def test_bad_counts_are_refused_in_one_line() -> None:
    assert parse_counts("1, 2,8") == [1, 2, 8]
    for text in ("0,2", "two", ""):
        with pytest.raises(ConfigError, match="--num-envs"):
            parse_counts(text)


def test_actor_learner_rows_come_beside_the_sequential_ones(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    measured_with: list[tuple[str, int]] = []  # (the state's class, threads while timed)

    def timed(state: Any, steps: int) -> tuple[float, dict[str, float]]:
        measured_with.append((type(state).__name__, torch.get_num_threads()))
        return measure_training(state, steps)

    monkeypatch.setattr(vector, "measure_training", timed)
    threads = torch.get_num_threads()
    figures = measure_num_envs(  # 10 steps: the actor's rounds of 3 are timed whole
        [1, 3], env="pong", steps=10, replay_capacity=600, device=torch.device("cpu"),
        rounds=1, concurrency=("none", "actor-learner"),
    )  # fmt: skip
    for count in (1, 3):
        for key in (f"num_envs_{count}", f"num_envs_{count}_actor_learner"):
            assert figures[f"{key}_train_frames_per_second"] > 0
            assert 0 <= figures[f"{key}_share_update"] <= 1
        assert 0 <= figures[f"num_envs_{count}_actor_learner_share_learner_waiting"] <= 1
    assert "num_envs_1_share_learner_waiting" not in figures
    # Each row ran with its own threads: an actor thread's state sets the process's
    # PyTorch threads one lower for its learner, which the sequential rows must not inherit.
    learner = max(1, threads - 1)
    expected = {"TrainingState": threads, "ActorLearnerState": learner}
    warm_ups, timed_rows = measured_with[:4], measured_with[4:]
    # (An actor thread's state sets its learner's threads at its first round, within the
    # warm-up; the next state's warm-up must start with all of them again.)
    assert [count for _, count in warm_ups] == [threads] * 4
    assert [count for _, count in timed_rows] == [expected[kind] for kind, _ in timed_rows]
    for count in (1, 3):
        assert figures[f"num_envs_{count}_threads"] == threads
        assert figures[f"num_envs_{count}_actor_learner_threads"] == learner
    assert torch.get_num_threads() == threads


def test_bad_concurrency_lists_are_refused_in_one_line() -> None:
    assert parse_concurrency("none, actor-learner,") == ["none", "actor-learner"]
    for text in ("threads", "", "none,threads"):
        with pytest.raises(ConfigError, match="--concurrency"):
            parse_concurrency(text)


def test_the_table_says_which_targets_are_met() -> None:
    figures: dict[str, Any] = {
        "env": "breakout", "steps": 1000, "rounds": 2, "threads": 2, "load_average_1min": 0.1,
        "num_envs_1_train_frames_per_second": 900.0,
        "num_envs_1_train_frames_per_second_runs": [880.0, 920.0],
        "num_envs_1_ratio_vs_1": 1.0, "num_envs_1_ratio_vs_cleanrl": 1.5,
        "num_envs_8_actor_learner_train_frames_per_second": 1200.0,
        "num_envs_8_actor_learner_train_frames_per_second_runs": [1200.0, 1200.0],
        "num_envs_8_actor_learner_ratio_vs_1": 4 / 3,
        "num_envs_8_actor_learner_ratio_vs_cleanrl": 2.0,
        "cleanrl_train_frames_per_second": 600.0,
        "cleanrl_train_frames_per_second_runs": [600.0, 600.0],
        "cleanrl_commit": "fe8d8a03abcdef",
        "update_ms": 10.0, "update_gflop_per_s": 218.0, "matmul_size": 2048,
        "matmul_threads": 2, "matmul_gflop_per_s": 250.0, "update_fraction_of_matmul": 0.872,
        "checkpoint_steps": 25_000, "checkpoint_target_bytes": 250_000_000,
        "checkpoint_target_seconds": 5.0,
        "checkpoint_stop_seconds_lz4": 1.5, "checkpoint_stop_bytes_lz4": 30_000_000,
        "checkpoint_stop_within_targets_lz4": True,
        "checkpoint_stop_seconds_none": 6.0, "checkpoint_stop_bytes_none": 190_000_000,
        "checkpoint_stop_within_targets_none": False,
    }  # fmt: skip
    lines = format_table(figures).splitlines()
    assert "| run | frames/s | rounds | × num_envs 1 | × CleanRL |" in lines  # no SB3 column
    assert "| dqnlab, num_envs 8, actor-learner | 1200.0 | 1200.0, 1200.0 | 1.33 | 2.00 |" in lines
    assert "| CleanRL dqn_atari.py @ fe8d8a03 | 600.0 | 600.0, 600.0 | | |" in lines
    assert "- exact loop (num_envs 1) against CleanRL: 1.50× (target ≥ 1.8×: NOT met)" in lines
    assert not any("against SB3" in line for line in lines)
    assert lines[-3].endswith("fraction 0.872 (target ≥ 0.75: met)")
    assert lines[-2] == (
        "- stop checkpoint after 25,000 steps (replay_compression = none): 190.0 MB in 6.00 s "
        "(targets ≤ 250 MB and ≤ 5 s: NOT met)"
    )
    assert lines[-1].endswith("30.0 MB in 1.50 s (targets ≤ 250 MB and ≤ 5 s: met)")
