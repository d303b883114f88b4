"""Periodic evaluations played while training goes on (`periodic_eval = "background"`).

The inline evaluation (`TrainingState.evaluate`) pauses training for `eval_steps` agent
steps and draws its ε-greedy choices from the agent's own generator, the one training
draws from, on an evaluation environment that carries on from one evaluation to the
next: as DeepMind's Lua code did (train_agent.lua), so each evaluation also moves
training's random stream. Here an evaluation plays a snapshot of the online network,
taken at its step, in a worker process with one torch thread, with the same protocol
(`play`: `eval_steps` agent steps, the finished games count), a generator and a fresh
environment of its own, both seeded from the run's seed and the step
(`evaluation_seed`). So its result is a function of the run alone, whatever the timing,
the worker count, or a resume in between; training no longer shares its generator, so
its trajectory differs from an inline run's.

Results are recorded in step order (`record_done`). A checkpoint does not wait for them:
it saves the evaluations still pending (their step, training frames, held-out figures
and the snapshot's weights, `state_dict`), and a resumed run plays them again.
"""

from __future__ import annotations

import contextlib
import io
import json
import multiprocessing
import os
import random
import signal
import sys
import threading
import traceback
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dqnlab.algorithm.heldout import HeldOutStatistics
from dqnlab.config import Config
from dqnlab.envs import make_env
from dqnlab.envs.pool import process_context
from dqnlab.errors import DqnlabError
from dqnlab.run import rundir
from dqnlab.run.determinism import apply_threads
from dqnlab.run.lockstep import torch_threads
from dqnlab.run.play import EvaluationResult, play

NetworkState = dict[str, torch.Tensor]
# What the training loop does with a result: (step, training frames, result, held-out
# figures, weights) -> evaluations.csv, the best network (`TrainingLoop._record_evaluation`).
Record = Callable[[int, int, EvaluationResult, HeldOutStatistics | None, NetworkState], None]
# A network file's contents (`rundir.network_payload`) from (step, eval mean, weights).
PayloadOf = Callable[[int, float | None, NetworkState], dict[str, Any]]
_CLOSE = b"close"
_ERROR = b"!"


def evaluation_seed(run_seed: int, step: int) -> int:
    """Seeds the background evaluation at `step`: child 0 of it its environment, child 1
    its generator (`rundir.agent_from_network`, as a final evaluation splits its seed)."""
    return int(np.random.SeedSequence([run_seed, step]).generate_state(1)[0])


def evaluate_snapshot(payload: dict[str, Any], seed: int) -> EvaluationResult:
    """One periodic evaluation of a network file's contents, on CPU with one torch thread
    (the same arithmetic wherever it runs): `play` for `eval_steps` agent steps at
    `eval_epsilon`, on a new environment, with a generator, both seeded from `seed`."""
    values = dict(payload["config"])
    # How the network was trained, not how it plays: an agent on CPU refuses a CUDA graph.
    values.update(compile_update=False, update_graph="off")
    payload = {**payload, "config": values}
    agent, config, env_seed = rundir.agent_from_network(
        payload, Path("<snapshot>"), seed, torch.device("cpu")
    )
    env = make_env(
        config, training=False, seed=env_seed, max_episode_frames=config.eval_max_episode_frames
    )
    try:
        with torch_threads(1):
            return play(
                agent, env, config.history_length, config.eval_epsilon, max_steps=config.eval_steps
            )
    finally:
        env.close()


@dataclass
class PendingEvaluation:
    """An evaluation submitted and not yet handed back: what the training loop records
    with its result (`TrainingLoop._record_evaluation`)."""

    step: int
    frames: int  # training frames at `step`
    network: NetworkState  # the online network's weights at `step`, on CPU
    heldout: HeldOutStatistics | None  # taken at `step`, on the training thread

    def state_dict(self) -> dict[str, Any]:
        heldout = self.heldout
        return {
            "step": self.step,
            "frames": self.frames,
            "network": self.network,
            "heldout_max_q": None if heldout is None else heldout.max_q,
            "heldout_td_error": None if heldout is None else heldout.td_error,
        }

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> PendingEvaluation:
        max_q, td_error = state["heldout_max_q"], state["heldout_td_error"]
        heldout = None if max_q is None else HeldOutStatistics(float(max_q), float(td_error))
        return cls(int(state["step"]), int(state["frames"]), dict(state["network"]), heldout)


class BackgroundEvaluations:
    """`workers` processes playing periodic evaluations one at a time each (0: played
    in this process at submission, with the same results); a context manager that ends
    them. `payload_of` builds the network file a worker is sent; `record` takes each
    result, in step order."""

    def __init__(self, config: Config, payload_of: PayloadOf, record: Record, workers: int) -> None:
        self.seed = config.seed
        self.payload_of = payload_of
        self.record = record
        self.pending: list[PendingEvaluation] = []  # in step order, not yet handed back
        self._results: dict[int, EvaluationResult] = {}
        self._queue: deque[PendingEvaluation] = deque()  # waiting for a free worker
        self._workers: list[_Worker] = []
        self._warned = False  # that evaluations fall behind training
        try:
            for index in range(workers):
                self._workers.append(_Worker(config, index))
            for worker in self._workers:
                worker.receive()  # built its environment: a failure shows now, not later
        except BaseException:
            self.close()
            raise

    def submit(
        self, step: int, frames: int, network: torch.nn.Module, heldout: HeldOutStatistics | None
    ) -> None:
        """Evaluate the online network as it is at `step` (its weights copied now)."""
        weights = {
            name: tensor.detach().to("cpu", copy=True)
            for name, tensor in network.state_dict().items()
        }
        self._submit(PendingEvaluation(step, frames, weights, heldout))

    def resubmit(self, states: list[dict[str, Any]]) -> None:
        """The evaluations a checkpoint saved as pending (`state_dict`), submitted again."""
        for state in states:
            self._submit(PendingEvaluation.from_state_dict(state))

    def _submit(self, evaluation: PendingEvaluation) -> None:
        if self.pending and evaluation.step <= self.pending[-1].step:
            raise ValueError(f"evaluation of step {evaluation.step} after {self.pending[-1].step}")
        self.pending.append(evaluation)
        if self._workers:
            self._queue.append(evaluation)
            self._dispatch()
            if len(self._queue) > 1 and not self._warned:
                self._warned = True
                print(
                    f"dqnlab: {len(self.pending)} periodic evaluations in flight at step "
                    f"{evaluation.step}: they take longer than training between them; "
                    "more periodic_eval_workers would keep up (the run waits for them at "
                    "its end)",
                    file=sys.stderr,
                )
        else:
            self._results[evaluation.step] = self._play_here(evaluation)

    def _play_here(self, evaluation: PendingEvaluation) -> EvaluationResult:
        """Played in this process, leaving its random streams as they were (building the
        network draws initial weights from torch's)."""
        payload = self.payload_of(evaluation.step, None, evaluation.network)
        python_state = random.getstate()
        with torch.random.fork_rng(devices=[]):
            result = evaluate_snapshot(payload, evaluation_seed(self.seed, evaluation.step))
        random.setstate(python_state)
        return result

    def _dispatch(self) -> None:
        for worker in self._workers:
            if worker.step is None and self._queue:
                evaluation = self._queue.popleft()
                seed = evaluation_seed(self.seed, evaluation.step)
                payload = self.payload_of(evaluation.step, None, evaluation.network)
                worker.send(evaluation.step, seed, payload)

    def record_done(self, timeout: float = 0.0) -> None:
        """Record the evaluations whose results are in and follow no pending one, in step
        order, after waiting up to `timeout` seconds for a worker to finish one."""
        busy = {worker.connection: worker for worker in self._workers if worker.step is not None}
        if busy:
            for connection in wait(list(busy), timeout):
                worker = busy[connection]  # type: ignore[index]
                step = worker.step
                assert step is not None
                self._results[step] = worker.receive()
            self._dispatch()
        while self.pending and self.pending[0].step in self._results:
            evaluation = self.pending[0]
            result = self._results[evaluation.step]
            self.record(
                evaluation.step, evaluation.frames, result, evaluation.heldout, evaluation.network
            )
            del self.pending[0], self._results[evaluation.step]  # recorded: no longer pending

    def record_all(self, stopped: Callable[[], bool]) -> bool:
        """Wait for every pending evaluation and record it, unless `stopped()` first;
        whether all were recorded."""
        while self.pending and not stopped():
            self.record_done(timeout=0.2)
        return not self.pending

    def state_dict(self) -> list[dict[str, Any]]:
        """The pending evaluations, for a checkpoint (tensors and plain values only)."""
        return [evaluation.state_dict() for evaluation in self.pending]

    def close(self) -> None:
        """End the workers: idle ones when told, busy ones at once."""
        for worker in self._workers:
            worker.close()
        self._workers = []

    def __enter__(self) -> BackgroundEvaluations:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


class _Worker:
    """One worker process and the evaluation it is playing (`step`, None when idle)."""

    def __init__(self, config: Config, index: int) -> None:
        context = process_context()
        self.connection, worker_end = context.Pipe()
        # Never written: the worker sees it end when this process does, killed or not.
        lifeline, self.lifeline = context.Pipe(duplex=False)
        self.process: multiprocessing.process.BaseProcess = context.Process(  # type: ignore[attr-defined]
            target=_worker,
            args=(worker_end, lifeline, config),
            name=f"dqnlab-periodic-eval-{index}",
            daemon=True,
        )
        self.process.start()
        worker_end.close()
        lifeline.close()
        self.index = index
        self.step: int | None = None

    def send(self, step: int, seed: int, payload: dict[str, Any]) -> None:
        buffer = io.BytesIO()
        torch.save(payload, buffer)
        header = step.to_bytes(8, "little") + seed.to_bytes(8, "little")
        self.connection.send_bytes(header + buffer.getvalue())
        self.step = step

    def receive(self) -> EvaluationResult:
        """The reply to the last message: a result (after the first, the worker's start)."""
        try:
            reply = self.connection.recv_bytes()
        except EOFError:
            self.process.join(timeout=1)
            raise DqnlabError(
                f"periodic_eval = 'background': evaluation worker {self.index} died (exit "
                f"code {self.process.exitcode})"
            ) from None
        step, self.step = self.step, None
        if reply.startswith(_ERROR):  # the traceback's last line: the error itself
            error = reply[1:].decode().strip().splitlines()[-1]
            if step is not None:
                what = f"the evaluation of step {step}: {error}"
            else:  # building the environment
                what = (
                    f"its start: {error} (an environment your script registers is unknown "
                    "to the worker: name it module:Env-id, or use periodic_eval = 'inline')"
                )
            raise DqnlabError(
                f"periodic_eval = 'background': evaluation worker {self.index} failed in {what}"
            )
        return EvaluationResult(**json.loads(reply)) if reply else EvaluationResult()

    def close(self) -> None:
        if self.step is None:
            with contextlib.suppress(OSError):  # a worker that died has closed its end
                self.connection.send_bytes(_CLOSE)
            self.process.join(timeout=10)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join()
        self.connection.close()
        self.lifeline.close()


def _worker(connection: Connection, lifeline: Connection, config: Config) -> None:
    """A worker process: builds the evaluation environment once (a failure is reported at
    once), then plays each evaluation it is sent and replies with its result as JSON.

    Signals to the training's process group (Ctrl-C, `timeout`'s SIGTERM) are the training
    process's to handle: it checkpoints, then ends this worker. A training process killed
    outright ends it through `lifeline`."""
    os.setsid()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    threading.Thread(target=_exit_with, args=(lifeline,), daemon=True).start()
    apply_threads(replace(config, threads=1))  # one thread, set as a run sets it
    try:
        make_env(config, training=False, seed=0).close()
    except Exception:  # noqa: BLE001 - sent to the training process, which raises it
        connection.send_bytes(_ERROR + traceback.format_exc().encode())
        return
    connection.send_bytes(b"")
    while True:
        try:
            message = connection.recv_bytes()
        except EOFError:  # the training process is gone
            return
        if message == _CLOSE:
            return
        seed = int.from_bytes(message[8:16], "little")
        try:
            payload = torch.load(io.BytesIO(message[16:]), map_location="cpu", weights_only=True)
            result = evaluate_snapshot(payload, seed)
        except Exception:  # noqa: BLE001
            connection.send_bytes(_ERROR + traceback.format_exc().encode())
            return
        connection.send_bytes(json.dumps(asdict(result)).encode())


def _exit_with(lifeline: Connection) -> None:
    """End this process when the training process has gone (the pipe's end is closed)."""
    with contextlib.suppress(EOFError, OSError):
        lifeline.recv_bytes()
    os._exit(1)
