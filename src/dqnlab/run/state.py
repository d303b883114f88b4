"""The Nature DQN algorithm, one agent step at a time, and the state it runs on.

Per step (Nature's Algorithm 1; DeepMind's Lua code with the same timings): act
epsilon-greedily with the network just updated, repeat the action in the environment,
store the transition, then every `update_period_steps` (once past `replay_start_steps`)
take one gradient step, and every `target_update_steps` copy the online network into the
target network. The training loop around it (`dqnlab.run.train`) evaluates, logs and saves.

With `num_envs` = N environments, one call steps all N: their actions come from one
batched forward pass, each environment's transition goes to its own replay stream, and
then the N agent steps it counts are walked in order, each doing what it would alone (an
update every `update_period_steps`, a target copy every `target_update_steps`, the
ε of its own step). With N = 1 that is the single loop above, bit for bit.
"""

from __future__ import annotations

import math
import random
import shutil
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from time import perf_counter
from typing import Any, NamedTuple

import numpy as np
import psutil
import torch

from dqnlab.algorithm.agent import Agent, build_agent, epsilon_at
from dqnlab.algorithm.compression import expected_frame_bytes
from dqnlab.algorithm.heldout import HeldOutSet, HeldOutStatistics
from dqnlab.algorithm.replay import FrameHistory, ReplayMemory, check_memory
from dqnlab.algorithm.samplers import build_sampler
from dqnlab.config import Config, derive_seeds
from dqnlab.envs import Environment, make_env
from dqnlab.errors import DqnlabError, ResourceError
from dqnlab.run.determinism import use_deterministic_algorithms
from dqnlab.run.play import EvaluationResult, play

TIMED_PARTS = ("env", "act", "store", "sample", "update")
# Resident bytes of one more training environment, beyond its frame history: an Atari
# emulator with its preprocessing buffers measured 1.8 MiB (Pong, 2026-12-03), CartPole
# 0.07 MiB. Counted at twice the Atari figure for any environment.
ENV_BYTES = 4 * 2**20


class FinishedGame(NamedTuple):
    """A whole training game (not a life) that ended: which environment played it, its raw
    score, its agent steps, and the run's agent step it ended at."""

    env: int
    score: float
    steps: int
    step: int


class TrainingDiverged(DqnlabError):
    """The loss or the weights stopped being finite."""


def diverged(what: str, when: str) -> TrainingDiverged:
    """The error for `what` (the loss, a weight) found non-finite `when`."""
    return TrainingDiverged(
        f"{what} became NaN or infinite {when}: training stopped; the last complete "
        "checkpoint and the best network are kept as they were"
    )


def choose_actions(
    agent: Agent, stacked: np.ndarray, first: int, count: int, config: Config
) -> tuple[list[int], list[float]]:
    """The actions of the first `count` environments on their stacked observations, whose
    agent steps are `first`, `first` + 1, ..., each under its step's epsilon (returned too):
    one batched choice, or `act` for one environment (an agent that overrides `act` still
    acts). The sequential loop and the actor thread (`concurrent.py`) both act here."""
    epsilons = [epsilon_at(step - 1, config) for step in range(first, first + count)]
    if count == 1:
        return [agent.act(stacked[0], epsilons[0], training=True)], epsilons
    return agent.act_batch(stacked[:count], epsilons, training=True), epsilons


class TrainingState:
    """Everything a run trains with: the training environments (`num_envs`, `env` the
    first) and the evaluation environment, the agent, the replay memory, a frame history per
    environment and the step counter.

    `advance()` is one agent step per environment (act, store, and update when due, with the
    parts the settings choose: Nature's, Rainbow's, a user's); the training
    loop (`dqnlab.run.train`) decides when to evaluate, log and save.
    """

    def __init__(
        self, config: Config, device: torch.device, replay: ReplayMemory | None = None
    ) -> None:
        """`replay` replaces the configured replay memory (a benchmark brings a filled one)."""
        self.config = config
        use_deterministic_algorithms(config, device)
        seeds = derive_seeds(config.seed, 7)
        random.seed(seeds[0])
        torch.manual_seed(seeds[1])
        count = config.num_envs
        # The first environment's seed is the one a single-environment run uses.
        env_seeds = [seeds[2], *derive_seeds(seeds[2], count)[1:]]
        self.env = make_env(config, training=True, seed=env_seeds[0])
        check_env_memory(config, self.env.observation_shape, self.env.observation_dtype)
        self.envs: list[Environment] = [self.env] + [
            make_env(config, training=True, seed=env_seed) for env_seed in env_seeds[1:]
        ]
        self.eval_env = make_env(
            config, training=False, seed=seeds[3], max_episode_frames=config.eval_max_episode_frames
        )
        self.agent = build_agent(config, self.env, device, seeds[4])
        self.replay = replay or self._build_replay(device, seeds[5])
        if self.replay.streams.count != count:
            raise ValueError(f"a replay of {self.replay.streams.count} streams for {count} envs")
        # The environments' histories, side by side: the batch the agent acts on.
        self.stacked = np.zeros(
            (count, config.history_length, *self.env.observation_shape),
            dtype=self.env.observation_dtype,
        )
        self.histories = []
        for frames in self.stacked:
            history = FrameHistory(config.history_length, self.env.observation_shape, frames.dtype)
            history.frames = frames  # a view: pushes and resets fill the batch in place
            self.histories.append(history)
        self.history = self.histories[0]
        self.steps = 0
        self.epsilon = epsilon_at(0, config)
        self.game_scores = [0.0] * count  # raw score of each game in progress
        self.game_steps = [0] * count
        self.loss_sum = torch.zeros((), device=device)  # summed on device: no sync per update
        self.losses = 0
        self.seconds = dict.fromkeys(TIMED_PARTS + ("total",), 0.0)
        # On CPU reading the loss costs nothing, so a NaN is caught at its step; on a GPU it
        # would synchronise every update, so the training loop checks periodically instead.
        self.check_every_update = device.type == "cpu"
        # Nature Fig. 2's held-out transitions (`heldout`), drawn at the first step past
        # replay start with a generator of their own: the run's minibatches stay the same.
        self.heldout: HeldOutSet | None = None
        self.heldout_rng = np.random.default_rng(seeds[6])
        for history, env in zip(self.histories, self.envs, strict=True):
            history.reset(env.reset())

    def _build_replay(self, device: torch.device, seed: int) -> ReplayMemory:
        """The configured replay memory: a stream per environment, its frames also on the
        device where `replay_storage` puts them there, the run's sampler."""
        config, env = self.config, self.env
        on_device = replay_device(config, device, env.observation_shape, env.observation_dtype)
        replay = ReplayMemory(
            config.replay_capacity,
            env.observation_shape,
            env.observation_dtype,
            config.history_length,
            config.batch_size,
            seed,
            device=on_device,
            pin_memory=device.type == "cuda" and on_device is None,
            compression=config.replay_compression,
            expected_frame_bytes=expected_frame_bytes(config.replay_compression, config.env),
            n_step=config.n_step,
            discount=config.discount,
            sampler=build_sampler(config),
            streams=config.num_envs,
        )
        if config.replay_compression != "none" and not replay.compressed:
            print(
                f"dqnlab: replay_compression = {config.replay_compression} is for image "
                f"observations; {config.env}'s are vectors {env.observation_shape}, "
                "stored uncompressed",
                file=sys.stderr,
            )
        return replay

    @property
    def frames(self) -> int:
        """Training frames of all the environments together."""
        return sum(env.frames for env in self.envs)

    def advance(self, max_steps: int | None = None) -> list[FinishedGame]:
        """One agent step in each environment (in the first `max_steps` of them, when
        fewer remain in the budget); returns the games that ended.

        The time of each part is added to `self.seconds` (a few clock reads per step).
        """
        config = self.config
        seconds = self.seconds
        count = len(self.envs) if max_steps is None else min(len(self.envs), max_steps)
        first = self.steps + 1
        start = perf_counter()
        actions, epsilons = choose_actions(self.agent, self.stacked, first, count, config)
        self.epsilon = epsilons[-1]
        acted = perf_counter()
        replay = self.replay
        finished, env_seconds = self.step_environments(
            actions,
            first,
            # The observation acted on (the history's newest frame) with its transition.
            lambda index, acted_on, action, reward, terminal: replay.add(
                acted_on, action, reward, terminal, index
            ),
            lambda index, observation: replay.add_last(observation, index),
        )
        stored = perf_counter()
        seconds["act"] += acted - start
        seconds["env"] += env_seconds
        seconds["store"] += stored - acted - env_seconds
        for step in range(first, first + count):
            self.steps = step
            self._learn(step)
        seconds["total"] += perf_counter() - start
        return finished

    def step_environments(
        self,
        actions: Sequence[int],
        first: int,
        store: Callable[[int, np.ndarray, int, float, bool], object],
        store_last: Callable[[int, np.ndarray], object],
    ) -> tuple[list[FinishedGame], float]:
        """Environment i takes `actions[i]` (its agent step is `first` + i): its transition
        goes to `store` (i, the observation acted on, the action, the clipped reward, the
        terminal flag), the observation that ended a life or a game to `store_last`; its
        score, its game's steps and its frame history are kept up to date, and a finished
        life or game is reset. Returns the whole games that ended and the seconds spent in
        the environments (resets included). The sequential loop and the actor thread
        (`concurrent.py`) both step their environments here."""
        finished = []
        env_seconds = 0.0
        clip = self.config.reward_clip
        for index, action in enumerate(actions):
            env, history = self.envs[index], self.histories[index]
            env_start = perf_counter()
            observation, reward, terminated, truncated = env.step(action)
            env_seconds += perf_counter() - env_start
            clipped = max(-clip, min(clip, reward)) if clip else reward
            store(index, history.newest, action, clipped, terminated)
            self.game_scores[index] += reward
            self.game_steps[index] += 1
            if terminated or truncated:
                store_last(index, observation)
                if env.game_ended:
                    score, steps = self.game_scores[index], self.game_steps[index]
                    finished.append(FinishedGame(index, score, steps, first + index))
                    self.game_scores[index], self.game_steps[index] = 0.0, 0
                reset_start = perf_counter()
                observation = env.reset()
                env_seconds += perf_counter() - reset_start  # resets are environment time
                history.reset(observation)
            else:
                history.push(observation)
        return finished, env_seconds

    def _learn(self, step: int) -> None:
        """What agent step `step` does after its transition is stored: the held-out draw,
        an update every `update_period_steps`, a target copy every `target_update_steps`."""
        config, seconds = self.config, self.seconds
        if self.heldout is None and config.heldout_transitions and step > config.replay_start_steps:
            # Lua NeuralQLearner:perceive draws them when numSteps == learn_start + 1.
            self.heldout = HeldOutSet.draw(
                self.replay, config.heldout_transitions, self.heldout_rng
            )
        if step > config.replay_start_steps and step % config.update_period_steps == 0:
            sampling = perf_counter()
            batch = self.replay.sample(step)
            sampled = perf_counter()
            loss, priorities = self.agent.update(batch)
            self.replay.sampler.tell(batch, priorities)
            if self.check_every_update and not math.isfinite(loss.item()):
                raise diverged("the loss", f"at step {step}")
            self.loss_sum += loss
            self.losses += 1
            updated = perf_counter()
            seconds["sample"] += sampled - sampling
            seconds["update"] += updated - sampled
        if step % config.target_update_steps == 0:
            self.agent.sync_target()

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

    def heldout_statistics(self) -> HeldOutStatistics | None:
        """Mean max-Q and mean |TD error| on the held-out transitions (None before they
        are drawn, or with heldout_transitions = 0)."""
        if self.heldout is None:
            return None
        agent, config = self.agent, self.config
        return self.heldout.statistics(
            agent.online, agent.target, config.discount, config.td_error_clip, agent.device
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
        """Everything but the replay arrays (saved chunk by chunk, `replay.arrays`). The
        first environment's under the keys of a single-environment run, the others' in
        "more_envs"."""
        state = {
            "steps": self.steps,
            "epsilon": self.epsilon,
            **self._env_state(0),
            "loss_sum": self.loss_sum.detach().cpu(),
            "losses": self.losses,
            "agent": self.agent.state_dict(),
            "replay": self.replay.state_dict(),
            "eval_env": self.eval_env.state_dict(),
            "python_random": random.getstate(),
            "torch_random": torch.get_rng_state(),
            "heldout": None if self.heldout is None else self.heldout.state_dict(),
            "heldout_rng": self.heldout_rng.bit_generator.state,
        }
        if len(self.envs) > 1:
            state["more_envs"] = [self._env_state(index) for index in range(1, len(self.envs))]
        if torch.cuda.is_available():
            state["cuda_random"] = torch.cuda.get_rng_state_all()
        return state

    def _env_state(self, index: int) -> dict[str, Any]:
        return {
            "game_score": self.game_scores[index],
            "game_steps": self.game_steps[index],
            "env": self.envs[index].state_dict(),
            "history": torch.from_numpy(self.histories[index].frames.copy()),
        }

    def _load_env_state(self, index: int, state: dict[str, Any]) -> None:
        self.game_scores[index] = float(state["game_score"])
        self.game_steps[index] = int(state["game_steps"])
        self.envs[index].load_state_dict(state["env"])
        self.histories[index].frames[...] = state["history"].numpy()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        more = state.get("more_envs", [])
        if len(more) + 1 != len(self.envs):
            raise ValueError(f"a state of {len(more) + 1} environments, not {len(self.envs)}")
        self.steps = int(state["steps"])
        self.epsilon = float(state["epsilon"])
        self._load_env_state(0, state)
        for index, env_state in enumerate(more, start=1):
            self._load_env_state(index, env_state)
        self.loss_sum.copy_(state["loss_sum"])
        self.losses = int(state["losses"])
        self.agent.load_state_dict(state["agent"])
        self.replay.load_state_dict(state["replay"])
        self.eval_env.load_state_dict(state["eval_env"])
        self._load_heldout(state)
        random.setstate(state["python_random"])
        torch.set_rng_state(state["torch_random"])
        if "cuda_random" in state and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(state["cuda_random"])

    def _load_heldout(self, state: dict[str, Any]) -> None:
        """The held-out set as saved. A checkpoint written before they existed, or with
        another heldout_transitions (a setting a run may resume with changed), has none
        of the right size: the set is drawn at the next step past replay start."""
        saved = state.get("heldout")
        if "heldout_rng" in state:
            self.heldout_rng.bit_generator.state = state["heldout_rng"]
        self.heldout = HeldOutSet.from_state_dict(saved) if saved is not None else None
        wanted = self.config.heldout_transitions
        if self.heldout is not None and len(self.heldout) != wanted:
            print(
                f"dqnlab: the checkpoint's held-out set has {len(self.heldout)} transitions, "
                f"heldout_transitions is now {wanted}: "
                + ("drawn again from the replay" if wanted else "no held-out statistics"),
                file=sys.stderr,
            )
            self.heldout = None

    def check_finite(self) -> None:
        """Stop before a checkpoint or a best network could keep non-finite values."""
        if not torch.isfinite(self.loss_sum):
            raise diverged("the loss", f"by step {self.steps}")
        for name, parameter in self.agent.online.named_parameters():
            if not torch.isfinite(parameter).all():
                raise diverged(f"the network weight {name}", f"by step {self.steps}")

    def close(self) -> None:
        for env in self.envs:
            env.close()
        self.eval_env.close()


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


def check_env_memory(config: Config, frame_shape: tuple[int, ...], frame_dtype: np.dtype) -> None:
    """Refuse more training environments than memory holds (`ENV_BYTES` each, with their
    frame histories), in one line naming `num_envs`."""
    frame_bytes = int(np.prod(frame_shape)) * np.dtype(frame_dtype).itemsize
    needed = config.num_envs * (ENV_BYTES + config.history_length * frame_bytes)
    available = psutil.virtual_memory().available
    if needed > available:
        raise ResourceError(
            f"num_envs = {config.num_envs}: the environments need about "
            f"{needed / 2**30:.2f} GiB but only {available / 2**30:.2f} GiB of memory is "
            "available; lower num_envs"
        )


def check_disk(run_dir: Path, replay: ReplayMemory) -> None:
    """Refuse at start when the disk cannot hold the checkpoints this replay grows to: at
    worst two full copies (every chunk rewritten while the previous checkpoint is kept), of
    the size the memory check counted on (compressed only where measured for this game).

    A checkpoint stores only the filled part of the replay, so the first ones are smaller;
    this checks the full size all the same, so that a run that cannot finish is refused
    now rather than days in. Each save checks the bytes it writes itself
    (`CheckpointStore.save`)."""
    needed = 2 * replay.expected_bytes
    free = shutil.disk_usage(run_dir).free
    if needed > free:
        raise ResourceError(
            f"checkpoints of this replay need up to {needed / 2**30:.1f} GiB of disk in "
            f"{run_dir} but only {free / 2**30:.1f} GiB are free; free some space or lower "
            "replay_capacity"
        )
