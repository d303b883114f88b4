"""The run directory: its layout, config.toml, network files (with the family's heads too)
and final evaluations."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from dqnlab import envs
from dqnlab.algorithm.agent import agent_for_input, build_agent
from dqnlab.algorithm.heads import has_noise, sample_noise
from dqnlab.algorithm.networks import DistributionalQNetwork
from dqnlab.config import resolve_config
from dqnlab.envs import make_env
from dqnlab.errors import DqnlabError
from dqnlab.run import rundir


def test_network_file_round_trip_and_refusals(tmp_path: Path) -> None:
    path = rundir.network_path(tmp_path, "best")
    assert path == tmp_path / "checkpoints" / "best.pt"
    rundir.save_network(path, {"step": 3, "network": {"w": torch.ones(2)}})
    payload = rundir.load_network(path)
    assert payload["format"] == rundir.NETWORK_FORMAT and payload["step"] == 3
    assert torch.equal(payload["network"]["w"], torch.ones(2))
    assert not list(path.parent.glob("*.tmp"))
    with pytest.raises(DqnlabError, match="no network file"):
        rundir.load_network(tmp_path / "missing.pt")
    torch.save({"format": "something else"}, tmp_path / "other.pt")
    with pytest.raises(DqnlabError, match="not a dqnlab network file"):
        rundir.load_network(tmp_path / "other.pt")
    with pytest.raises(ValueError, match="not one of"):
        rundir.network_path(tmp_path, "bestt")


@pytest.mark.parametrize("env", ["CartPole-v1", "pong"])
def test_an_agent_is_built_from_the_network_file_alone(tmp_path, monkeypatch, env) -> None:
    config = resolve_config("classic" if env == "CartPole-v1" else "nature", env=env)
    game = make_env(config, training=False, seed=0)
    trained = build_agent(config, game, torch.device("cpu"), seed=0)
    input_shape = (config.history_length, *game.observation_shape)
    payload = rundir.network_payload(
        config, input_shape, game.observation_dtype, game.action_names, 7, trained.online, 1.5
    )
    game.close()
    path = tmp_path / "net.pt"
    rundir.save_network(path, payload)

    def no_environment(*args, **kwargs):
        raise AssertionError("a network file is loaded without making an environment")

    monkeypatch.setattr(envs.AtariEnv, "__init__", no_environment)
    monkeypatch.setattr(envs.gym, "make", no_environment)
    agent, loaded_config, _ = rundir.agent_from_network(
        rundir.load_network(path), path, seed=1, device=torch.device("cpu")
    )
    assert loaded_config == config
    assert agent.input_shape == input_shape and agent.action_names == trained.action_names
    inputs = np.zeros((2, *input_shape), dtype=agent.observation_dtype)
    assert np.array_equal(agent.q_values(inputs), trained.q_values(inputs))
    # Files written before the observation dtype was stored read as their input implies.
    del payload["observation_dtype"]
    agent, _, _ = rundir.agent_from_network(payload, path, 1, torch.device("cpu"))
    assert agent.observation_dtype == trained.observation_dtype
    del payload["action_names"]
    with pytest.raises(DqnlabError, match="lacks 'action_names'"):
        rundir.agent_from_network(payload, path, 1, torch.device("cpu"))


def test_a_final_evaluation_with_more_games_of_the_same_network_is_kept(tmp_path) -> None:
    assert rundir.load_final_evaluation(tmp_path) is None
    thirty = {"checkpoint_step": 100, "episodes": 30, "mean": 1.0}
    assert rundir.record_final_evaluation(tmp_path, thirty) == (
        tmp_path / "final_evaluation.json",
        True,
    )
    fewer = {"checkpoint_step": 100, "episodes": 2, "mean": 5.0}
    assert rundir.record_final_evaluation(tmp_path, fewer)[1] is False
    assert rundir.load_final_evaluation(tmp_path) == thirty
    newer = {"checkpoint_step": 200, "episodes": 2, "mean": 5.0}
    assert rundir.record_final_evaluation(tmp_path, newer)[1] is True
    assert rundir.load_final_evaluation(tmp_path) == newer
    rundir.final_evaluation_path(tmp_path).write_text("{")
    with pytest.raises(DqnlabError, match="not valid JSON"):
        rundir.load_final_evaluation(tmp_path)


def test_config_is_rewritten_for_a_new_budget_only(tmp_path: Path) -> None:
    run = tmp_path / "run"
    config = resolve_config("classic", env="CartPole-v1", total_steps=1000)
    assert rundir.prepare_run_dir(run, force=False, config=config) is False
    rundir.write_run_config(run, config)
    longer = dataclasses.replace(config, total_steps=5000)
    assert rundir.prepare_run_dir(run, force=False, config=longer) is True
    assert rundir.load_run_config(run) == longer
    with pytest.raises(DqnlabError, match=r"other settings \(discount\)"):
        rundir.update_run_config(run, dataclasses.replace(longer, discount=0.5))
    assert rundir.load_run_config(run) == longer


def test_kept_evaluation_networks_and_names(tmp_path: Path) -> None:
    assert rundir.eval_network_steps(tmp_path) == []
    for step in (2500, 500):
        rundir.save_network(rundir.eval_network_path(tmp_path, step), {"step": step})
    (rundir.checkpoints_dir(tmp_path) / "evals" / "notes.txt").write_text("x")
    assert rundir.eval_network_steps(tmp_path) == [500, 2500]
    assert rundir.default_run_dir("module:Env", "nature", 3) == Path("runs/module_Env-nature-s3")
    assert rundir.default_run_dir("Acrobot-v1", "tuned/Acrobot-v1", 1) == Path(
        "runs/Acrobot-v1-tuned-s1"
    )
    assert rundir.default_run_dir("pong", "my/own.toml", 0) == Path("runs/pong-own-s0")
    assert rundir.default_sweep_dir("ALE/Pong-v5", ["a", "b"]) == Path("sweeps/ALE_Pong-v5-a+b")


@pytest.mark.parametrize(
    ("preset", "input_shape", "dtype"),
    [("nature", (4, 36, 36), np.uint8), ("classic", (2, 4), np.float32)],
)
def test_a_network_file_of_a_rainbow_head_loads_from_its_config(
    tmp_path, preset, input_shape, dtype
) -> None:
    config = resolve_config(
        preset, env="pong", dueling=True, noisy=True, distributional="c51", noisy_sigma0=0.1
    )
    trained = agent_for_input(config, input_shape, dtype, ["a", "b", "c"], torch.device("cpu"), 0)
    assert isinstance(trained.online, DistributionalQNetwork) and has_noise(trained.online)
    sample_noise(trained.online, torch.Generator().manual_seed(0))
    with torch.no_grad():  # weights that differ from a fresh network's
        for parameter in trained.online.parameters():
            parameter.add_(0.01)
    payload = rundir.network_payload(
        config, input_shape, dtype, trained.action_names, 3, trained.online
    )
    assert not [key for key in payload["network"] if "epsilon" in key or "support" in key]
    path = tmp_path / "best.pt"
    rundir.save_network(path, payload)
    agent, loaded_config, _ = rundir.agent_from_network(
        rundir.load_network(path), path, seed=1, device=torch.device("cpu")
    )
    assert loaded_config == config and isinstance(agent.online, DistributionalQNetwork)
    inputs = np.random.default_rng(0).integers(0, 256, (2, *input_shape)).astype(dtype)
    assert np.array_equal(agent.q_values(inputs), trained.q_values(inputs))  # eval: the means
