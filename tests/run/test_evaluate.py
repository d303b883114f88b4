"""The final evaluation of a run's network: a network file played on several
environments, under another protocol (`dqnlab evaluate --set`), and a warning for games
that might never end."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from dqnlab.config import Config, derive_seeds, resolve_config, with_evaluation_settings
from dqnlab.errors import ConfigError
from dqnlab.run import rundir
from dqnlab.run.evaluate import final_evaluation
from tests.helpers import BlinkEnv, dqnlab_main, untrained_agent


def _saved_network(config: Config, path: Path) -> Path:
    agent = untrained_agent(config)
    stored = {"input_shape": agent.input_shape, "action_names": agent.action_names}
    rundir.save_network(
        path, {"config": config.to_dict(), **stored, "network": agent.online.state_dict()}
    )
    return path


def test_final_evaluation_plays_a_checkpoint_on_several_environments(tmp_path) -> None:
    config = resolve_config("classic", env="CartPole-v1", final_eval_max_episode_frames=200)
    path = _saved_network(config, tmp_path / "net.pt")
    result, network = final_evaluation(
        tmp_path, str(path), 5, seed=2, device=torch.device("cpu"), num_envs=2
    )
    assert (network.config, network.path, network.step) == (config, path, None)
    assert len(result.scores) == 5
    assert all(1 <= score <= 200 for score in result.scores)
    assert sum(result.scores) == result.steps == result.frames
    again, _ = final_evaluation(tmp_path, str(path), 5, 2, torch.device("cpu"), num_envs=2)
    assert again.scores == result.scores


def test_noisy_layers_evaluate_on_their_means_or_with_fresh_noise_as_eval_noise_says(
    tmp_path: Path,
) -> None:
    noisy = resolve_config(
        "classic", env="CartPole-v1", noisy=True, final_eval_max_episode_frames=200
    )
    path = _saved_network(noisy, tmp_path / "net.pt")
    cpu = torch.device("cpu")
    means, network = final_evaluation(tmp_path, str(path), 4, seed=3, device=cpu, num_envs=2)
    assert network.config.eval_noise == "mean"
    drawn = network.agent.noise_generator.get_state()  # untouched: no noise drawn
    assert torch.equal(drawn, torch.Generator().manual_seed(derive_seeds(3, 2)[1]).get_state())
    sampled, network = final_evaluation(
        tmp_path, str(path), 4, 3, cpu, num_envs=2, settings={"eval_noise": "sampled"}
    )
    assert network.config.eval_noise == "sampled"  # the run's own config says "mean"
    # Fresh noise for every action, drawn from the agent's generator: a draw per step.
    assert not torch.equal(network.agent.noise_generator.get_state(), drawn)
    again, _ = final_evaluation(
        tmp_path, str(path), 4, 3, cpu, num_envs=2, settings={"eval_noise": "sampled"}
    )
    assert again.scores == sampled.scores  # seeded: the same games
    # One observation: the acting values are the mean network's, or a noisy draw each call.
    observation = np.zeros((1, 1, 4), dtype=np.float32)
    agent = network.agent
    first, second = (agent.acting_q_values(observation, training=False) for _ in range(2))
    assert not np.array_equal(first, second)
    assert not np.array_equal(first, agent.q_values(observation))
    agent.noisy_evaluation = False
    assert np.array_equal(agent.acting_q_values(observation, False), agent.q_values(observation))


def test_eval_noise_is_refused_where_it_cannot_apply() -> None:
    with pytest.raises(ConfigError, match=r"eval_noise = 'often' is not one of: mean, sampled"):
        resolve_config("classic", env="CartPole-v1", eval_noise="often")
    plain = resolve_config("classic", env="CartPole-v1", eval_noise="sampled")
    with pytest.raises(ConfigError, match=r"eval_noise = 'sampled' .* this network has none"):
        untrained_agent(plain)
    with pytest.raises(ConfigError, match=r"--set learning_rate: evaluate changes only how"):
        with_evaluation_settings(plain, {"learning_rate": 0.1})
    assert with_evaluation_settings(plain, {"eval_epsilon": "0"}).eval_epsilon == 0.0


def test_evaluate_with_set_records_the_protocol_and_keeps_the_runs_own_result(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    noisy = resolve_config(
        "classic", env="CartPole-v1", noisy=True, final_eval_max_episode_frames=50
    )
    path = _saved_network(noisy, tmp_path / "net.pt")
    out = tmp_path / "sampled.json"
    code, stderr = dqnlab_main(
        capsys, monkeypatch, "evaluate", str(tmp_path), "--checkpoint", str(path),
        "--episodes", "2", "--set", "eval_noise=sampled", "--set", "noop_max_frames=0",
        "--json", str(out),
    )  # fmt: skip
    assert code == 0, stderr
    record = json.loads(out.read_text())
    assert record["settings"] == {"eval_noise": "sampled", "noop_max_frames": 0}
    assert record["episodes"] == 2
    assert not (tmp_path / "final_evaluation.json").exists()
    code, stderr = dqnlab_main(
        capsys, monkeypatch, "evaluate", str(tmp_path), "--checkpoint", str(path),
        "--set", "noisy=false",
    )  # fmt: skip
    assert code == 2 and "--set noisy: evaluate changes only how the network plays" in stderr


def test_a_final_evaluation_that_might_never_end_is_announced() -> None:
    from dqnlab.cli.common import format_warning
    from dqnlab.run.evaluate import unbounded_games_warning

    endless = resolve_config("classic", env=f"{BlinkEnv.__module__}:BlinkEnv")  # no TimeLimit
    message = unbounded_games_warning(endless)
    assert message is not None and "no step limit" in message
    capped = dataclasses.replace(endless, final_eval_max_episode_frames=100)
    assert unbounded_games_warning(capped) is None
    assert unbounded_games_warning(resolve_config("classic", env="CartPole-v1")) is None
    assert unbounded_games_warning(resolve_config("nature", env="pong")) is None
    # Shown by the command as one line of its own.
    assert format_warning(message, UserWarning, "/x/dqnlab/evaluate.py", 1) == (
        f"dqnlab: warning: {message}\n"
    )
    assert "UserWarning" in format_warning("other", UserWarning, "/x/gymnasium/core.py", 1)
