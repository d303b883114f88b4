"""`dqnlab bench --num-envs`: one set of figures per number of environments."""

from __future__ import annotations

import pytest
import torch

from dqnlab.bench.vector import measure_num_envs, parse_concurrency, parse_counts
from dqnlab.errors import ConfigError


def test_each_count_gets_its_training_figures() -> None:
    figures = measure_num_envs(
        [2, 1], env="pong", steps=12, replay_capacity=600, device=torch.device("cpu"), rounds=1
    )
    for count in (1, 2):
        assert figures[f"num_envs_{count}_train_frames_per_second"] > 0
        assert len(figures[f"num_envs_{count}_train_frames_per_second_runs"]) == 1
        assert 0 <= figures[f"num_envs_{count}_share_env"] <= 1
    assert figures["num_envs_1_ratio_vs_1"] == 1.0


def test_bad_counts_are_refused_in_one_line() -> None:
    assert parse_counts("1, 2,8") == [1, 2, 8]
    for text in ("0,2", "two", ""):
        with pytest.raises(ConfigError, match="--num-envs"):
            parse_counts(text)


def test_actor_learner_rows_come_beside_the_sequential_ones() -> None:
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


def test_bad_concurrency_lists_are_refused_in_one_line() -> None:
    assert parse_concurrency("none, actor-learner,") == ["none", "actor-learner"]
    for text in ("threads", "", "none,threads"):
        with pytest.raises(ConfigError, match="--concurrency"):
            parse_concurrency(text)
