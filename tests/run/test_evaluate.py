"""The final evaluation of a run's network: a network file played on several
environments, and a warning for games that might never end."""

from __future__ import annotations

import dataclasses

import torch

from dqnlab.config import resolve_config
from dqnlab.run import rundir
from dqnlab.run.evaluate import final_evaluation
from tests.helpers import BlinkEnv, untrained_agent


def test_final_evaluation_plays_a_checkpoint_on_several_environments(tmp_path) -> None:
    config = resolve_config("classic", env="CartPole-v1", final_eval_max_episode_frames=200)
    agent = untrained_agent(config)
    path = tmp_path / "net.pt"
    stored = {"input_shape": agent.input_shape, "action_names": agent.action_names}
    rundir.save_network(
        path, {"config": config.to_dict(), **stored, "network": agent.online.state_dict()}
    )
    result, network = final_evaluation(
        tmp_path, str(path), 5, seed=2, device=torch.device("cpu"), num_envs=2
    )
    assert (network.config, network.path, network.step) == (config, path, None)
    assert len(result.scores) == 5
    assert all(1 <= score <= 200 for score in result.scores)
    assert sum(result.scores) == result.steps == result.frames
    again, _ = final_evaluation(tmp_path, str(path), 5, 2, torch.device("cpu"), num_envs=2)
    assert again.scores == result.scores


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
