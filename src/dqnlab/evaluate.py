"""Evaluation: epsilon-greedy play of whole games, raw scores.

Two protocols from the Nature paper: the periodic one (a budget of agent steps, the mean
of the episodes that finished within it, as the Lua code's train_agent.lua) and the final
one (a number of whole games of at most 5 minutes each).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from dqnlab import checkpoints
from dqnlab.agent import Agent, build_agent
from dqnlab.config import Config, config_from_dict, derive_seeds
from dqnlab.envs import Environment, make_env
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
) -> tuple[EvaluationResult, Config, Path]:
    """Nature's final protocol on a run's network: whole games of at most
    `final_eval_max_episode_frames`, at `eval_epsilon`, with random no-op starts.

    The network is built from the configuration saved in the checkpoint itself, so a
    checkpoint file from another run evaluates with its own settings.
    """
    if checkpoint in ("best", "last"):
        load_run_config(run_dir)  # a clear error if RUN_DIR is not a run
        path = run_dir / "checkpoints" / f"{checkpoint}.pt"
    else:
        path = Path(checkpoint)
    payload = checkpoints.load(path, map_location=device)
    config = config_from_dict(payload["config"])
    weights = payload["network"] if "network" in payload else payload["agent"]["online"]
    env_seed, agent_seed = derive_seeds(seed, 2)
    env = make_env(
        config,
        training=False,
        seed=env_seed,
        max_episode_frames=config.final_eval_max_episode_frames,
    )
    agent = build_agent(config, env, device, agent_seed)
    try:
        agent.online.load_state_dict(weights)
    except RuntimeError as error:
        raise DqnlabError(f"checkpoint {path} does not fit its network: {error}") from None
    count = episodes if episodes is not None else config.final_eval_episodes
    if count <= 0:
        raise DqnlabError(f"--episodes {count} must be positive")
    result = play(agent, env, config.history_length, config.eval_epsilon, max_episodes=count)
    env.close()
    return result, config, path
