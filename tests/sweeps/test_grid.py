"""A sweep's grid: games × settings × seeds, named and resolved before anything starts."""

from __future__ import annotations

from pathlib import Path

from dqnlab.sweeps.grid import game_set, parse_variation, plan_grid


def test_grid_is_games_times_settings_times_seeds(tmp_path: Path) -> None:
    sweep = plan_grid(
        ["pong", "breakout"],
        [parse_variation("optimizer+learning_rate=rmsprop+0.00025,adam+0.0001")],
        preset=None, overrides={"replay_capacity": 1000}, seeds=2, first_seed=0, steps=500,
        sweep_dir=tmp_path,
    )  # fmt: skip
    assert len(sweep.runs) == 8
    assert sweep.runs[0].name == "pong-optimizer=rmsprop,learning_rate=0.00025-s0"
    assert {run.config.env for run in sweep.runs} == {"pong", "breakout"}
    assert sweep.preset == "nature" and all(
        run.config.replay_capacity == 1000 for run in sweep.runs
    )
    plain = plan_grid(["CartPole-v1"], [], preset=None, overrides={}, seeds=2, first_seed=3,
                      steps=None, sweep_dir=tmp_path)  # fmt: skip
    assert [run.name for run in plain.runs] == ["CartPole-v1-s3", "CartPole-v1-s4"]


def test_game_sets() -> None:
    nature = game_set("nature49")
    assert len(nature) == 49 and "pong" in nature and "surround" not in nature
    assert len(game_set("atari57")) == 57
    atari100k = game_set("atari100k")  # Kaiser et al. 2019, Table 1's 26 games
    assert len(atari100k) == 26 and {"road_runner", "up_n_down", "private_eye"} <= set(atari100k)
    assert not {"montezuma_revenge", "enduro", "space_invaders"} & set(atari100k)
