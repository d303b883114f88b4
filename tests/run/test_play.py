"""The one play loop: a step or game budget, only finished games scored, a chooser."""

from __future__ import annotations

import pytest

from dqnlab.envs import make_env
from dqnlab.run.play import EvaluationResult, play
from tests.helpers import untrained_agent


def test_a_step_budget_drops_the_game_it_cuts(cartpole) -> None:
    agent = untrained_agent(cartpole)
    env = make_env(cartpole, training=False, seed=3, max_episode_frames=500)
    result = play(agent, env, cartpole.history_length, 1.0, max_steps=50)
    assert result.steps == result.frames == 50
    assert sum(result.scores) < 50  # the game cut at step 50 is not scored
    assert all(score >= 1 for score in result.scores)


def test_a_chooser_replaces_the_agent_and_counts_steps_from_zero(cartpole) -> None:
    agent = untrained_agent(cartpole)
    seen: list[int] = []

    def always_left(step: int, history) -> int:
        assert history.shape == (cartpole.history_length, 4)
        seen.append(step)
        return 0

    env = make_env(cartpole, training=False, seed=3, max_episode_frames=500)
    result = play(agent, env, cartpole.history_length, 0.0, max_episodes=2, choose=always_left)
    assert len(result.scores) == 2 and seen == list(range(result.steps))
    assert sum(result.scores) == result.steps  # CartPole pays 1 a step


def test_play_needs_a_budget(cartpole) -> None:
    env = make_env(cartpole, training=False, seed=0)
    with pytest.raises(ValueError, match="max_steps or max_episodes"):
        play(untrained_agent(cartpole), env, cartpole.history_length, 0.0)
    assert EvaluationResult().frames_per_second == 0.0
