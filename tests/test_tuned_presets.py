"""Tuned settings per environment id (presets/tuned/ID.toml): chosen by `train` when the id
matches, as rl-baselines3-zoo picks its hyperparameters by id, and named in the run's
config.toml; each file says how it was found and what it scored."""

from __future__ import annotations

from pathlib import Path

import pytest
import tomllib

from dqnlab.config import (
    config_from_dict,
    load_preset,
    preset_names,
    preset_text,
    resolve_config,
    tuned_envs,
    tuned_preset,
)
from dqnlab.envs import default_preset
from dqnlab.errors import ConfigError
from tests.helpers import dqnlab

# The tasks issue 33 names; each ships the settings `dqnlab tune` found for it.
COMMON_TASKS = ("CartPole-v1", "Acrobot-v1", "MountainCar-v0", "LunarLander-v3")
SHIPPED = tuned_envs()
NONE_YET = pytest.mark.skipif(not SHIPPED, reason="no tuned settings shipped yet")


def test_default_preset_by_environment() -> None:
    assert default_preset("pong") == "nature"
    assert default_preset("FrozenLake-v1") == "classic"  # no tuned settings for it
    for env in SHIPPED:
        assert default_preset(env) == tuned_preset(env) == f"tuned/{env}"
    assert tuned_preset("CartPole-v0") is None  # the id must match exactly, version too


def test_the_tuned_presets_are_listed_with_the_others() -> None:
    assert set(SHIPPED) <= set(COMMON_TASKS)
    assert [f"tuned/{env}" for env in SHIPPED] == [n for n in preset_names() if "/" in n]


@pytest.mark.parametrize("env", SHIPPED)
def test_a_tuned_preset_resolves_and_names_how_it_was_found(env: str) -> None:
    config = resolve_config(f"tuned/{env}", env=env)
    assert config.preset == f"tuned/{env}"
    header = "\n".join(
        line for line in preset_text(f"tuned/{env}").splitlines() if line.startswith("#")
    )
    # The study that found it, the seeds that verified it, and the published score it is
    # held against.
    assert f"dqnlab tune --env {env}" in header
    assert "5 seeds" in header
    assert "rl-baselines3-zoo" in header
    assert "env" not in load_preset(f"tuned/{env}")  # the environment is the command's


def test_the_preset_is_recorded_and_cannot_be_set() -> None:
    assert resolve_config("classic", env="CartPole-v1").preset == "classic"
    with pytest.raises(ConfigError, match="choose it with --preset"):
        resolve_config("classic", {"preset": "nature"}, env="CartPole-v1")
    # A run saved before the record existed loads with an empty one.
    saved = resolve_config("classic", env="CartPole-v1").to_dict()
    del saved["preset"]
    assert config_from_dict(saved).preset == ""


@NONE_YET
def test_train_chooses_the_tuned_settings_by_id_and_records_them(tmp_path: Path) -> None:
    env = SHIPPED[0]
    runs = {"tuned": [], "classic": ["--preset", "classic"]}
    for name, args in runs.items():
        run = tmp_path / name
        trained = dqnlab(
            "train", "--env", env, *args, "--steps", "300", "--run-dir", str(run),
            "--set", "replay_start_steps=100", "--set", "eval_period_steps=300",
            "--set", "eval_steps=100", "--no-progress",
        )  # fmt: skip
        assert trained.returncode == 0, trained.stderr
        recorded = tomllib.loads((run / "config.toml").read_text())["preset"]
        assert recorded == (f"tuned/{env}" if name == "tuned" else "classic")
        assert f"with preset {recorded} " in trained.stdout
