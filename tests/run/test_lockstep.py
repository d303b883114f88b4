"""The final evaluation's lockstep player: exact game counts, determinism, the same
games as a sequential loop, a step budget, and worker processes without torch."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import textwrap

import pytest

from dqnlab.algorithm.agent import Agent
from dqnlab.algorithm.replay import FrameHistory
from dqnlab.config import Config, derive_seeds, resolve_config
from dqnlab.envs import Environment, make_env
from dqnlab.errors import DqnlabError
from dqnlab.run.lockstep import play_games
from dqnlab.run.play import EvaluationResult, play
from tests.helpers import untrained_agent

EPSILON = 0.05
CARTPOLE_CAP = 500
PONG_CAP = 2_000  # an untrained network loses a game of Pong in more frames: games end here


def games(config: Config, episodes: int, seed: int, cap: int, **options) -> EvaluationResult:
    agent = untrained_agent(config)
    return play_games(
        agent, config, episodes, seed, epsilon=EPSILON, max_episode_frames=cap, **options
    )


def reference_games(
    agent: Agent, env: Environment, history_length: int, count: int
) -> tuple[list[float], int]:
    """`count` whole games played one step at a time with `agent.act`: (scores, steps)."""
    history = FrameHistory(history_length, env.observation_shape, env.observation_dtype)
    history.reset(env.reset(new_game=True))
    scores: list[float] = []
    score = 0.0
    steps = 0
    while True:
        observation, reward, _, _ = env.step(agent.act(history.frames, EPSILON))
        steps += 1
        score += reward
        if env.game_ended:  # evaluation episodes end only with their game
            scores.append(score)
            score = 0.0
            if len(scores) == count:
                return scores, steps
            history.reset(env.reset())
        else:
            history.push(observation)


def test_cartpole_plays_exactly_the_requested_games_and_scores_add_up(cartpole) -> None:
    result = games(cartpole, 7, seed=3, cap=CARTPOLE_CAP, num_envs=3)
    assert len(result.scores) == 7
    assert all(1 <= score <= CARTPOLE_CAP for score in result.scores)
    # CartPole pays 1 per step and a frame is a step: scores, steps and frames agree.
    assert sum(result.scores) == result.steps == result.frames
    assert result.seconds > 0


def test_one_environment_plays_the_games_of_a_sequential_loop(cartpole) -> None:
    result = games(cartpole, 4, seed=11, cap=CARTPOLE_CAP, num_envs=1, workers=0)
    env_seed = derive_seeds(11, 1)[0]
    env = make_env(cartpole, training=False, seed=env_seed, max_episode_frames=CARTPOLE_CAP)
    scores, steps = reference_games(untrained_agent(cartpole), env, cartpole.history_length, 4)
    assert result.scores == scores
    assert result.steps == steps == result.frames
    env = make_env(cartpole, training=False, seed=env_seed, max_episode_frames=CARTPOLE_CAP)
    sequential = play(untrained_agent(cartpole), env, cartpole.history_length, EPSILON, None, 4)
    assert sequential.scores == scores


def round_robin_games(
    config: Config, count: int, seed: int, cap: int, num_envs: int, max_steps: int | None = None
) -> tuple[dict[int, float], int, int]:
    """One agent stepping `num_envs` environments round-robin, each one's games in the slots
    i, i + N, ..., in two halves (envs 0 to ceil(N/2) - 1, then the others) until a half
    would overrun `max_steps`: (the finished games' scores by slot, steps, frames)."""
    agent = untrained_agent(config)
    envs = [
        make_env(config, training=False, seed=env_seed, max_episode_frames=cap)
        for env_seed in derive_seeds(seed, num_envs)
    ]
    shape, dtype = envs[0].observation_shape, envs[0].observation_dtype
    histories = [FrameHistory(config.history_length, shape, dtype) for _ in envs]
    for env, history in zip(envs, histories, strict=True):
        history.reset(env.reset(new_game=True))
    half = (num_envs + 1) // 2
    halves = [range(half), range(half, num_envs)]
    games_left = [len(range(i, count, num_envs)) for i in range(num_envs)]
    game = list(range(num_envs))
    score = [0.0] * num_envs
    scores: dict[int, float] = {}
    steps = 0
    while any(games_left):
        for envs_in_half in halves:
            playing = [i for i in envs_in_half if games_left[i]]
            if max_steps is not None and steps + len(playing) > max_steps:
                return scores, steps, sum(env.frames for env in envs)
            actions = {i: agent.act(histories[i].frames, EPSILON) for i in playing}
            for i in playing:
                observation, reward, _, _ = envs[i].step(actions[i])
                steps += 1
                score[i] += reward
                if envs[i].game_ended:
                    scores[game[i]], score[i], game[i] = score[i], 0.0, game[i] + num_envs
                    games_left[i] -= 1
                    if games_left[i]:
                        histories[i].reset(envs[i].reset())
                else:
                    histories[i].push(observation)
    return scores, steps, sum(env.frames for env in envs)


def test_environment_i_plays_games_i_i_plus_n_and_so_on(cartpole) -> None:
    """The lockstep acts for env 0, 1, ..., N-1 in turn: one agent stepping the N
    environments round-robin, each one's games in the slots i, i + N, ..."""
    result = games(cartpole, 7, seed=5, cap=CARTPOLE_CAP, num_envs=3, workers=0)
    scores, steps, frames = round_robin_games(cartpole, 7, seed=5, cap=CARTPOLE_CAP, num_envs=3)
    assert result.scores == [scores[slot] for slot in range(7)]
    assert (result.steps, result.frames) == (steps, frames)
    assert (result.num_envs, result.workers) == (3, 0)


@pytest.mark.parametrize("workers", [0, 2])
def test_a_step_budget_ends_the_play_and_scores_only_finished_games(cartpole, workers) -> None:
    """Games cut by `max_steps` are not scored but their steps and frames count; the games
    finished are those of the unbounded play, scored alike."""
    budget = 50  # untrained CartPole games last about 10 to 40 steps
    result = games(
        cartpole, 7, seed=5, cap=CARTPOLE_CAP, num_envs=3, workers=workers, max_steps=budget
    )
    scores, steps, frames = round_robin_games(
        cartpole, 7, seed=5, cap=CARTPOLE_CAP, num_envs=3, max_steps=budget
    )
    assert 0 < len(scores) < 7  # some games finished, some were cut: the case under test
    assert result.scores == [scores[slot] for slot in sorted(scores)]
    assert (result.steps, result.frames) == (steps, frames)
    assert budget - 2 < result.steps <= budget  # the halves have 2 and 1 environments
    assert sum(result.scores) < result.steps  # steps of the games cut short are counted
    unbounded = games(cartpole, 7, seed=5, cap=CARTPOLE_CAP, num_envs=3, workers=workers)
    assert [unbounded.scores[slot] for slot in sorted(scores)] == result.scores


def test_a_step_budget_counts_every_atari_frame_emulated(pong) -> None:
    """Frames are those the emulators ran, no-op starts and the games cut short included."""
    cap, budget = 400, 390  # games of about 95 steps: each env finishes one, starts one
    result = games(pong, 6, seed=8, cap=cap, num_envs=3, workers=2, max_steps=budget)
    scores, steps, frames = round_robin_games(
        pong, 6, seed=8, cap=cap, num_envs=3, max_steps=budget
    )
    assert len(scores) == 3
    assert result.scores == [scores[slot] for slot in sorted(scores)]
    assert (result.steps, result.frames) == (steps, frames)
    assert result.frames > 3 * cap  # more than the finished games' frames


def test_worker_processes_step_the_same_games_as_the_player_itself(cartpole) -> None:
    in_process = games(cartpole, 5, seed=9, cap=CARTPOLE_CAP, num_envs=3, workers=0)
    two_workers = games(cartpole, 5, seed=9, cap=CARTPOLE_CAP, num_envs=3, workers=2)
    assert two_workers.scores == in_process.scores
    assert (two_workers.steps, two_workers.frames) == (in_process.steps, in_process.frames)


def test_atari_games_end_at_the_cap_and_repeat_exactly(pong) -> None:
    first = games(pong, 3, seed=21, cap=PONG_CAP, num_envs=2)  # default: worker processes
    second = games(pong, 3, seed=21, cap=PONG_CAP, num_envs=2)
    assert len(first.scores) == 3
    assert first.scores == second.scores
    assert (first.steps, first.frames) == (second.steps, second.frames)
    # Every game was cut at the cap, no-op frames included: 2,000 raw frames each.
    assert first.frames == 3 * PONG_CAP
    assert first.steps < first.frames / pong.action_repeat_frames
    assert all(-21 <= score <= 21 for score in first.scores)


def test_atari_one_environment_plays_the_games_of_a_sequential_loop(pong) -> None:
    result = games(pong, 2, seed=4, cap=PONG_CAP, num_envs=1, workers=1)
    env = make_env(pong, training=False, seed=derive_seeds(4, 1)[0], max_episode_frames=PONG_CAP)
    scores, steps = reference_games(untrained_agent(pong), env, pong.history_length, 2)
    assert result.scores == scores
    assert result.steps == steps
    assert result.frames == env.frames == 2 * PONG_CAP


def test_more_environments_than_games_play_each_game_once(cartpole) -> None:
    result = games(cartpole, 2, seed=1, cap=CARTPOLE_CAP, num_envs=8, workers=0)
    assert len(result.scores) == 2
    assert sum(result.scores) == result.steps


@pytest.mark.parametrize("options", [{"num_envs": 0}, {"workers": -1}, {"max_steps": 0}])
def test_bad_settings_are_refused(cartpole, options) -> None:
    with pytest.raises(ValueError):
        games(cartpole, 2, seed=1, cap=CARTPOLE_CAP, **options)
    with pytest.raises(ValueError):
        games(cartpole, 0, seed=1, cap=CARTPOLE_CAP)


def test_a_failure_in_a_worker_process_is_reported(pong) -> None:
    """A network with Pong's 18 full-set actions acting on the 6 minimal ones: the worker's
    env.step fails, and the player says which worker and why."""
    agent = untrained_agent(dataclasses.replace(pong, full_action_space=True))
    with pytest.raises(DqnlabError, match="(?s)evaluation worker .* failed.*IndexError"):
        play_games(agent, pong, 2, 1, epsilon=1.0, max_episode_frames=PONG_CAP, workers=2)


TORCH_PROBE = """
import sys

import gymnasium as gym
import numpy as np


class TorchProbe(gym.Env):
    observation_space = gym.spaces.Box(0.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Discrete(2)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.steps = 0
        return np.zeros(2, np.float32), {}

    def step(self, action):
        self.steps += 1
        reward = float("torch" in sys.modules)
        return np.zeros(2, np.float32), reward, self.steps == 3, False, {}
"""


def test_worker_processes_do_not_import_torch(tmp_path, monkeypatch) -> None:
    """The player has torch (the probe scores 3 a game there); the workers must not."""
    (tmp_path / "torch_probe.py").write_text(TORCH_PROBE)
    monkeypatch.syspath_prepend(str(tmp_path))  # workers get the player's sys.path
    config = resolve_config("classic", env="torch_probe:TorchProbe")
    in_player = games(config, 2, seed=0, cap=0, num_envs=2, workers=0)
    assert in_player.scores == [3.0, 3.0]
    in_workers = games(config, 2, seed=0, cap=0, num_envs=2, workers=2)
    assert in_workers.scores == [0.0, 0.0]


def test_the_worker_module_does_not_import_torch() -> None:
    """What the forkserver preloads: its imports alone, in a fresh interpreter."""
    code = textwrap.dedent("""
        import sys
        import dqnlab.envs.pool
        print(sorted(name for name in sys.modules if name.split(".")[0] == "torch")[:1])
    """)
    imported = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    assert imported.strip() == "[]"
