"""Playing games epsilon-greedily on one environment, raw scores: the periodic
evaluation's protocol (a budget of agent steps, the mean of the games that finished within
it, as the Lua code's train_agent.lua), and the loop every other player reuses.

The periodic evaluation plays one environment: a step budget shared by several games in
parallel would end other games than the sequential protocol.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dqnlab.algorithm.agent import Agent
from dqnlab.algorithm.replay import FrameHistory
from dqnlab.envs import Environment


@dataclass
class EvaluationResult:
    scores: list[float] = field(default_factory=list)  # finished games only, in game order
    steps: int = 0  # agent steps, those of games cut short included
    frames: int = 0  # raw frames emulated, no-op starts and games cut short included
    seconds: float = 0.0
    num_envs: int = 1  # environments played at once
    workers: int = 0  # processes stepping them (0: the player's own)

    @property
    def mean(self) -> float:
        return float(np.mean(self.scores)) if self.scores else float("nan")

    @property
    def std(self) -> float:
        return float(np.std(self.scores)) if self.scores else float("nan")

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0


def play(
    agent: Agent,
    env: Environment,
    history_length: int,
    epsilon: float,
    max_steps: int | None = None,
    max_episodes: int | None = None,
    choose: Callable[[int, np.ndarray], int] | None = None,
) -> EvaluationResult:
    """Play until `max_steps` agent steps or `max_episodes` finished games, whichever first.

    Only finished games count: an episode cut by `max_steps` is dropped (Lua, dqn_zoo).
    A game ends at game over or at the environment's episode cap. Each action is
    `agent.act(history, epsilon)`, or `choose(step, history)` where given (`step`
    counts the agent steps of this play from 0).
    """
    if max_steps is None and max_episodes is None:
        raise ValueError("play needs max_steps or max_episodes")
    history = FrameHistory(history_length, env.observation_shape, env.observation_dtype)
    result = EvaluationResult()
    frames_before = env.frames
    start = time.perf_counter()
    history.reset(env.reset(new_game=True))
    score = 0.0
    while (max_steps is None or result.steps < max_steps) and (
        max_episodes is None or len(result.scores) < max_episodes
    ):
        if choose is None:
            action = agent.act(history.frames, epsilon)
        else:
            action = choose(result.steps, history.frames)
        observation, reward, terminated, truncated = env.step(action)
        result.steps += 1
        score += reward
        if env.game_ended:
            result.scores.append(score)
            score = 0.0
            if max_episodes is not None and len(result.scores) >= max_episodes:
                break
            history.reset(env.reset())
        elif terminated or truncated:  # an environment may end an episode without a game end
            history.reset(env.reset())
        else:
            history.push(observation)
    result.frames = env.frames - frames_before
    result.seconds = time.perf_counter() - start
    return result
