"""Training throughput with several environments: `dqnlab bench envs --num-envs 1,2,4,8`.

Each count N is the nature preset with `num_envs` = N on the same game, its replay streams
filled with the same frames, measured past the replay start and the ε anneal (ε = 0.1, as
for most of a run) in alternating rounds, so that a change in the machine's load falls on
every N alike. What N changes per agent step: one forward pass chooses N actions, and the
N emulators are stepped one after another in this process (docs/benchmark.md, "Many
environments", says why not in worker processes). The update, one per 4 agent steps, is
the same work for any N. With `--concurrency none,actor-learner` each N is measured both
ways: the actor thread's acting and emulator time then overlap the update, so the shares
of the parts add up to more than 1, and `share_learner_waiting` is the learner's time
waiting for the actor. With `--peers` and `--cleanrl DIR` Stable-Baselines3's and
CleanRL's DQN take their turn in each round, so that one command gives issue 22's whole
table (`table.py` prints it)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np
import torch

from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.bench.cleanrl import CleanRLPeer
from dqnlab.bench.flops import matmul_figures, measure_matmul, update_flop_figures, update_flops
from dqnlab.bench.measure import (
    machine_figures,
    measure_training,
    median_update_ms,
    whole_rounds,
)
from dqnlab.bench.peers import peer_round
from dqnlab.config import CHOICES, Config, resolve_config
from dqnlab.errors import ConfigError
from dqnlab.run.concurrent import training_state
from dqnlab.run.determinism import set_threads
from dqnlab.run.state import TrainingState

# The replay the update is timed on: only its minibatch matters.
UPDATE_REPLAY_SLOTS = 5_000


def parse_counts(text: str) -> list[int]:
    """A comma-separated list of environment counts, each at least 1."""
    try:
        counts = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        raise ConfigError(f"--num-envs {text!r}: give counts of at least 1, e.g. 1,2,4,8")
    return counts


def parse_concurrency(text: str) -> list[str]:
    """A comma-separated list of `concurrency` values."""
    values = [part.strip() for part in text.split(",") if part.strip()]
    choices = CHOICES["concurrency"]
    if not values or any(value not in choices for value in values):
        raise ConfigError(f"--concurrency {text!r}: give some of {', '.join(choices)}")
    return values


def row_key(count: int, concurrency: str) -> str:
    """The figures' prefix for N environments and a concurrency (none: the older keys)."""
    suffix = "" if concurrency == "none" else "_" + concurrency.replace("-", "_")
    return f"num_envs_{count}{suffix}"


def _fill(replay: ReplayMemory, rng: np.random.Generator) -> None:
    """Every stream's slots written with distinct-looking frames (a cycled pool of random
    ones), the streams in turn as a vector step writes them."""
    pool = rng.integers(0, 256, size=(64, *replay.frame_shape), dtype=np.uint8)
    streams = replay.streams.count
    for i in range(replay.capacity):
        replay.add(pool[i % 64], int(i % 4), float(i % 7 == 0), False, i % streams)


def _states(
    counts: list[int],
    concurrency: tuple[str, ...],
    env: str,
    replay_capacity: int,
    device: torch.device,
    seed: int,
) -> dict[str, TrainingState]:
    """One training state per count and concurrency, filled, past the ε anneal, warmed up."""
    states: dict[str, TrainingState] = {}
    threads = torch.get_num_threads()
    for count in counts:
        for mode in concurrency:
            config = _config(
                env, seed, replay_capacity=replay_capacity, num_envs=count, concurrency=mode
            )
            state = training_state(config, device)
            _fill(state.replay, np.random.default_rng(seed))
            state.steps = config.replay_start_steps + config.epsilon_decay_steps
            measure_training(state, whole_rounds(100, count))  # warm-up
            set_threads(threads)  # as it was: an actor thread's state changed it
            states[row_key(count, mode)] = state
    return states


def _config(env: str, seed: int, **settings: Any) -> Config:
    return resolve_config("nature", env=env, seed=seed, **settings)


def _update_figures(env: str, device: torch.device, seed: int) -> dict[str, Any]:
    """The nature preset's update (median ms on one minibatch of a small filled replay)
    and its GFLOP/s against a large matrix multiply's, timed now on the same threads."""
    training = TrainingState(_config(env, seed, replay_capacity=UPDATE_REPLAY_SLOTS), device)
    try:
        _fill(training.replay, np.random.default_rng(seed))
        batch = training.replay.sample()
        flop = update_flops(training.agent, batch)
        update_ms = median_update_ms(training.agent, batch)
    finally:
        training.close()
    matmul = measure_matmul(device)
    return {
        "update_ms": update_ms,
        **update_flop_figures("", flop, update_ms, matmul),
        **matmul_figures(matmul),
    }


def _threads_of(state: TrainingState, threads: int) -> int:
    """The threads `state`'s training thread runs with (fewer with an actor thread)."""
    learner = getattr(state, "learner_threads", None)
    return threads if learner is None else learner


def measure_num_envs(
    counts: list[int],
    env: str = "breakout",
    steps: int = 2000,
    replay_capacity: int = 100_000,
    device: torch.device | None = None,
    seed: int = 0,
    rounds: int = 2,
    concurrency: tuple[str, ...] = ("none",),
    peers: bool = False,
    cleanrl: CleanRLPeer | None = None,
    peer_learning_starts: int = 5000,
) -> dict[str, Any]:
    """Training frames/s and where the time goes for each number of environments (and
    each `concurrency`), as `num_envs_{N}[_actor_learner]_{figure}` keys beside the
    machine's; the nature update's GFLOP/s against this machine's matrix multiply, timed
    first (`_update_figures`). With `peers` (Stable-Baselines3) and `cleanrl`, the peers
    take their turn in each round, and every row gets its ratio to each."""
    device = device or torch.device("cpu")
    figures: dict[str, Any] = {
        "env": env,
        **machine_figures(device),
        "replay_capacity": replay_capacity,
        "steps": steps,
        "rounds": rounds,
    }
    figures.update(_update_figures(env, device, seed))
    states = _states(counts, concurrency, env, replay_capacity, device, seed)
    peers_round = partial(
        peer_round, _config(env, seed), steps, peer_learning_starts, device, peers, cleanrl
    )
    measured = _rounds(states, figures, rounds, peers_round)
    for key, state in states.items():
        runs, shares = measured.frames_per_second[key], measured.shares[key]
        figures[f"{key}_train_frames_per_second"] = float(np.mean(runs))
        figures[f"{key}_train_frames_per_second_runs"] = [round(f, 1) for f in runs]
        for part in shares[0]:
            figures[f"{key}_share_{part}"] = round(float(np.mean([s[part] for s in shares])), 4)
        state.close()
    peer_figures = _peer_figures(measured.sb3_runs, measured.cleanrl_runs)
    figures.update(peer_figures)
    figures.update(_ratios(figures, list(states), peer_figures))
    return figures


@dataclass
class _Measured:
    """What the rounds measured: per state, its frames/s and the shares of its parts in
    each round; the peers' runs."""

    frames_per_second: dict[str, list[float]]
    shares: dict[str, list[dict[str, float]]]
    sb3_runs: list[dict[str, Any]] = field(default_factory=list)
    cleanrl_runs: list[dict[str, Any]] = field(default_factory=list)


def _rounds(
    states: dict[str, TrainingState],
    figures: dict[str, Any],
    rounds: int,
    peers_round: Callable[[], tuple[dict[str, Any] | None, dict[str, Any] | None]],
) -> _Measured:
    """Each round: every state in turn for `figures["steps"]` agent steps (its threads
    noted in `figures`), then the peers."""
    measured = _Measured({key: [] for key in states}, {key: [] for key in states})
    threads = figures["threads"]
    for _ in range(rounds):
        for key, state in states.items():
            # An actor thread's state runs its learner with fewer threads, set for the
            # whole process when it started: each state runs with its own count.
            figures[f"{key}_threads"] = _threads_of(state, threads)
            set_threads(figures[f"{key}_threads"])
            frames_per_second, shares = measure_training(
                state, whole_rounds(figures["steps"], len(state.envs))
            )
            set_threads(threads)
            if "wait" in state.seconds:
                shares["learner_waiting"] = state.seconds["wait"] / state.seconds["total"]
            measured.frames_per_second[key].append(frames_per_second)
            measured.shares[key].append(shares)
        sb3_run, cleanrl_run = peers_round()
        measured.sb3_runs += [sb3_run] if sb3_run else []
        measured.cleanrl_runs += [cleanrl_run] if cleanrl_run else []
    return measured


def _ratios(
    figures: dict[str, Any], keys: list[str], peer_figures: dict[str, Any]
) -> dict[str, float]:
    """Each row's frames/s against one environment's and against each peer's."""
    ratios = {}
    base = figures.get("num_envs_1_train_frames_per_second")
    for key in keys:
        ours = figures[f"{key}_train_frames_per_second"]
        if base:
            ratios[f"{key}_ratio_vs_1"] = ours / base
        for peer in ("sb3", "cleanrl"):
            theirs = peer_figures.get(f"{peer}_train_frames_per_second")
            if theirs:
                ratios[f"{key}_ratio_vs_{peer}"] = ours / theirs
    return ratios


def _peer_figures(
    peer_runs: list[dict[str, Any]], cleanrl_runs: list[dict[str, Any]]
) -> dict[str, Any]:
    """The peers' mean frames/s over the rounds (as `sb3_...` and `cleanrl_...`), each
    round's, and the last round's settings."""
    figures: dict[str, Any] = {}
    if peer_runs:
        figures.update({k: v for k, v in peer_runs[-1].items() if k.startswith("peer")})
        fps = [run["peer_train_frames_per_second"] for run in peer_runs]
        figures["sb3_train_frames_per_second"] = float(np.mean(fps))
        figures["sb3_train_frames_per_second_runs"] = [round(f, 1) for f in fps]
    if cleanrl_runs:
        figures.update(cleanrl_runs[-1])
        fps = [run["cleanrl_train_frames_per_second"] for run in cleanrl_runs]
        figures["cleanrl_train_frames_per_second"] = float(np.mean(fps))
        figures["cleanrl_train_frames_per_second_runs"] = [round(f, 1) for f in fps]
    return figures
