"""The training loop: the Nature DQN algorithm, one agent step at a time.

Per step (Nature's Algorithm 1; DeepMind's Lua code with the same timings): act
epsilon-greedily with the network just updated, repeat the action in the environment,
store the transition, then every `update_period_steps` (once past `replay_start_steps`)
take one gradient step, and every `target_update_steps` copy the online network into the
target network. Every `eval_period_steps` the network is evaluated and the best one kept.
"""

from __future__ import annotations

import random
import shutil
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from time import perf_counter

import numpy as np
import torch
from tqdm import tqdm

from dqnlab import checkpoints
from dqnlab.agent import build_agent, epsilon_at
from dqnlab.config import Config, config_to_toml, derive_seeds
from dqnlab.envs import make_env
from dqnlab.errors import DqnlabError
from dqnlab.evaluate import CONFIG_FILE, EvaluationResult, play
from dqnlab.logs import RunLogger
from dqnlab.replay import FrameHistory, ReplayMemory


def prepare_run_dir(run_dir: Path, force: bool) -> None:
    """Create an empty run directory; with `force`, replace an earlier dqnlab run there.

    Only a directory holding a dqnlab run (its config.toml) is ever deleted, so a mistyped
    `--run-dir . --force` cannot wipe a project.
    """
    if run_dir.exists() and not run_dir.is_dir():
        raise DqnlabError(f"--run-dir {run_dir} exists and is not a directory")
    if run_dir.exists() and any(run_dir.iterdir()):
        if not force:
            raise DqnlabError(
                f"run directory {run_dir} already exists and is not empty; "
                "choose another --run-dir or pass --force to overwrite it"
            )
        if not (run_dir / CONFIG_FILE).is_file():
            raise DqnlabError(
                f"--force refuses to delete {run_dir}: it is not a dqnlab run directory "
                f"(no {CONFIG_FILE}); choose an empty or new --run-dir"
            )
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)


@dataclass
class TrainResult:
    steps: int
    frames: int
    seconds: float
    learning_frames_per_second: float  # after replay start, evaluations included
    best_eval_mean: float
    evaluations: list[tuple[int, float]]

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0


TIMED_PARTS = ("env", "act", "store", "sample", "update")


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
        self.replay = replay or ReplayMemory(
            config.replay_capacity,
            self.env.observation_shape,
            self.env.observation_dtype,
            config.history_length,
            config.batch_size,
            seeds[5],
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
            self.loss_sum += self.agent.update(batch)
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

    def close(self) -> None:
        self.env.close()
        self.eval_env.close()


def train(
    config: Config,
    run_dir: Path,
    device: torch.device,
    progress: bool = True,
    tensorboard: bool = True,
) -> TrainResult:
    """Train from scratch into `run_dir` (created by the caller with `prepare_run_dir`)."""
    learner = Learner(config, device)
    env, agent = learner.env, learner.agent
    (run_dir / CONFIG_FILE).write_text(config_to_toml(config))
    logger = RunLogger(run_dir, tensorboard=tensorboard)
    metadata = {
        "config": config.to_dict(),
        "input_shape": (config.history_length, *env.observation_shape),
        "action_names": env.action_names,
    }

    best_mean = -float("inf")
    evaluations: list[tuple[int, float]] = []
    recent_scores: deque[float] = deque(maxlen=20)
    episodes = 0
    start = time.perf_counter()
    bar = tqdm(total=config.total_steps, disable=not progress, unit="step", smoothing=0.05)
    last_eval_text = "-"
    window_start, window_frames = start, 0
    learning_start, learning_frames = start, 0  # reset when learning starts

    for step in range(1, config.total_steps + 1):
        finished = learner.advance()
        if finished is not None:
            episodes += 1
            recent_scores.append(finished[0])
            logger.episode(
                {
                    "step": step,
                    "frames": env.frames,
                    "episode": episodes,
                    "score": finished[0],
                    "steps": finished[1],
                    "epsilon": round(learner.epsilon, 6),
                    "wall_seconds": round(time.perf_counter() - start, 3),
                }
            )

        if step % config.eval_period_steps == 0 and step > config.replay_start_steps:
            result = learner.evaluate()
            result_mean = _periodic_mean(result)
            is_best = result_mean > best_mean
            if is_best:
                best_mean = result_mean
                checkpoints.save(
                    run_dir / "checkpoints" / "best.pt",
                    {**metadata, "step": step, "eval_mean": result_mean,
                     "network": agent.online.state_dict()},
                )  # fmt: skip
            evaluations.append((step, result_mean))
            logger.evaluation(
                {
                    "step": step,
                    "frames": env.frames,
                    "mean": result_mean,
                    "std": result.std,
                    "episodes": len(result.scores),
                    "steps": result.steps,
                    "best_mean": best_mean,
                    "frames_per_second": round(result.frames_per_second, 1),
                    "wall_seconds": round(time.perf_counter() - start, 3),
                }
            )
            checkpoints.save(
                run_dir / "checkpoints" / "last.pt",
                {**metadata, "step": step, "agent": agent.state_dict()},
            )
            last_eval_text = f"{result_mean:.1f}"

        if step % 1000 == 0:
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
                bar.update(1000)
                bar.set_postfix(
                    fps=f"{frames_per_second:.0f}",
                    eps=f"{learner.epsilon:.3f}",
                    score=f"{np.mean(recent_scores):.1f}" if recent_scores else "-",
                    eval=last_eval_text,
                    refresh=False,
                )
        if step == config.replay_start_steps:
            learning_start, learning_frames = time.perf_counter(), env.frames
    bar.update(config.total_steps - bar.n)
    bar.close()
    end = time.perf_counter()
    learning_seconds = end - learning_start
    learning_fps = (env.frames - learning_frames) / learning_seconds if learning_seconds else 0.0
    checkpoints.save(
        run_dir / "checkpoints" / "last.pt",
        {**metadata, "step": config.total_steps, "agent": agent.state_dict()},
    )
    if not (run_dir / "checkpoints" / "best.pt").exists():
        # No periodic evaluation happened (a very short run): the final network stands in.
        checkpoints.save(
            run_dir / "checkpoints" / "best.pt",
            {**metadata, "step": config.total_steps, "eval_mean": float("nan"),
             "network": agent.online.state_dict()},
        )  # fmt: skip
    logger.close()
    learner.close()
    return TrainResult(
        config.total_steps, env.frames, end - start, learning_fps, best_mean, evaluations
    )


def _periodic_mean(result: EvaluationResult) -> float:
    """Mean raw score of the games finished within the budget, 0 if none finished
    (Lua train_agent.lua: total_reward / max(1, nepisodes))."""
    return result.mean if result.scores else 0.0
