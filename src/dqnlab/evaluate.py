"""Evaluation: epsilon-greedy play of whole games, raw scores.

Two protocols from the Nature paper: the periodic one (a budget of agent steps, the mean
of the episodes that finished within it, as the Lua code's train_agent.lua) and the final
one (a number of whole games of at most 5 minutes each).

The periodic one plays one environment (`play`): a step budget shared by several games
in parallel would end other games than the sequential protocol. The final one counts
whole games, so `play_games` plays them on several environments in lockstep: one batched
forward pass per lockstep, the environments stepped by worker processes, one per core.
Processes, not threads: ale-py holds the GIL while it emulates (ALEInterface.act), so
threads stepping Atari games take turns on one core.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import sys
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dqnlab import checkpoints
from dqnlab.agent import Agent, build_agent
from dqnlab.config import Config, config_from_dict, derive_seeds
from dqnlab.envs import Environment, is_atari, make_env
from dqnlab.errors import DqnlabError
from dqnlab.replay import FrameHistory

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

CONFIG_FILE = "config.toml"


@dataclass
class EvaluationResult:
    scores: list[float] = field(default_factory=list)
    steps: int = 0
    frames: int = 0
    seconds: float = 0.0

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
) -> EvaluationResult:
    """Play until `max_steps` agent steps or `max_episodes` finished games, whichever first.

    Only finished games count: an episode cut by `max_steps` is dropped (Lua, dqn_zoo).
    A game ends at game over or at the environment's episode cap.
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
        observation, reward, terminated, truncated = env.step(agent.act(history.frames, epsilon))
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


# Whole games on several environments in lockstep -------------------------------------

# What an environment did in the last lockstep (one byte per environment).
_RUNNING = 0  # its episode goes on: push the observation on its history
_NEW_EPISODE = 1  # reset (a game start, or an episode that ended without a game end)
_NEXT_GAME = 2  # a game ended and the environment started its next game
_FINISHED = 3  # a game ended and the environment has no game left: it stops stepping

_LOCKSTEP_FIELDS = ("actions", "observations", "rewards", "statuses", "frames")


@dataclass
class _Lockstep:
    """What the player and the environments exchange at each lockstep, one row per env."""

    actions: np.ndarray  # (envs,) int64, written by the player
    observations: np.ndarray  # (envs, *frame_shape): each environment's newest observation
    rewards: np.ndarray  # (envs,) float64: raw reward of the last step
    statuses: np.ndarray  # (envs,) uint8: _RUNNING ... _FINISHED
    frames: np.ndarray  # (envs,) int64: raw frames emulated so far, no-ops included

    @staticmethod
    def layout(
        num_envs: int, frame_shape: tuple[int, ...], frame_dtype: np.dtype
    ) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
        return {
            "actions": ((num_envs,), np.dtype(np.int64)),
            "observations": ((num_envs, *frame_shape), np.dtype(frame_dtype)),
            "rewards": ((num_envs,), np.dtype(np.float64)),
            "statuses": ((num_envs,), np.dtype(np.uint8)),
            "frames": ((num_envs,), np.dtype(np.int64)),
        }

    @classmethod
    def over(cls, buffers: dict[str, Any], layout: dict[str, Any]) -> _Lockstep:
        """Arrays over `buffers` (bytes-like objects, shared memory included)."""
        arrays = {}
        for name in _LOCKSTEP_FIELDS:
            shape, dtype = layout[name]
            count = int(np.prod(shape))
            arrays[name] = np.frombuffer(buffers[name], dtype=dtype, count=count).reshape(shape)
        return cls(**arrays)


class _EnvGroup:
    """Some of the lockstep environments, each with the number of games it has to play."""

    def __init__(
        self,
        config: Config,
        max_episode_frames: int,
        env_ids: Sequence[int],
        seeds: Sequence[int],
        games: Sequence[int],
        lockstep: _Lockstep,
    ) -> None:
        self.env_ids = list(env_ids)
        self.envs: list[Environment] = []
        try:
            for i in self.env_ids:
                self.envs.append(
                    make_env(
                        config, training=False, seed=seeds[i], max_episode_frames=max_episode_frames
                    )
                )
        except BaseException:
            self.close()
            raise
        self.games_left = [games[i] for i in self.env_ids]
        self.lockstep = lockstep

    def start(self) -> None:
        """A new game on every environment."""
        lockstep = self.lockstep
        for i, env in zip(self.env_ids, self.envs, strict=True):
            lockstep.observations[i] = env.reset(new_game=True)
            lockstep.rewards[i] = 0.0
            lockstep.statuses[i] = _NEW_EPISODE
            lockstep.frames[i] = env.frames

    def step(self) -> None:
        """One step of every environment with a game left, then its reset if needed (as
        `play`: the next game starts right after a game end, with its own no-ops)."""
        lockstep = self.lockstep
        for k, (i, env) in enumerate(zip(self.env_ids, self.envs, strict=True)):
            if not self.games_left[k]:
                continue
            observation, reward, terminated, truncated = env.step(int(lockstep.actions[i]))
            if env.game_ended:
                self.games_left[k] -= 1
                if self.games_left[k]:
                    observation, status = env.reset(), _NEXT_GAME
                else:
                    status = _FINISHED
            elif terminated or truncated:  # an environment may end an episode without a game end
                observation, status = env.reset(), _NEW_EPISODE
            else:
                status = _RUNNING
            lockstep.observations[i] = observation
            lockstep.rewards[i] = reward
            lockstep.statuses[i] = status
            lockstep.frames[i] = env.frames

    def close(self) -> None:
        for env in self.envs:
            env.close()

    def __enter__(self) -> _EnvGroup:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _worker(
    connection: Connection,
    config: Config,
    max_episode_frames: int,
    env_ids: list[int],
    seeds: list[int],
    games: list[int],
    buffers: dict[str, Any],
    layout: dict[str, Any],
) -> None:
    """A worker process: builds its environments, then runs the player's commands.

    Each command is answered with an empty message, or with the traceback of a failure.
    """
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the player's to handle
    try:
        group = _EnvGroup(
            config, max_episode_frames, env_ids, seeds, games, _Lockstep.over(buffers, layout)
        )
    except Exception:  # noqa: BLE001 - sent to the player, which raises it
        connection.send_bytes(traceback.format_exc().encode())
        return
    with group:
        connection.send_bytes(b"")
        while True:
            command = connection.recv_bytes()
            try:
                if command == b"step":
                    group.step()
                elif command == b"start":
                    group.start()
                else:
                    return
            except Exception:  # noqa: BLE001
                connection.send_bytes(traceback.format_exc().encode())
                return
            connection.send_bytes(b"")


def _process_context() -> multiprocessing.context.BaseContext:
    """Workers forked from a fresh server process that has imported this module once.

    Plain fork would copy the player's thread pools (torch, OpenCV) into a process that
    has no threads, a known cause of deadlocks; spawn would import torch in every worker
    (about 2 s each).
    """
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([__name__])
    return context


class _EnvWorkers:
    """Worker processes stepping the environments, env i on worker i mod `workers`.

    Observations, actions and rewards travel through shared memory; a pipe per worker
    carries only the commands and their acknowledgements.
    """

    def __init__(
        self,
        config: Config,
        max_episode_frames: int,
        seeds: Sequence[int],
        games: Sequence[int],
        layout: dict[str, Any],
        workers: int,
    ) -> None:
        context = _process_context()
        self.buffers = {
            name: context.RawArray("B", int(np.prod(shape)) * dtype.itemsize)
            for name, (shape, dtype) in layout.items()
        }
        self.lockstep = _Lockstep.over(self.buffers, layout)
        self.connections: list[Connection] = []
        self.processes: list[multiprocessing.process.BaseProcess] = []
        num_envs = len(seeds)
        try:
            for w in range(workers):
                player_end, worker_end = context.Pipe()
                process = context.Process(  # type: ignore[attr-defined]
                    target=_worker,
                    args=(
                        worker_end,
                        config,
                        max_episode_frames,
                        list(range(w, num_envs, workers)),
                        list(seeds),
                        list(games),
                        self.buffers,
                        layout,
                    ),  # fmt: skip
                    name=f"dqnlab-eval-{w}",
                    daemon=True,
                )
                process.start()
                worker_end.close()
                self.connections.append(player_end)
                self.processes.append(process)
            self._receive_all()  # every worker has built its environments
        except BaseException:
            self.close()
            raise

    def start(self) -> None:
        self._run(b"start")

    def step(self) -> None:
        self._run(b"step")

    def _run(self, command: bytes) -> None:
        for connection in self.connections:
            connection.send_bytes(command)
        self._receive_all()

    def _receive_all(self) -> None:
        for w, connection in enumerate(self.connections):
            try:
                reply = connection.recv_bytes()
            except EOFError:
                self.processes[w].join(timeout=1)
                raise DqnlabError(
                    f"evaluation worker {w} died (exit code {self.processes[w].exitcode})"
                ) from None
            if reply:
                raise DqnlabError(f"evaluation worker {w} failed:\n{reply.decode()}")

    def close(self) -> None:
        for connection in self.connections:
            with contextlib.suppress(OSError):  # a worker that died has closed its end
                connection.send_bytes(b"close")
        for process in self.processes:
            process.join(timeout=10)
            if process.is_alive():
                process.terminate()
                process.join()
        for connection in self.connections:
            connection.close()
        self.connections, self.processes = [], []

    def __enter__(self) -> _EnvWorkers:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _cpu_count() -> int:
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def default_workers(config: Config) -> int:
    """One worker process per core for Atari games, none (the player steps) otherwise.

    A Gymnasium environment is usually cheaper to step than a message to a process, and
    it may be registered by the user's code, which a worker process would not have run.
    """
    cores = _cpu_count()
    return cores if cores > 1 and is_atari(config.env) else 0


def default_num_envs(workers: int) -> int:
    """Environments in lockstep: enough to batch the forward pass and keep every worker
    busy (measured on 2 cores: 16 environments, see README), 8 with no workers."""
    return 8 * max(1, workers)


def _epsilon_greedy(q_values: np.ndarray, epsilon: float, rng: np.random.Generator) -> int:
    """`Agent.act` from Q-values already computed: the same choice, the same draws."""
    if rng.random() < epsilon:
        return int(rng.integers(len(q_values)))
    best = np.flatnonzero(q_values == q_values.max())
    return int(best[0] if len(best) == 1 else rng.choice(best))


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
) -> EvaluationResult:
    """Exactly `episodes` whole games at `epsilon`, on `num_envs` environments in lockstep.

    Environment i, seeded with child i of `seed`, plays games i, i + num_envs, ... each
    after its own no-op start, and the scores come back in game order: they depend on the
    seeds and `num_envs`, never on timing. Each lockstep is one forward pass over the
    stacked histories of the environments still playing, then `agent.act`'s choice for
    each of them in turn (the same draws from `agent.rng`), then one step of each. With
    one environment this is `play(..., max_episodes=episodes)`. `workers` processes step
    the environments (default `default_workers`; 0: the player steps them itself).
    """
    if episodes <= 0:
        raise ValueError(f"episodes must be positive, got {episodes}")
    if workers is None:
        workers = default_workers(config)
    if num_envs is None:
        num_envs = default_num_envs(workers)
    if num_envs <= 0 or workers < 0:
        raise ValueError(f"num_envs ({num_envs}) must be positive and workers ({workers}) >= 0")
    num_envs = min(num_envs, episodes)
    workers = min(workers, num_envs)
    seeds = derive_seeds(seed, num_envs)
    games = [len(range(i, episodes, num_envs)) for i in range(num_envs)]
    probe = make_env(config, training=False, seed=seeds[0], max_episode_frames=max_episode_frames)
    frame_shape, frame_dtype = probe.observation_shape, np.dtype(probe.observation_dtype)
    probe.close()
    layout = _Lockstep.layout(num_envs, frame_shape, frame_dtype)
    if workers:
        stepper: _EnvWorkers | _EnvGroup = _EnvWorkers(
            config, max_episode_frames, seeds, games, layout, workers
        )
        lockstep = stepper.lockstep
    else:
        buffers = {name: bytearray(int(np.prod(s)) * d.itemsize) for name, (s, d) in layout.items()}
        lockstep = _Lockstep.over(buffers, layout)
        stepper = _EnvGroup(config, max_episode_frames, range(num_envs), seeds, games, lockstep)
    with stepper:
        return _lockstep_play(agent, stepper, lockstep, config.history_length, epsilon, episodes)


def _lockstep_play(
    agent: Agent,
    stepper: _EnvWorkers | _EnvGroup,
    lockstep: _Lockstep,
    history_length: int,
    epsilon: float,
    episodes: int,
) -> EvaluationResult:
    num_envs = len(lockstep.statuses)
    frame_shape = lockstep.observations.shape[1:]
    dtype = lockstep.observations.dtype
    # Two sets of histories, written alternately: a push is one copy with no overlap.
    histories = np.zeros((2, num_envs, history_length, *frame_shape), dtype=dtype)
    batch = np.zeros((num_envs, history_length, *frame_shape), dtype=dtype)
    result = EvaluationResult(scores=[0.0] * episodes)
    game = list(range(num_envs))  # the game each environment is playing
    score = [0.0] * num_envs
    active = list(range(num_envs))
    active_index = np.arange(num_envs)
    start = time.perf_counter()
    stepper.start()
    current = 0
    histories[current, :, -1] = lockstep.observations
    while active:
        if len(active) == num_envs:
            inputs = histories[current]
        else:
            inputs = batch[: len(active)]
            np.take(histories[current], active_index, axis=0, out=inputs, mode="clip")
        q_values = agent.q_values(inputs)
        for row, i in enumerate(active):
            lockstep.actions[i] = _epsilon_greedy(q_values[row], epsilon, agent.rng)
        stepper.step()
        result.steps += len(active)
        previous, current = current, 1 - current
        np.copyto(histories[current, :, :-1], histories[previous, :, 1:])
        np.copyto(histories[current, :, -1], lockstep.observations)
        finished = False
        for i in active:
            score[i] += float(lockstep.rewards[i])
            status = lockstep.statuses[i]
            if status == _RUNNING:
                continue
            histories[current, i, :-1] = 0  # a new episode: zeros before its first frame
            if status == _NEW_EPISODE:
                continue
            result.scores[game[i]] = score[i]
            score[i] = 0.0
            game[i] += num_envs
            finished = finished or status == _FINISHED
        if finished:
            active = [i for i in active if lockstep.statuses[i] != _FINISHED]
            active_index = np.array(active, dtype=np.int64)
    result.seconds = time.perf_counter() - start
    result.frames = int(lockstep.frames.sum())
    return result


def load_run_config(run_dir: Path) -> Config:
    path = run_dir / CONFIG_FILE
    if not path.is_file():
        raise DqnlabError(f"{run_dir} is not a dqnlab run directory (no {CONFIG_FILE})")
    try:
        with path.open("rb") as handle:
            return config_from_dict(tomllib.load(handle))
    except tomllib.TOMLDecodeError as error:
        raise DqnlabError(f"{path} is not valid TOML: {error}") from None


def final_evaluation(
    run_dir: Path,
    checkpoint: str,
    episodes: int | None,
    seed: int,
    device: torch.device,
    *,
    num_envs: int | None = None,
) -> tuple[EvaluationResult, Config, Path]:
    """Nature's final protocol on a run's network: whole games of at most
    `final_eval_max_episode_frames`, at `eval_epsilon`, with random no-op starts.

    The games are played by `play_games` on `num_envs` environments in lockstep (None:
    `default_num_envs`), stepped on every core. The network is built from the
    configuration saved in the checkpoint itself, so a checkpoint file from another run
    evaluates with its own settings.
    """
    if checkpoint in ("best", "last"):
        load_run_config(run_dir)  # a clear error if RUN_DIR is not a run
        path = run_dir / "checkpoints" / f"{checkpoint}.pt"
    else:
        path = Path(checkpoint)
    payload = checkpoints.load(path, map_location=device)
    config = config_from_dict(payload["config"])
    weights = payload["network"] if "network" in payload else payload["agent"]["online"]
    count = episodes if episodes is not None else config.final_eval_episodes
    if count <= 0:
        raise DqnlabError(f"--episodes {count} must be positive")
    if num_envs is not None and num_envs <= 0:
        raise DqnlabError(f"num_envs {num_envs} must be positive")
    env_seed, agent_seed = derive_seeds(seed, 2)
    probe = make_env(config, training=False, seed=env_seed)  # for the network's shapes
    agent = build_agent(config, probe, device, agent_seed)
    probe.close()
    try:
        agent.online.load_state_dict(weights)
    except RuntimeError as error:
        raise DqnlabError(f"checkpoint {path} does not fit its network: {error}") from None
    result = play_games(
        agent,
        config,
        count,
        env_seed,
        epsilon=config.eval_epsilon,
        max_episode_frames=config.final_eval_max_episode_frames,
        num_envs=num_envs,
    )
    return result, config, path
