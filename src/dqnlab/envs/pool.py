"""Environments in lockstep, stepped in this process or by worker processes.

The final evaluation (`lockstep.play_games`) acts for many environments at once; this
module holds the environments' side: what each environment did in its last step, laid out
in shared memory, and the worker processes that step them, one per core.

This module and what it imports must not import torch: the forkserver and every worker
import it, and torch would cost each of them seconds to import and hundreds of MB
resident.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import signal
import traceback
from collections.abc import Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from dqnlab.config import Config
from dqnlab.envs import Environment, make_env
from dqnlab.errors import DqnlabError

# What an environment did in its last step (one byte per environment).
RUNNING = 0  # its episode goes on: push the observation on its history
NEW_EPISODE = 1  # reset (a game start, or an episode that ended without a game end)
NEXT_GAME = 2  # a game ended and the environment started its next game
FINISHED = 3  # a game ended and the environment has no game left: it stops stepping

Layout = dict[str, tuple[tuple[int, ...], np.dtype]]


@dataclass
class Lockstep:
    """What the player and the environments exchange, one row per environment."""

    actions: np.ndarray  # (envs,) int64, written by the player
    observations: np.ndarray  # (envs, *frame_shape): each environment's newest observation
    rewards: np.ndarray  # (envs,) float64: raw reward of the last step
    statuses: np.ndarray  # (envs,) uint8: RUNNING ... FINISHED
    frames: np.ndarray  # (envs,) int64: raw frames emulated so far, no-ops included

    @staticmethod
    def layout(num_envs: int, frame_shape: tuple[int, ...], frame_dtype: np.dtype) -> Layout:
        return {
            "actions": ((num_envs,), np.dtype(np.int64)),
            "observations": ((num_envs, *frame_shape), np.dtype(frame_dtype)),
            "rewards": ((num_envs,), np.dtype(np.float64)),
            "statuses": ((num_envs,), np.dtype(np.uint8)),
            "frames": ((num_envs,), np.dtype(np.int64)),
        }

    @staticmethod
    def buffers(layout: Layout) -> dict[str, bytearray]:
        """Private memory for the layout (environments stepped in the player's process)."""
        return {name: bytearray(_nbytes(shape, dtype)) for name, (shape, dtype) in layout.items()}

    @classmethod
    def over(cls, buffers: dict[str, Any], layout: Layout) -> Lockstep:
        """Arrays over `buffers` (bytes-like objects, shared memory included)."""
        arrays = {}
        for name, (shape, dtype) in layout.items():
            count = int(np.prod(shape))
            arrays[name] = np.frombuffer(buffers[name], dtype=dtype, count=count).reshape(shape)
        return cls(**arrays)


def _nbytes(shape: tuple[int, ...], dtype: np.dtype) -> int:
    return int(np.prod(shape)) * dtype.itemsize


class EnvGroup:
    """Some of the environments, each with the number of games it has to play.

    The player acts for the environments in `batches` (ranges of environment ids), one
    forward pass each; `step(k)` steps this group's environments of batch k.
    """

    def __init__(
        self,
        config: Config,
        max_episode_frames: int,
        env_ids: Sequence[int],
        seeds: Sequence[int],
        games: Sequence[int],
        batches: Sequence[range],
        lockstep: Lockstep,
    ) -> None:
        self.envs: dict[int, Environment] = {}
        try:
            for i in env_ids:
                self.envs[i] = make_env(
                    config, training=False, seed=seeds[i], max_episode_frames=max_episode_frames
                )
        except BaseException:
            self.close()
            raise
        self.games_left = {i: games[i] for i in env_ids}
        self.batches = [[i for i in batch if i in self.envs] for batch in batches]
        self.lockstep = lockstep

    def start(self) -> None:
        """A new game on every environment."""
        lockstep = self.lockstep
        for i, env in self.envs.items():
            lockstep.observations[i] = env.reset(new_game=True)
            lockstep.rewards[i] = 0.0
            lockstep.statuses[i] = NEW_EPISODE
            lockstep.frames[i] = env.frames

    def step(self, batch: int) -> None:
        """One step of each environment of the batch with a game left, then its reset if
        needed (as in `play`: the next game starts right after a game end, with no-ops)."""
        lockstep = self.lockstep
        for i in self.batches[batch]:
            if not self.games_left[i]:
                continue
            env = self.envs[i]
            observation, reward, terminated, truncated = env.step(int(lockstep.actions[i]))
            if env.game_ended:
                self.games_left[i] -= 1
                if self.games_left[i]:
                    observation, status = env.reset(), NEXT_GAME
                else:
                    status = FINISHED
            elif terminated or truncated:  # an environment may end an episode without a game end
                observation, status = env.reset(), NEW_EPISODE
            else:
                status = RUNNING
            lockstep.observations[i] = observation
            lockstep.rewards[i] = reward
            lockstep.statuses[i] = status
            lockstep.frames[i] = env.frames

    # The player's interface, shared with EnvWorkers: here a step is done when submitted.
    def submit(self, batch: int) -> None:
        self.step(batch)

    def wait(self) -> None:
        pass

    def close(self) -> None:
        for env in self.envs.values():
            env.close()

    def __enter__(self) -> EnvGroup:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


_START = b"start"
_CLOSE = b"close"


def _worker(
    connection: Connection, group_arguments: dict[str, Any], buffers: dict, layout: Layout
) -> None:
    """A worker process: builds its environments, then runs the player's commands in order
    (start, a batch index to step, close). Each command is answered with an empty message,
    or with the traceback of a failure."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the player's to handle
    try:
        group = EnvGroup(**group_arguments, lockstep=Lockstep.over(buffers, layout))
    except Exception:  # noqa: BLE001 - sent to the player, which raises it
        connection.send_bytes(traceback.format_exc().encode())
        return
    with group, contextlib.suppress(BrokenPipeError, ConnectionResetError, EOFError):
        # Suppressed: the player is gone (killed), so there is no one to answer.
        connection.send_bytes(b"")
        while True:
            command = connection.recv_bytes()
            try:
                if command == _CLOSE:
                    return
                if command == _START:
                    group.start()
                else:
                    group.step(command[0])
            except Exception:  # noqa: BLE001
                connection.send_bytes(traceback.format_exc().encode())
                return
            connection.send_bytes(b"")


def process_context() -> multiprocessing.context.BaseContext:
    """Workers forked from a fresh server process that has imported this module once.

    Plain fork would copy the player's thread pools (torch, OpenCV) into a process that
    has no threads, a known cause of deadlocks; spawn would import this module's
    dependencies in every worker. Like spawn, it imports the main module again in each
    worker (not a package's `__main__`: `python -m` skips it), so a script must guard its
    top level with `if __name__ == "__main__":`, and what it imports there, each worker
    imports too (the `dqnlab` command's script imports only the command line).
    """
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = multiprocessing.get_context("forkserver")
    # Only effective before this process's forkserver starts (it starts once, on first use).
    context.set_forkserver_preload([__name__])
    return context


class EnvWorkers:
    """Worker processes stepping the environments, env i on worker i mod `workers`.

    Observations, actions and rewards travel through shared memory; a pipe per worker
    carries the commands and their acknowledgements. Commands queue up: the player can
    submit a batch, act for another while the workers step it, then wait.
    """

    def __init__(
        self,
        config: Config,
        max_episode_frames: int,
        seeds: Sequence[int],
        games: Sequence[int],
        batches: Sequence[range],
        layout: Layout,
        workers: int,
    ) -> None:
        context = process_context()
        self.buffers = {
            name: context.RawArray("B", _nbytes(shape, dtype))
            for name, (shape, dtype) in layout.items()
        }
        self.lockstep = Lockstep.over(self.buffers, layout)
        self.connections: list[Connection] = []
        self.processes: list[multiprocessing.process.BaseProcess] = []
        num_envs = len(seeds)
        try:
            for w in range(workers):
                group_arguments = {
                    "config": config,
                    "max_episode_frames": max_episode_frames,
                    "env_ids": list(range(w, num_envs, workers)),
                    "seeds": list(seeds),
                    "games": list(games),
                    "batches": list(batches),
                }
                player_end, worker_end = context.Pipe()
                process = context.Process(  # type: ignore[attr-defined]
                    target=_worker,
                    args=(worker_end, group_arguments, self.buffers, layout),
                    name=f"dqnlab-eval-{w}",
                    daemon=True,
                )
                process.start()
                worker_end.close()
                self.connections.append(player_end)
                self.processes.append(process)
            self.wait()  # every worker has built its environments
        except BaseException:
            self.close()
            raise

    def start(self) -> None:
        self._send(_START)
        self.wait()

    def submit(self, batch: int) -> None:
        self._send(bytes((batch,)))

    def _send(self, command: bytes) -> None:
        for connection in self.connections:
            # A worker that failed sent its error and closed its end: `wait` reports it.
            with contextlib.suppress(BrokenPipeError):
                connection.send_bytes(command)

    def wait(self) -> None:
        """Wait for the oldest submitted command to be done by every worker."""
        for w, connection in enumerate(self.connections):
            try:
                reply = connection.recv_bytes()
            except EOFError:
                self.processes[w].join(timeout=1)
                raise DqnlabError(
                    f"evaluation worker {w} died (exit code {self.processes[w].exitcode}); "
                    "if its error says the main module is being imported, guard your "
                    'script with `if __name__ == "__main__":`'
                ) from None
            if reply:
                raise DqnlabError(f"evaluation worker {w} failed:\n{reply.decode()}")

    def close(self) -> None:
        for connection in self.connections:
            with contextlib.suppress(OSError):  # a worker that died has closed its end
                connection.send_bytes(_CLOSE)
        for process in self.processes:
            process.join(timeout=10)
            if process.is_alive():
                process.terminate()
                process.join()
        for connection in self.connections:
            connection.close()
        self.connections, self.processes = [], []

    def __enter__(self) -> EnvWorkers:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
