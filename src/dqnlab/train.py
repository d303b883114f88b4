"""The training loop: the Nature DQN algorithm, one agent step at a time.

Per step (Nature's Algorithm 1; DeepMind's Lua code with the same timings): act
epsilon-greedily with the network just updated, repeat the action in the environment,
store the transition, then every `update_period_steps` (once past `replay_start_steps`)
take one gradient step, and every `target_update_steps` copy the online network into the
target network. Every `eval_period_steps` the network is evaluated and the best one kept.
"""

from __future__ import annotations

import dataclasses
import random
import shutil
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from time import perf_counter
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from dqnlab import checkpoints
from dqnlab.agent import build_agent, epsilon_at
from dqnlab.checkpoints import CheckpointStore, written_slots
from dqnlab.config import (
    RESUMABLE_CHANGES,
    Config,
    config_fingerprint,
    config_to_toml,
    derive_seeds,
)
from dqnlab.envs import make_env
from dqnlab.errors import DqnlabError, ResourceError
from dqnlab.evaluate import CONFIG_FILE, EvaluationResult, load_run_config, play
from dqnlab.logs import RunLogger
from dqnlab.replay import FrameHistory, ReplayMemory, check_memory


def prepare_run_dir(run_dir: Path, force: bool, config: Config | None = None) -> bool:
    """Make `run_dir` ready for `config`; True when it holds the same run, to be resumed.

    An existing run with the same settings (the step budget may differ) is resumed; one
    with other settings is refused unless `force`, which deletes it. Only a directory
    holding a dqnlab run (its config.toml) is ever deleted, so a mistyped
    `--run-dir . --force` cannot wipe a project.
    """
    if run_dir.exists() and not run_dir.is_dir():
        raise DqnlabError(f"--run-dir {run_dir} exists and is not a directory")
    if run_dir.exists() and any(run_dir.iterdir()):
        is_run = (run_dir / CONFIG_FILE).is_file()
        if force and is_run:
            shutil.rmtree(run_dir)
        elif force:
            raise DqnlabError(
                f"--force refuses to delete {run_dir}: it is not a dqnlab run directory "
                f"(no {CONFIG_FILE}); choose an empty or new --run-dir"
            )
        elif is_run and config is not None:
            saved = load_run_config(run_dir)
            if config_fingerprint(saved) == config_fingerprint(config):
                if saved != config:  # a new budget or checkpoint cadence
                    (run_dir / CONFIG_FILE).write_text(config_to_toml(config))
                return True
            differing = [
                name
                for name, value in config.to_dict().items()
                if name not in RESUMABLE_CHANGES and saved.to_dict()[name] != value
            ]
            raise DqnlabError(
                f"run directory {run_dir} holds a run with other settings "
                f"({', '.join(differing)}); continue it with `dqnlab resume {run_dir}`, "
                "choose another --run-dir, or pass --force to delete it and start over"
            )
        else:
            raise DqnlabError(
                f"run directory {run_dir} already exists and is not empty; "
                "choose another --run-dir or pass --force to overwrite it"
            )
    run_dir.mkdir(parents=True, exist_ok=True)
    return False


@dataclass
class TrainResult:
    steps: int  # the run's, from its start (also before a resume)
    frames: int  # the run's training frames, from its start
    seconds: float  # this session's (since the resume, if one)
    learning_frames_per_second: float  # after replay start, evaluations included
    best_eval_mean: float
    evaluations: list[tuple[int, float]]
    session_frames: int  # training frames of this session
    interrupted: str | None = None  # the signal that stopped the run early

    @property
    def frames_per_second(self) -> float:
        """This session's training frames over its time."""
        return self.session_frames / self.seconds if self.seconds > 0 else 0.0


TIMED_PARTS = ("env", "act", "store", "sample", "update")


class TrainingDiverged(DqnlabError):
    """The loss or the weights stopped being finite."""


class Learner:
    """The whole learning state of a run: environments, agent, replay memory, step counter.

    `advance()` is one agent step of the Nature algorithm; the caller decides when to
    evaluate, log and save.
    """

    def __init__(
        self, config: Config, device: torch.device, replay: ReplayMemory | None = None
    ) -> None:
        """`replay` replaces the configured replay memory (a benchmark brings a filled one)."""
        self.config = config
        seeds = derive_seeds(config.seed, 6)
        random.seed(seeds[0])
        torch.manual_seed(seeds[1])
        self.env = make_env(config, training=True, seed=seeds[2])
        self.eval_env = make_env(
            config, training=False, seed=seeds[3], max_episode_frames=config.eval_max_episode_frames
        )
        self.agent = build_agent(config, self.env, device, seeds[4])
        on_device = (
            replay_device(config, device, self.env.observation_shape, self.env.observation_dtype)
            if replay is None
            else replay.device
        )
        self.replay = replay or ReplayMemory(
            config.replay_capacity,
            self.env.observation_shape,
            self.env.observation_dtype,
            config.history_length,
            config.batch_size,
            seeds[5],
            device=on_device,
            pin_memory=device.type == "cuda" and on_device is None,
        )
        self.history = FrameHistory(
            config.history_length, self.env.observation_shape, self.env.observation_dtype
        )
        self.steps = 0
        self.epsilon = epsilon_at(0, config)
        self.game_score = 0.0  # raw score of the game in progress
        self.game_steps = 0
        self.loss_sum = torch.zeros((), device=device)  # summed on device: no sync per update
        self.losses = 0
        self.seconds = dict.fromkeys(TIMED_PARTS + ("total",), 0.0)
        # On CPU reading the loss costs nothing, so a NaN is caught at its step; on a GPU it
        # would synchronise every update, so the training loop checks periodically instead.
        self.check_every_update = device.type == "cpu"
        self.history.reset(self.env.reset())

    def advance(self) -> tuple[float, int] | None:
        """One agent step; returns (raw score, steps) of a game that just ended, else None.

        The time of each part is added to `self.seconds` (a few clock reads per step).
        """
        config = self.config
        seconds = self.seconds
        self.steps += 1
        step = self.steps
        start = perf_counter()
        self.epsilon = epsilon_at(step - 1, config)
        action = self.agent.act(self.history.frames, self.epsilon)
        acted = perf_counter()
        observation, reward, terminated, truncated = self.env.step(action)
        stepped = perf_counter()
        clip = config.reward_clip
        self.replay.add(
            self.history.newest,
            action,
            max(-clip, min(clip, reward)) if clip else reward,
            terminated,
        )
        self.game_score += reward
        self.game_steps += 1
        finished = None
        reset_seconds = 0.0
        if terminated or truncated:
            self.replay.add_last(observation)
            if self.env.game_ended:
                finished = (self.game_score, self.game_steps)
                self.game_score, self.game_steps = 0.0, 0
            reset_start = perf_counter()
            observation = self.env.reset()
            reset_seconds = perf_counter() - reset_start
            self.history.reset(observation)
        else:
            self.history.push(observation)
        stored = perf_counter()
        seconds["act"] += acted - start
        seconds["env"] += stepped - acted + reset_seconds  # resets are environment time
        seconds["store"] += stored - stepped - reset_seconds

        if step > config.replay_start_steps and step % config.update_period_steps == 0:
            batch = self.replay.sample()
            sampled = perf_counter()
            loss = self.agent.update(batch)
            if self.check_every_update and not torch.isfinite(loss):
                raise TrainingDiverged(
                    f"the loss became NaN or infinite at step {step}: training stopped; the "
                    "last complete checkpoint and the best network are kept as they were"
                )
            self.loss_sum += loss
            self.losses += 1
            updated = perf_counter()
            seconds["sample"] += sampled - stored
            seconds["update"] += updated - sampled
        if step % config.target_update_steps == 0:
            self.agent.sync_target()
        seconds["total"] += perf_counter() - start
        return finished

    def evaluate(self) -> EvaluationResult:
        """A periodic evaluation: `eval_steps` steps at `eval_epsilon`, finished games count."""
        config = self.config
        return play(
            self.agent,
            self.eval_env,
            config.history_length,
            config.eval_epsilon,
            max_steps=config.eval_steps,
        )

    def mean_loss(self) -> float | None:
        """Mean loss since the last call (one synchronisation), None if no update ran."""
        if not self.losses:
            return None
        mean = float(self.loss_sum) / self.losses
        self.loss_sum.zero_()
        self.losses = 0
        return mean

    def state_dict(self) -> dict[str, Any]:
        """Everything but the replay arrays (saved chunk by chunk, `replay.arrays`)."""
        state = {
            "steps": self.steps,
            "epsilon": self.epsilon,
            "game_score": self.game_score,
            "game_steps": self.game_steps,
            "loss_sum": self.loss_sum.detach().cpu(),
            "losses": self.losses,
            "agent": self.agent.state_dict(),
            "replay": self.replay.state_dict(),
            "env": self.env.state_dict(),
            "eval_env": self.eval_env.state_dict(),
            "history": torch.from_numpy(self.history.frames.copy()),
            "python_random": random.getstate(),
            "torch_random": torch.get_rng_state(),
        }
        if torch.cuda.is_available():
            state["cuda_random"] = torch.cuda.get_rng_state_all()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.steps = int(state["steps"])
        self.epsilon = float(state["epsilon"])
        self.game_score = float(state["game_score"])
        self.game_steps = int(state["game_steps"])
        self.loss_sum.copy_(state["loss_sum"])
        self.losses = int(state["losses"])
        self.agent.load_state_dict(state["agent"])
        self.replay.load_state_dict(state["replay"])
        self.env.load_state_dict(state["env"])
        self.eval_env.load_state_dict(state["eval_env"])
        self.history.frames[...] = state["history"].numpy()
        random.setstate(state["python_random"])
        torch.set_rng_state(state["torch_random"])
        if "cuda_random" in state and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(state["cuda_random"])

    def check_finite(self) -> None:
        """Stop before a checkpoint or a best network could keep non-finite values."""
        if not torch.isfinite(self.loss_sum):
            raise TrainingDiverged(
                f"the loss became NaN or infinite by step {self.steps}: training stopped; "
                "the last complete checkpoint and the best network are kept as they were"
            )
        for name, parameter in self.agent.online.named_parameters():
            if not torch.isfinite(parameter).all():
                raise TrainingDiverged(
                    f"the network weight {name} became NaN or infinite by step {self.steps}: "
                    "training stopped; the last complete checkpoint and the best network "
                    "are kept as they were"
                )

    def close(self) -> None:
        self.env.close()
        self.eval_env.close()


@dataclass
class RunProgress:
    """The training loop's own bookkeeping, saved in every checkpoint."""

    best_mean: float = -float("inf")
    evaluations: list[tuple[int, float]] = field(default_factory=list)
    episodes: int = 0
    recent_scores: list[float] = field(default_factory=list)  # the last 20 games


class StopRequests:
    """SIGINT/SIGTERM ask the loop to finish its step, checkpoint and stop; a second one
    stops at once."""

    def __init__(self) -> None:
        self.signal_name: str | None = None
        self._previous: dict[int, Any] = {}

    def _handle(self, number: int, frame: Any) -> None:
        if self.signal_name is not None:
            raise KeyboardInterrupt
        self.signal_name = signal.Signals(number).name

    def __enter__(self) -> StopRequests:
        if threading.current_thread() is threading.main_thread():
            for number in (signal.SIGINT, signal.SIGTERM):
                self._previous[number] = signal.signal(number, self._handle)
        return self

    def __exit__(self, *exc_info: object) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)


def replay_device(
    config: Config, device: torch.device, frame_shape: tuple[int, ...], frame_dtype: np.dtype
) -> torch.device | None:
    """Where the replay keeps a second copy of its frames to gather minibatches from
    (`replay_storage`): the training device, or None for host memory alone. "auto" picks
    a GPU when its free memory holds the frames with 2 GiB to spare; on CPU the host
    arrays already are the device's memory. "device" on CPU keeps a (useless but
    faithful) second copy: it runs the GPU's code path where there is no GPU."""
    if config.replay_storage == "host" or (
        config.replay_storage == "auto" and device.type != "cuda"
    ):
        return None
    frame_bytes = int(np.prod(frame_shape)) * np.dtype(frame_dtype).itemsize
    needed = config.replay_capacity * frame_bytes
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        if needed + 2 * 2**30 > free:
            if config.replay_storage == "auto":
                return None
            raise ResourceError(
                f'replay_storage = "device" needs {needed / 2**30:.2f} GiB of {device} memory '
                f"for the frames but {free / 2**30:.2f} GiB is free (2 GiB kept for the "
                'networks); use "host" or lower replay_capacity'
            )
    else:
        # The host arrays are allocated next, beside this copy.
        check_memory(
            2 * needed, "the replay with a second copy of its frames (replay_storage = device)"
        )
    return device


def check_disk(run_dir: Path, replay: ReplayMemory) -> None:
    """Refuse at start when the disk cannot hold the checkpoints of this replay: at worst
    two full copies (every chunk rewritten while the previous checkpoint is kept)."""
    needed = 2 * sum(array.nbytes for array in replay.arrays.values())
    free = shutil.disk_usage(run_dir).free
    if needed > free:
        raise ResourceError(
            f"checkpoints of this replay need up to {needed / 2**30:.1f} GiB of disk in "
            f"{run_dir} but only {free / 2**30:.1f} GiB are free; free some space or lower "
            "replay_capacity"
        )


def train(
    config: Config,
    run_dir: Path,
    device: torch.device,
    progress: bool = True,
    tensorboard: bool = True,
    resume: bool = False,
) -> TrainResult:
    """Train into `run_dir`: from scratch, or with `resume` from its newest complete
    checkpoint (the run directory created by the caller with `prepare_run_dir`)."""
    learner = Learner(config, device)
    env, agent, replay = learner.env, learner.agent, learner.replay
    store = CheckpointStore(run_dir, keep=config.checkpoints_kept)
    fingerprint = config_fingerprint(config)
    run = RunProgress()
    if resume:
        loaded = store.latest(fingerprint, into=replay.arrays, map_location=device)
        replay.upload()
        if loaded is not None:
            learner.load_state_dict(loaded.state["learner"])
            run = RunProgress(**loaded.state["run"])
    else:
        (run_dir / CONFIG_FILE).write_text(config_to_toml(config))
    check_disk(run_dir, replay)
    logger = RunLogger(
        run_dir, tensorboard=tensorboard, resume_step=learner.steps if resume else None
    )
    metadata = {
        "config": config.to_dict(),
        "input_shape": (config.history_length, *env.observation_shape),
        "action_names": env.action_names,
    }
    saved_position, saved_writes = replay.position, replay.writes
    saved_time = time.monotonic()
    checkpoint_seconds = config.checkpoint_period_minutes * 60

    def save_checkpoint(step: int) -> None:
        nonlocal saved_position, saved_writes, saved_time
        learner.check_finite()
        logger.flush()
        changed = written_slots(saved_position, replay.writes - saved_writes, replay.capacity)
        state = {"learner": learner.state_dict(), "run": dataclasses.asdict(run)}
        try:
            store.save(step, state, replay.arrays, changed, fingerprint)
            checkpoints.save(
                run_dir / "checkpoints" / "last.pt",
                {**metadata, "step": step, "network": agent.online.state_dict()},
            )
        except (DqnlabError, OSError) as error:
            if config.on_checkpoint_error == "stop":
                raise DqnlabError(f"checkpoint at step {step} failed: {error}") from None
            tqdm.write(f"dqnlab: warning: checkpoint at step {step} failed, training goes on: "
                       f"{error}")  # fmt: skip
            return
        saved_position, saved_writes = replay.position, replay.writes
        saved_time = time.monotonic()

    recent_scores: deque[float] = deque(run.recent_scores, maxlen=20)
    start, start_frames = time.perf_counter(), env.frames
    first_step = learner.steps + 1
    bar = tqdm(
        total=config.total_steps, initial=learner.steps, disable=not progress, unit="step",
        smoothing=0.05,
    )  # fmt: skip
    last_eval_text = f"{run.evaluations[-1][1]:.1f}" if run.evaluations else "-"
    window_start, window_frames = start, env.frames
    learning_start, learning_frames = start, env.frames  # reset when learning starts
    interrupted = None

    with StopRequests() as stop:
        for step in range(first_step, config.total_steps + 1):
            finished = learner.advance()
            if finished is not None:
                run.episodes += 1
                recent_scores.append(finished[0])
                logger.episode(
                    {
                        "step": step,
                        "frames": env.frames,
                        "episode": run.episodes,
                        "score": finished[0],
                        "steps": finished[1],
                        "epsilon": round(learner.epsilon, 6),
                        "wall_seconds": round(time.perf_counter() - start, 3),
                    }
                )

            evaluated = step % config.eval_period_steps == 0 and step > config.replay_start_steps
            if evaluated:
                learner.check_finite()
                result = learner.evaluate()
                result_mean = _periodic_mean(result)
                if result_mean > run.best_mean:
                    run.best_mean = result_mean
                    checkpoints.save(
                        run_dir / "checkpoints" / "best.pt",
                        {**metadata, "step": step, "eval_mean": result_mean,
                         "network": agent.online.state_dict()},
                    )  # fmt: skip
                keep_evaluated_network(run_dir, config, run.evaluations, step, result_mean,
                                       {**metadata, "step": step, "eval_mean": result_mean,
                                        "network": agent.online.state_dict()})  # fmt: skip
                run.evaluations.append((step, result_mean))
                logger.evaluation(
                    {
                        "step": step,
                        "frames": env.frames,
                        "mean": result_mean,
                        "std": result.std,
                        "episodes": len(result.scores),
                        "steps": result.steps,
                        "best_mean": run.best_mean,
                        "frames_per_second": round(result.frames_per_second, 1),
                        "wall_seconds": round(time.perf_counter() - start, 3),
                    }
                )
                last_eval_text = f"{result_mean:.1f}"

            if step % 1000 == 0:
                if not learner.check_every_update:
                    learner.check_finite()
                now = time.perf_counter()
                frames_per_second = (env.frames - window_frames) / (now - window_start)
                window_start, window_frames = now, env.frames
                scalars = {
                    "train/epsilon": learner.epsilon,
                    "train/frames_per_second": frames_per_second,
                }
                loss = learner.mean_loss()
                if loss is not None:
                    scalars["train/loss"] = loss
                logger.scalars(step, scalars)
                if progress:
                    bar.update(step - bar.n)
                    bar.set_postfix(
                        fps=f"{frames_per_second:.0f}",
                        eps=f"{learner.epsilon:.3f}",
                        score=f"{np.mean(recent_scores):.1f}" if recent_scores else "-",
                        eval=last_eval_text,
                        refresh=False,
                    )
            if step == config.replay_start_steps:
                learning_start, learning_frames = time.perf_counter(), env.frames

            if (
                evaluated
                or stop.signal_name is not None
                or step == config.total_steps
                or (config.checkpoint_period_steps and step % config.checkpoint_period_steps == 0)
                or time.monotonic() - saved_time >= checkpoint_seconds
            ):
                run.recent_scores = list(recent_scores)
                save_checkpoint(step)
            if stop.signal_name is not None:
                interrupted = stop.signal_name
                break
    bar.update(learner.steps - bar.n)
    bar.close()
    end = time.perf_counter()
    learning_seconds = end - learning_start
    learning_fps = (env.frames - learning_frames) / learning_seconds if learning_seconds else 0.0
    if not (run_dir / "checkpoints" / "best.pt").exists():
        # No periodic evaluation happened (a very short run): the final network stands in.
        checkpoints.save(
            run_dir / "checkpoints" / "best.pt",
            {**metadata, "step": learner.steps, "eval_mean": float("nan"),
             "network": agent.online.state_dict()},
        )  # fmt: skip
    logger.close()
    learner.close()
    return TrainResult(
        learner.steps,
        env.frames,
        end - start,
        learning_fps,
        run.best_mean,
        run.evaluations,
        env.frames - start_frames,
        interrupted,
    )


def keep_evaluated_network(
    run_dir: Path,
    config: Config,
    earlier: list[tuple[int, float]],
    step: int,
    mean: float,
    payload: dict[str, Any],
) -> None:
    """Keep the network just evaluated for `dqnlab inspect`: a file per evaluation
    (`eval_networks_kept = "all"`), and `worst.pt`, the lowest mean among evaluations in
    the last three quarters of the budget (the seed paper compares the best network with
    "a network that performed poorly very late into training"; ties go to the later)."""
    if config.eval_networks_kept == "all":
        checkpoints.save(checkpoints.eval_network_path(run_dir, step), payload)
    quarter = config.total_steps / 4
    if step >= quarter and all(mean <= m for s, m in earlier if s >= quarter):
        checkpoints.save(run_dir / "checkpoints" / "worst.pt", payload)


def _periodic_mean(result: EvaluationResult) -> float:
    """Mean raw score of the games finished within the budget, 0 if none finished
    (Lua train_agent.lua: total_reward / max(1, nepisodes))."""
    return result.mean if result.scores else 0.0
