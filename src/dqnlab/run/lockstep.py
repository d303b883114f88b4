"""Whole games on several environments in lockstep: the final evaluation's way to play.

The final evaluation counts whole games, so `play_games` plays them on several
environments at once, acted for in two halves with a batched forward pass each, the
environments stepped by worker processes (`dqnlab.envs.pool`), one per core, one half
while the player acts for the other. Processes, not threads: ale-py holds the GIL while it
emulates (ALEInterface.act: a thread emulating a no-op start stalls every other Python
thread until it returns), so threads stepping Atari games take turns on one core. OpenCV
releases it, but emulation is most of a step.
"""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Iterator

import numpy as np
import torch

from dqnlab.algorithm.agent import Agent
from dqnlab.config import Config, derive_seeds
from dqnlab.envs import is_atari
from dqnlab.envs.pool import FINISHED, NEW_EPISODE, RUNNING, EnvGroup, EnvWorkers, Lockstep
from dqnlab.run.determinism import set_threads, usable_cores
from dqnlab.run.play import EvaluationResult


class _ActingBatch:
    """A range of environments acted for with one forward pass: their histories, stacked.

    Histories are kept twice and written alternately, so that a push is one copy without
    overlap; the inputs buffer gathers the environments still playing once some are done.
    """

    def __init__(
        self,
        index: int,
        env_ids: range,
        history_length: int,
        frame_shape: tuple[int, ...],
        dtype: np.dtype,
    ) -> None:
        self.index = index
        self.env_ids = env_ids
        size = len(env_ids)
        self.histories = np.zeros((2, size, history_length, *frame_shape), dtype=dtype)
        self.current = 0
        self.inputs = np.zeros((size, history_length, *frame_shape), dtype=dtype)
        self.active = list(env_ids)
        self.active_rows = np.arange(size)

    def act(self, agent: Agent, epsilon: float, actions: np.ndarray) -> None:
        """One forward pass, then `agent.act`'s choice for each environment in turn."""
        histories = self.histories[self.current]
        if len(self.active) == len(self.env_ids):
            inputs = histories
        else:
            inputs = self.inputs[: len(self.active)]
            np.take(histories, self.active_rows, axis=0, out=inputs, mode="clip")
        q_values = agent.acting_q_values(inputs, training=False)
        for row, i in enumerate(self.active):
            actions[i] = agent.choose(epsilon, q_values[row])

    def record(
        self,
        lockstep: Lockstep,
        score: list[float],
        game: list[int],
        game_scores: list[float | None],
    ) -> int:
        """Take in the step just done: push observations, score ended games (in
        `game_scores`, by game index). Returns the number of environments stepped."""
        stepped = len(self.active)
        rows = slice(self.env_ids.start, self.env_ids.stop)
        previous, self.current = self.current, 1 - self.current
        histories = self.histories[self.current]
        np.copyto(histories[:, :-1], self.histories[previous, :, 1:])
        np.copyto(histories[:, -1], lockstep.observations[rows])
        finished = False
        for i in self.active:
            score[i] += float(lockstep.rewards[i])
            status = lockstep.statuses[i]
            if status == RUNNING:
                continue
            histories[i - self.env_ids.start, :-1] = 0  # zeros before an episode's start
            if status == NEW_EPISODE:
                continue
            game_scores[game[i]] = score[i]
            score[i] = 0.0
            game[i] += len(game)
            finished = finished or status == FINISHED
        if finished:
            self.active = [i for i in self.active if lockstep.statuses[i] != FINISHED]
            self.active_rows = np.array(self.active, dtype=np.int64) - self.env_ids.start
        return stepped


def default_workers(config: Config) -> int:
    """One worker process per core for Atari games, none (the player steps) otherwise.

    A Gymnasium environment is usually cheaper to step than a message to a process, and
    it may be registered by the user's code, which a worker process would not have run.
    """
    cores = usable_cores()
    return cores if cores > 1 and is_atari(config.env) else 0


def default_num_envs(episodes: int) -> int:
    """All the games at once, up to 32: each environment plays one game, so the evaluation
    lasts as long as its longest game, and the forward passes have the largest batches
    (more environments were faster at every count tried; `dqnlab bench` measures it)."""
    return min(episodes, 32)


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    before = torch.get_num_threads()
    set_threads(count)
    try:
        yield
    finally:
        set_threads(before)


def play_games(
    agent: Agent,
    config: Config,
    episodes: int,
    seed: int,
    *,
    epsilon: float,
    max_episode_frames: int,
    num_envs: int | None = None,
    workers: int | None = None,
    max_steps: int | None = None,
) -> EvaluationResult:
    """Exactly `episodes` whole games at `epsilon`, on `num_envs` environments in lockstep.

    Environment i, seeded with child i of `seed`, plays games i, i + num_envs, ... each
    after its own no-op start, and the scores come back in game order. The environments
    are acted for in two halves, each with one forward pass over its stacked histories and
    then `agent.act`'s choice for each environment in turn (the same draws from
    `agent.rng`): environments 0 to num_envs - 1 act in this order at every lockstep, so
    the games depend on the seeds and `num_envs`, never on timing or `workers`. With one
    environment this is `play(..., max_episodes=episodes)`.

    `max_steps` bounds the agent steps of all environments together (a benchmark's
    budget): a half is stepped only if all its playing environments fit in what is left,
    and the first half that does not fit ends the play. Games in progress then are
    abandoned and not scored; their steps and frames are counted. The games finished are
    those of the unbounded play, with the same scores.

    `workers` processes step the environments (default `default_workers`; 0: the player
    steps them itself). While they step one half, the player acts for the other with one
    torch thread, leaving the cores to them; the thread count is restored afterwards.
    """
    num_envs, workers = _checked_counts(config, episodes, max_steps, num_envs, workers)
    seeds = derive_seeds(seed, num_envs)
    games = [len(range(i, episodes, num_envs)) for i in range(num_envs)]
    half = (num_envs + 1) // 2
    batches = [range(0, half), range(half, num_envs)] if num_envs > 1 else [range(1)]
    if agent.input_shape is None or agent.observation_dtype is None:
        raise ValueError("play_games needs an agent built for its input (agent_for_input)")
    frame_shape, frame_dtype = agent.input_shape[1:], agent.observation_dtype
    layout = Lockstep.layout(num_envs, frame_shape, frame_dtype)
    acting = [
        _ActingBatch(k, ids, config.history_length, frame_shape, frame_dtype)
        for k, ids in enumerate(batches)
    ]
    threads = 1 if workers and agent.device.type == "cpu" else torch.get_num_threads()
    stepper: EnvWorkers | EnvGroup
    if workers:
        stepper = EnvWorkers(config, max_episode_frames, seeds, games, batches, layout, workers)
    else:
        lockstep = Lockstep.over(Lockstep.buffers(layout), layout)
        stepper = EnvGroup(
            config, max_episode_frames, range(num_envs), seeds, games, batches, lockstep
        )
    with stepper, torch_threads(threads):
        result = _lockstep_play(agent, stepper, acting, epsilon, episodes, max_steps)
    result.num_envs, result.workers = num_envs, workers
    return result


def _checked_counts(
    config: Config, episodes: int, max_steps: int | None, num_envs: int | None, workers: int | None
) -> tuple[int, int]:
    """`play_games`' numbers of environments and workers, defaults filled in, at most one
    environment per game and one worker per environment; a ValueError for a count out of
    range (`max_steps` included)."""
    if episodes <= 0:
        raise ValueError(f"episodes must be positive, got {episodes}")
    if max_steps is not None and max_steps <= 0:
        raise ValueError(f"max_steps must be positive, got {max_steps}")
    if num_envs is None:
        num_envs = default_num_envs(episodes)
    if workers is None:  # one environment cannot overlap with acting: no process to talk to
        workers = default_workers(config) if num_envs > 1 else 0
    if num_envs <= 0 or workers < 0:
        raise ValueError(f"num_envs ({num_envs}) must be positive and workers ({workers}) >= 0")
    num_envs = min(num_envs, episodes)
    return num_envs, min(workers, num_envs)


def _lockstep_play(
    agent: Agent,
    stepper: EnvWorkers | EnvGroup,
    acting: list[_ActingBatch],
    epsilon: float,
    episodes: int,
    max_steps: int | None,
) -> EvaluationResult:
    """Act for one batch while the other is stepped: act 0, submit 0, act 1, submit 1,
    wait for 0, act 0, submit 0, wait for 1, ... (the acting order of a plain lockstep).

    A batch is acted for only once it is sure to be stepped, so that a bounded play draws
    from `agent.rng` as the unbounded one does up to where it stops."""
    lockstep = stepper.lockstep
    num_envs = len(lockstep.statuses)
    budget = max_steps if max_steps is not None else sys.maxsize
    result = EvaluationResult()
    game_scores: list[float | None] = [None] * episodes
    game = list(range(num_envs))  # the game each environment is playing
    score = [0.0] * num_envs
    submitted = 0  # agent steps submitted
    start = time.perf_counter()
    stepper.start()
    playing = []
    for batch in acting:
        rows = slice(batch.env_ids.start, batch.env_ids.stop)
        batch.histories[batch.current, :, -1] = lockstep.observations[rows]
        if submitted + len(batch.active) > budget:
            break
        batch.act(agent, epsilon, lockstep.actions)
        stepper.submit(batch.index)
        submitted += len(batch.active)
        playing.append(batch)
    while playing:
        for batch in list(playing):
            stepper.wait()
            result.steps += batch.record(lockstep, score, game, game_scores)
            if batch.active and submitted + len(batch.active) <= budget:
                batch.act(agent, epsilon, lockstep.actions)
                stepper.submit(batch.index)
                submitted += len(batch.active)
            else:
                if batch.active:  # out of budget: no half is stepped any more
                    budget = submitted
                playing.remove(batch)
    result.seconds = time.perf_counter() - start
    result.frames = int(lockstep.frames.sum())
    result.scores = [s for s in game_scores if s is not None]
    return result
