"""`dqnlab bench small`: every small network's update figures and the classic preset's
training figures are produced, SB3 is given the classic preset's settings under its own
names, and the subcommand writes its JSON (the mechanism, not the speeds)."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from dqnlab.bench import peers, small
from dqnlab.bench.sb3 import peer_available
from dqnlab.bench.small import (
    measure_small_networks,
    sb3_dqn_kwargs,
    small_networks,
    training_against_sb3,
)
from dqnlab.cli import app
from dqnlab.config import Config, resolve_config
from dqnlab.errors import ConfigError

CPU = torch.device("cpu")
needs_sb3 = pytest.mark.skipif(not peer_available(), reason="Stable-Baselines3 not installed")


def _classic() -> Config:
    return resolve_config("classic", env="CartPole-v1")


def test_every_small_networks_figures_and_the_classic_training() -> None:
    figures = measure_small_networks(steps=200, rounds=1, device=CPU, update_repeats=2)
    for name in ("mlp", "small_cnn", "der_cnn"):
        for figure in ("update_ms", "updates_per_second", "dense_ms", "update_over_dense"):
            assert figures[f"{name}_{figure}"] > 0, (name, figure)
        assert figures[f"{name}_updates_per_second"] == pytest.approx(
            1e3 / figures[f"{name}_update_ms"]
        )
        assert figures[f"{name}_parameters"] > 0
    assert figures["mlp_input"] == "1 x 4 float32" and figures["mlp_batch_size"] == 64
    assert figures["small_cnn_input"] == "1 x 10x10x4 bool"
    assert figures["der_cnn_input"] == "4 x 84x84 uint8" and figures["der_cnn_preset"] == "der"
    assert figures["classic_train_steps_per_second"] > 0
    assert len(figures["classic_train_steps_per_second_runs"]) == 1
    assert figures["classic_train_split_update"] > 0
    assert not any(name.startswith("sb3") for name in figures) and "classic_over_sb3" not in figures


def test_the_networks_are_the_ones_named() -> None:
    networks = small_networks()
    assert networks["small_cnn"].network == "small_cnn"
    assert networks["small_cnn"].observation.shape == (10, 10, 4)  # MinAtar's size
    assert resolve_config("der").network == "der_cnn"
    with pytest.raises(ConfigError, match="at least 1"):
        measure_small_networks(steps=0, rounds=1)


def test_sb3_is_given_the_classic_presets_settings() -> None:
    config = _classic()
    kwargs = sb3_dqn_kwargs(config, total_steps=16_000)
    assert kwargs["learning_rate"] == config.learning_rate == 0.0023
    assert kwargs["buffer_size"] == config.replay_capacity == 100_000
    assert kwargs["learning_starts"] == config.replay_start_steps == 1_000
    assert kwargs["batch_size"] == config.batch_size == 64
    assert kwargs["gamma"] == config.discount == 0.99
    assert kwargs["train_freq"] == config.update_period_steps == 2
    assert kwargs["gradient_steps"] == 1
    assert kwargs["target_update_interval"] == config.target_update_steps == 256
    assert kwargs["exploration_initial_eps"] == config.epsilon_start == 1.0
    assert kwargs["exploration_final_eps"] == config.epsilon_end == 0.04
    assert kwargs["exploration_fraction"] * 16_000 == config.epsilon_decay_steps == 8_000
    assert config.max_gradient_norm == 0 and kwargs["max_grad_norm"] == math.inf  # no clip
    assert kwargs["policy_kwargs"]["net_arch"] == list(config.mlp_hidden_sizes) == [256, 256]
    assert kwargs["policy_kwargs"]["optimizer_class"] is torch.optim.Adam
    assert kwargs["policy_kwargs"]["optimizer_kwargs"] == {"eps": config.adam_epsilon}
    # A part SB3's DQN has built in cannot be changed: refused, not silently dropped.
    for changed in ({"n_step": 3}, {"dueling": True}, {"td_error_clip": 0.0}):
        with pytest.raises(ValueError, match="SB3's DQN cannot run"):
            sb3_dqn_kwargs(dataclasses.replace(config, **changed), total_steps=16_000)


@needs_sb3
def test_the_settings_read_back_from_sb3_are_the_classic_presets() -> None:
    config = _classic()
    model = small.make_sb3_classic(config, total_steps=16_000, device=CPU)
    try:
        settings = small.sb3_settings(model, total_steps=16_000)
    finally:
        model.env.close()  # type: ignore[union-attr]
    assert settings["net_arch"] == [256, 256]
    for sb3_name, setting in small.SB3_NAMES.items():
        assert settings[sb3_name] == getattr(config, setting), sb3_name
    assert settings["train_freq_unit"] == "step" and settings["gradient_steps"] == 1
    assert settings["tau"] == 1.0  # a hard target copy, as dqnlab's
    assert settings["exploration_decay_steps"] == config.epsilon_decay_steps
    assert settings["optimizer"] == "Adam" and settings["optimizer_eps"] == config.adam_epsilon
    assert settings["max_grad_norm"] == "inf"


@needs_sb3
def test_a_short_run_against_sb3_gives_the_ratio() -> None:
    figures = training_against_sb3(steps=200, rounds=1, device=CPU, peers=True, seed=0)
    assert figures["sb3_train_steps_per_second"] > 0
    assert figures["classic_over_sb3"] == pytest.approx(
        figures["classic_train_steps_per_second"] / figures["sb3_train_steps_per_second"]
    )
    # Timed once learning ran, at the final ε: 200 steps, an update every 2.
    assert figures["sb3_settings"]["updates"] == 100
    assert figures["sb3_settings"]["exploration_decay_steps"] == 1_000  # its learning starts


def test_the_subcommand_writes_its_figures(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    fewer_repeats = functools.partial(small.measure_small_networks, update_repeats=2)
    monkeypatch.setattr(small, "measure_small_networks", fewer_repeats)
    path = tmp_path / "small.json"
    command = ["bench", "small", "--steps", "200", "--rounds", "1", "--json", str(path)]
    result = CliRunner().invoke(app, command)
    assert result.exit_code == 0, result.output
    figures = json.loads(path.read_text())
    for name in ("mlp", "small_cnn", "der_cnn"):
        assert figures[f"{name}_updates_per_second"] > 0
    assert figures["classic_train_steps_per_second"] > 0
    assert "classic_train_steps_per_second" in result.output


def test_peers_without_sb3_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(peers, "peer_available", lambda: False)
    result = CliRunner().invoke(app, ["bench", "small", "--peers"])
    assert result.exit_code != 0
    assert "--peers needs Stable-Baselines3" in str(result.exception)
    assert "\n" not in str(result.exception)
