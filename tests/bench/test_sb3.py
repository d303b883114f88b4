"""The Stable-Baselines3 peer is built with the Nature hyperparameters and gives its figures."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("stable_baselines3")

from stable_baselines3.common.type_aliases import TrainFreq, TrainFrequencyUnit  # noqa: E402

from dqnlab.bench.sb3 import (  # noqa: E402
    atari_env_id,
    make_sb3_dqn,
    peer_available,
    replay_bytes_per_transition,
    run_sb3_dqn,
)
from dqnlab.errors import EnvError  # noqa: E402


def test_atari_env_ids() -> None:
    assert atari_env_id("breakout") == "ALE/Breakout-v5"
    assert atari_env_id("space_invaders") == "ALE/SpaceInvaders-v5"
    assert peer_available()


def test_unknown_game_is_a_clear_error() -> None:
    with pytest.raises(EnvError, match="no_such_game"):
        make_sb3_dqn("no_such_game", total_steps=10, learning_starts=5, buffer_size=10)


def test_the_nature_hyperparameters_reach_the_model() -> None:
    model = make_sb3_dqn("breakout", total_steps=400, learning_starts=200, buffer_size=300)
    try:
        assert model.learning_rate == 0.00025
        assert model.gamma == 0.99
        assert model.batch_size == 32
        assert model.train_freq == TrainFreq(4, TrainFrequencyUnit.STEP)
        assert model.gradient_steps == 1
        assert model.target_update_interval == 10_000
        assert model.learning_starts == 200 and model.buffer_size == 300
        # The anneal spans 1M steps of the 400 given to learn(): 1.0 -> 0.1.
        assert model.exploration_schedule(1.0) == 1.0
        assert model.exploration_schedule(1 - 500_000 / 400) == pytest.approx(0.55)
        assert model.exploration_schedule(1 - 1_000_000 / 400) == pytest.approx(0.1)
        optimizer = model.policy.optimizer
        assert isinstance(optimizer, torch.optim.RMSprop)
        assert optimizer.defaults["lr"] == 0.00025
        assert optimizer.defaults["alpha"] == 0.95
        assert optimizer.defaults["eps"] == 0.01
        assert optimizer.defaults["centered"] is True
        # Stacked 4x84x84 uint8 frames, stored twice (obs and next obs), plus a few scalars.
        assert model.observation_space.shape == (4, 84, 84)
        assert 2 * 4 * 84 * 84 < replay_bytes_per_transition(model) < 2 * 4 * 84 * 84 + 64
    finally:
        env = model.get_env()
        assert env is not None
        env.close()


def test_throughput_figures_after_replay_start() -> None:
    figures = run_sb3_dqn("breakout", steps=200, learning_starts=200, buffer_size=300)
    assert figures["peer"] == "stable-baselines3" and figures["peer_version"]
    assert figures["peer_train_frames_per_second"] > 0
    assert figures["peer_steps"] == 200
    assert figures["peer_learning_starts"] == 200 and figures["peer_buffer_size"] == 300
    settings = figures["peer_settings"]
    assert settings["updates"] == 200 // 4  # an update every 4 steps, none during replay start
    assert settings["optimizer"] == "RMSprop" and settings["max_grad_norm"] == 10
    assert settings["exploration_decay_steps"] == 1_000_000
    assert settings["process_cpu_cores"] > 0 and "other_processes_cpu_cores" in settings
    assert settings["env_kwargs"] == {"frameskip": 1, "repeat_action_probability": 0.0}
