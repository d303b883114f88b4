"""The training loop: the algorithm's steps (`state.TrainingState.advance`, with the parts
the settings choose), and around them, each in a method of its own, what a run does
besides learning.

    for every step:      advance the algorithm one agent step (one per environment)
    a game ended:        log its raw score                               (_end_game)
    every eval period:   evaluate; keep the best, worst, evaluated nets  (_evaluate)
                         (or submit it to `background_eval`, recorded when it returns)
    every 1,000 steps:   check for NaN, log loss and frames/s, progress  (_report_progress)
    every digest period: a digest of the weights, compared after a kill  (digests.py)
    when due:            write a complete training checkpoint            (_checkpoint)
    on SIGINT/SIGTERM:   checkpoint, then stop                           (StopRequests)
    when on_evaluation says so after an evaluation: checkpoint, then stop (`dqnlab tune`)

With `num_envs` = N, one advance is N agent steps: a period's work happens after the
advance whose steps cross one of its multiples, at the step the advance ended on.
"""

from __future__ import annotations

import contextlib
import dataclasses
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from dqnlab.algorithm.agent import epsilon_at, recorded_network
from dqnlab.algorithm.heldout import HeldOutStatistics
from dqnlab.config import Config, config_fingerprint
from dqnlab.errors import DqnlabError
from dqnlab.run import rundir
from dqnlab.run.background_eval import BackgroundEvaluations, NetworkState
from dqnlab.run.checkpoints import CheckpointStore
from dqnlab.run.concurrent import training_state
from dqnlab.run.determinism import (
    apply_threads,
    arithmetic_fingerprint,
    busy_cores_warning,
    resume_arithmetic,
    resume_threads,
    resume_warning,
)
from dqnlab.run.digests import WeightDigests
from dqnlab.run.lease import RunLease, held
from dqnlab.run.logs import RunLogger
from dqnlab.run.play import EvaluationResult
from dqnlab.run.state import FinishedGame, check_disk
from dqnlab.run.wandb_log import WandbLog, import_wandb, uses_wandb

PROGRESS_PERIOD_STEPS = 1000  # NaN checks, TensorBoard scalars and the progress bar
RECENT_GAMES = 20  # games in the progress bar's mean score
STOPPED_BY_HOOK = "on_evaluation"  # TrainResult.interrupted when on_evaluation stopped the run
# Told each periodic evaluation's (step, mean) as it is recorded; True stops the run.
EvaluationHook = Callable[[int, float], bool]


@dataclass
class TrainResult:
    steps: int  # the run's, from its start (also before a resume)
    frames: int  # the run's training frames, from its start
    seconds: float  # this session's (since the resume, if one)
    learning_frames_per_second: float  # after replay start, evaluations included
    best_eval_mean: float
    evaluations: list[tuple[int, float]]
    session_frames: int  # training frames of this session
    interrupted: str | None = None  # the signal that stopped the run early, or STOPPED_BY_HOOK

    @property
    def frames_per_second(self) -> float:
        """This session's training frames over its time."""
        return self.session_frames / self.seconds if self.seconds > 0 else 0.0


@dataclass
class RunProgress:
    """The training loop's own bookkeeping, saved in every checkpoint."""

    best_mean: float = -float("inf")
    evaluations: list[tuple[int, float]] = field(default_factory=list)
    episodes: int = 0
    recent_scores: list[float] = field(default_factory=list)  # the last RECENT_GAMES games


class StopRequests:
    """SIGINT/SIGTERM ask the loop to finish its step, checkpoint and stop; a second one
    stops at once, unless it comes within SAME_REQUEST_SECONDS of the first: one request
    delivered twice (a signal to the process group that a parent also forwards, as
    `timeout`, make and batch schedulers do), not a user insisting."""

    SAME_REQUEST_SECONDS = 1.0

    def __init__(self) -> None:
        self.signal_name: str | None = None
        self._requested_at = 0.0
        self._previous: dict[int, Any] = {}

    def _handle(self, number: int, frame: Any) -> None:
        now = time.monotonic()
        if self.signal_name is None:
            self.signal_name, self._requested_at = signal.Signals(number).name, now
        elif now - self._requested_at >= self.SAME_REQUEST_SECONDS:
            raise KeyboardInterrupt

    def __enter__(self) -> StopRequests:
        if threading.current_thread() is threading.main_thread():
            for number in (signal.SIGINT, signal.SIGTERM):
                self._previous[number] = signal.signal(number, self._handle)
        return self

    def __exit__(self, *exc_info: object) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)


def train(
    config: Config,
    run_dir: Path,
    device: torch.device,
    progress: bool = True,
    tensorboard: bool = True,
    resume: bool = False,
    on_evaluation: EvaluationHook | None = None,
) -> TrainResult:
    """Train into `run_dir`: from scratch, or with `resume` from its newest complete
    checkpoint (the run directory created by the caller with `rundir.prepare_run_dir`),
    holding the run's lease (`lease.RunLease`) from start to end. `on_evaluation` is told
    each periodic evaluation's step and mean; when it returns True the run checkpoints and
    stops as a stop request stops it (`interrupted` = STOPPED_BY_HOOK): `dqnlab tune`
    prunes a trial so."""
    with held(run_dir) as lease:
        loop = TrainingLoop(config, run_dir, device, progress, tensorboard, resume, lease)
        loop.on_evaluation = on_evaluation
        return loop.run()


class TrainingLoop:
    """One session of a run: from its start or its newest checkpoint to its budget or a
    stop request."""

    on_evaluation: EvaluationHook | None = None  # see `train`
    hook_stop = False  # on_evaluation asked the run to stop
    arithmetic: str | None = None  # `_arithmetic`

    def __init__(
        self,
        config: Config,
        run_dir: Path,
        device: torch.device,
        progress: bool,
        tensorboard: bool,
        resume: bool,
        lease: RunLease | None = None,
    ) -> None:
        if uses_wandb(config):
            import_wandb()  # without the extra, one line now, before anything is built
        self.run_dir = run_dir
        self.lease = lease
        self.threads = apply_threads(config)  # before anything computes
        if not resume:
            _say(busy_cores_warning(self.threads, device))
        self.state = training_state(config, device)
        # The network `auto` chose, written out where it is one of the newer kinds.
        if resume:
            config = rundir.with_recorded_network(config, rundir.load_run_config(run_dir))
        else:
            config = dataclasses.replace(config, network=recorded_network(config, self.state.agent))
        self.config = config
        self.store = CheckpointStore(run_dir, keep=config.checkpoints_kept)
        self.fingerprint = config_fingerprint(config)
        self.progress = RunProgress()
        pending: list[dict[str, Any]] = []  # evaluations a checkpoint left in flight
        if resume:
            pending = self._restore(device)
        else:
            rundir.write_run_config(run_dir, config)
        check_disk(run_dir, self.state.replay)
        self._open_logs(tensorboard, self.state.steps if resume else None, pending)
        frames = self.state.frames
        self.saved_mark = self.state.replay.mark()
        self.saved_time = time.monotonic()
        self.recent_scores: deque[float] = deque(self.progress.recent_scores, maxlen=RECENT_GAMES)
        self.start, self.start_frames = time.perf_counter(), frames
        self.window_start, self.window_frames = self.start, frames  # frames/s window
        self.learning_since = (self.start, frames)  # time and frames when learning starts
        self.bar = tqdm(
            total=config.total_steps, initial=self.state.steps, disable=not progress,
            unit="step", smoothing=0.05,
        )  # fmt: skip
        evaluations = self.progress.evaluations
        self.last_eval_text = f"{evaluations[-1][1]:.1f}" if evaluations else "-"
        self.background: BackgroundEvaluations | None = None
        if config.periodic_eval == "background":
            self.background = BackgroundEvaluations(
                config, self._network_payload, self._record_evaluation, config.periodic_eval_workers
            )
            self.background.resubmit(pending)

    def _open_logs(
        self, tensorboard: bool, resume_step: int | None, pending: list[dict[str, Any]]
    ) -> None:
        """The run's CSV files, TensorBoard (and W&B) and the weights' digests, each
        carried on from `resume_step` (None: a new run)."""
        config, run_dir = self.config, self.run_dir
        self.logger = RunLogger(
            run_dir,
            tensorboard=tensorboard,
            resume_step=resume_step,
            evaluations_resume_step=pending[0]["step"] - 1 if pending else None,
            wandb_log=WandbLog(run_dir, config, resume_step) if uses_wandb(config) else None,
        )
        self.digests = WeightDigests(rundir.digests_path(run_dir), resume_step)

    def run(self) -> TrainResult:
        config, state = self.config, self.state
        interrupted = None
        with StopRequests() as stop, self.background or contextlib.nullcontext():
            while state.steps < config.total_steps:
                first, remaining = state.steps + 1, config.total_steps - state.steps
                # The last advance steps only the environments the budget has room for.
                short = remaining < len(state.envs)
                for game in state.advance(remaining) if short else state.advance():
                    self._end_game(game)
                step = state.steps
                evaluated = config.eval_period_steps > 0 and self._crosses(
                    first, step, config.eval_period_steps, after=True
                )
                if evaluated:
                    self._evaluate(step)
                if self.background is not None and self.background.pending:
                    self.background.record_done()
                if self._crosses(first, step, PROGRESS_PERIOD_STEPS):
                    self._report_progress(step)
                if config.digest_period_steps and self._crosses(
                    first, step, config.digest_period_steps
                ):
                    _say(self.digests.record(step, state.agent.online))
                if first <= config.replay_start_steps <= step:
                    self.learning_since = (time.perf_counter(), state.frames)
                stopping = stop.signal_name is not None or self.hook_stop
                if evaluated or stopping or self._checkpoint_due(first, step):
                    self._checkpoint(step)
                if stopping:
                    interrupted = stop.signal_name or STOPPED_BY_HOOK
                    break
                self.logger.keep_fresh()
            if interrupted is None and self.background is not None and self.background.pending:
                # The last checkpoint holds them as pending: a stop ends the wait.
                if self.background.record_all(lambda: stop.signal_name is not None):
                    self._checkpoint(state.steps)
                interrupted = stop.signal_name
        return self._finish(interrupted)

    # Phases --------------------------------------------------------------------------

    def _end_game(self, game: FinishedGame) -> None:
        """A training game ended (a whole game, not a life, in any environment): log its
        raw score, at the agent step it ended and the ε it was played at then."""
        self.progress.episodes += 1
        self.recent_scores.append(game.score)
        self.logger.episode(
            {
                "step": game.step,
                "frames": self.state.frames,
                "episode": self.progress.episodes,
                "score": game.score,
                "steps": game.steps,
                "epsilon": round(epsilon_at(game.step - 1, self.config), 6),
                "wall_seconds": round(time.perf_counter() - self.start, 3),
                "env": game.env,
            }
        )

    def _crosses(self, first: int, last: int, period: int, after: bool = False) -> bool:
        """Whether agent steps first..last hold a multiple of `period` (past replay start,
        with `after`): with one environment, whether step `last` is one."""
        multiple = last - last % period  # the last multiple up to `last`
        return multiple >= first and not (after and multiple <= self.config.replay_start_steps)

    def _evaluate(self, step: int) -> None:
        """A periodic evaluation: its mean decides the best network, and the networks kept
        for inspection (`rundir.keep_evaluated_network`)."""
        self.logger.keep_fresh(at_once=True)
        state = self.state
        state.check_finite()
        if self.background is not None:  # recorded when it comes back
            heldout = state.heldout_statistics()
            self.background.submit(step, state.frames, state.agent.online, heldout)
            return
        result = state.evaluate()
        heldout = state.heldout_statistics()
        self._record_evaluation(step, state.frames, result, heldout, state.agent.online)

    def _record_evaluation(
        self,
        step: int,
        frames: int,
        result: EvaluationResult,
        heldout: HeldOutStatistics | None,
        network: torch.nn.Module | NetworkState,
    ) -> None:
        """An evaluation's result, whichever way it was played."""
        mean = _periodic_mean(result)
        progress = self.progress
        payload = self._network_payload(step, mean, network)
        if mean > progress.best_mean:
            progress.best_mean = mean
            rundir.save_network(rundir.network_path(self.run_dir, "best"), payload)
        rundir.keep_evaluated_network(
            self.run_dir, self.config, progress.evaluations, step, mean, payload
        )
        progress.evaluations.append((step, mean))
        self.logger.evaluation(
            {
                "step": step,
                "frames": frames,
                "mean": mean,
                "std": result.std,
                "episodes": len(result.scores),
                "steps": result.steps,
                "best_mean": progress.best_mean,
                "frames_per_second": round(result.frames_per_second, 1),
                "wall_seconds": round(time.perf_counter() - self.start, 3),
                "heldout_max_q": None if heldout is None else heldout.max_q,
                "heldout_td_error": None if heldout is None else heldout.td_error,
            }
        )
        self.last_eval_text = f"{mean:.1f}"
        if self.on_evaluation is not None and self.on_evaluation(step, mean):
            self.hook_stop = True

    def _report_progress(self, step: int) -> None:
        """Every PROGRESS_PERIOD_STEPS: catch NaN where the update does not (on a GPU),
        log loss, epsilon and frames/s, move the progress bar."""
        state = self.state
        if not state.check_every_update:
            state.check_finite()
        now, frames = time.perf_counter(), state.frames
        frames_per_second = (frames - self.window_frames) / (now - self.window_start)
        self.window_start, self.window_frames = now, frames
        scalars = {"train/epsilon": state.epsilon, "train/frames_per_second": frames_per_second}
        loss = state.mean_loss()
        if loss is not None:
            scalars["train/loss"] = loss
        self.logger.scalars(step, scalars)
        if not self.bar.disable:
            self.bar.update(step - self.bar.n)
            self.bar.set_postfix(
                fps=f"{frames_per_second:.0f}",
                eps=f"{state.epsilon:.3f}",
                score=f"{np.mean(self.recent_scores):.1f}" if self.recent_scores else "-",
                eval=self.last_eval_text,
                refresh=False,
            )

    def _checkpoint_due(self, first: int, step: int) -> bool:
        """At the end of the budget, every `checkpoint_period_steps` and every
        `checkpoint_period_minutes` (besides every evaluation and a stop request)."""
        config = self.config
        period = config.checkpoint_period_steps
        return (
            step == config.total_steps
            or (period > 0 and self._crosses(first, step, period))
            or time.monotonic() - self.saved_time >= config.checkpoint_period_minutes * 60
        )

    def _arithmetic(self) -> str | None:
        """This process's arithmetic fingerprint, computed once (on the CPU only)."""
        if self.arithmetic is None and self.state.agent.device.type == "cpu":
            self.arithmetic = arithmetic_fingerprint()
        return self.arithmetic

    def _checkpoint(self, step: int) -> None:
        """A complete training checkpoint (only the replay chunks written since the last
        one), then last.pt. A failure stops the run, or with `on_checkpoint_error =
        "continue"` is reported and training goes on. A run whose lease another process
        took over stops here, before writing (LeaseLost)."""
        if self.lease is not None:
            self.lease.check()
        state, replay = self.state, self.state.replay
        state.check_finite()
        self.progress.recent_scores = list(self.recent_scores)
        self.logger.flush()
        changed = replay.written_since(self.saved_mark)
        # "learner": the key of the training state in checkpoints written since the first.
        saved: dict[str, Any] = {
            "learner": state.state_dict(),
            "run": dataclasses.asdict(self.progress),
            "threads": self.threads,  # the CPU's arithmetic depends on it: a resume keeps it
            "arithmetic": self._arithmetic(),  # and on the processor: a resume elsewhere says so
        }
        if self.background is not None:  # played again by a resumed run
            saved["pending_evaluations"] = self.background.state_dict()
        try:
            self.store.save(step, saved, replay.arrays, changed, self.fingerprint)
            rundir.save_network(
                rundir.network_path(self.run_dir, "last"), self._network_payload(step)
            )
        except (DqnlabError, OSError) as error:
            if self.config.on_checkpoint_error == "stop":
                raise DqnlabError(f"checkpoint at step {step} failed: {error}") from None
            tqdm.write(f"dqnlab: warning: checkpoint at step {step} failed, training goes on: "
                       f"{error}")  # fmt: skip
            return
        self.saved_mark = replay.mark()
        self.saved_time = time.monotonic()

    def _restore(self, device: torch.device) -> list[dict[str, Any]]:
        """Carry on from the newest complete checkpoint, if there is one, with the thread
        count it was written with; returns the background evaluations it left pending."""
        replay = self.state.replay
        # Loaded into host memory whatever the device: the state's load_state_dict copies
        # each tensor where it belongs (weights and optimizer state onto the device; random
        # states, frame histories and screens stay on the host, where NumPy reads them).
        loaded = self.store.latest(self.fingerprint, into=replay.arrays, map_location="cpu")
        replay.upload()
        _say(resume_warning(self.config, device))
        if loaded is not None:
            _say(resume_threads(self.config, device, loaded.state.get("threads")))
            self.threads = torch.get_num_threads()
            self.arithmetic = None  # this process's, at the count taken back
            _say(resume_arithmetic(device, loaded.state.get("arithmetic"), self._arithmetic()))
            self.state.load_state_dict(loaded.state["learner"])
            self.progress = RunProgress(**loaded.state["run"])
            return list(loaded.state.get("pending_evaluations", []))
        return []

    def _finish(self, interrupted: str | None) -> TrainResult:
        state = self.state
        self.bar.update(state.steps - self.bar.n)
        self.bar.close()
        end = time.perf_counter()
        learning_seconds = end - self.learning_since[0]
        learning_frames = state.frames - self.learning_since[1]
        best = rundir.network_path(self.run_dir, "best")
        if not best.exists():
            # No periodic evaluation happened (a very short run): the final network stands in.
            rundir.save_network(best, self._network_payload(state.steps, float("nan")))
        self.logger.close()
        self.digests.close()
        state.close()
        return TrainResult(
            steps=state.steps,
            frames=state.frames,
            seconds=end - self.start,
            learning_frames_per_second=learning_frames / learning_seconds
            if learning_seconds
            else 0.0,
            best_eval_mean=self.progress.best_mean,
            evaluations=self.progress.evaluations,
            session_frames=state.frames - self.start_frames,
            interrupted=interrupted,
        )

    def _network_payload(
        self,
        step: int,
        eval_mean: float | None = None,
        network: torch.nn.Module | NetworkState | None = None,
    ) -> dict[str, Any]:
        """A network file: of the online network, or of `network` (a snapshot)."""
        env = self.state.env
        return rundir.network_payload(
            self.config,
            (self.config.history_length, *env.observation_shape),
            env.observation_dtype,
            env.action_names,
            step,
            self.state.agent.online if network is None else network,
            eval_mean,
            self.state.agent.observation_layout,
        )


def _say(message: str | None) -> None:
    """A warning or note on stderr, clear of the progress bar; nothing for None."""
    if message:
        tqdm.write(message, file=sys.stderr)


def _periodic_mean(result: EvaluationResult) -> float:
    """Mean raw score of the games finished within the budget, 0 if none finished
    (Lua train_agent.lua: total_reward / max(1, nepisodes))."""
    return result.mean if result.scores else 0.0
