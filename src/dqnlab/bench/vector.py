"""Training throughput with several environments: `dqnlab bench --num-envs 1,2,4,8`.

Each count N is the nature preset with `num_envs` = N on the same game, its replay streams
filled with the same frames, measured past the replay start and the ε anneal (ε = 0.1, as
for most of a run) in alternating rounds, so that a change in the machine's load falls on
every N alike. What N changes per agent step: one forward pass chooses N actions, and the
N emulators are stepped one after another in this process (docs/benchmark.md, "Many
environments", says why not in worker processes). The update, one per 4 agent steps, is
the same work for any N. With `--concurrency none,actor-learner` each N is measured both
ways: the actor thread's acting and emulator time then overlap the update, so the shares
of the parts add up to more than 1, and `share_learner_waiting` is the learner's time
waiting for the actor.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.bench.measure import machine_figures, measure_training, whole_rounds
from dqnlab.config import resolve_config
from dqnlab.config.settings import CHOICES
from dqnlab.errors import ConfigError
from dqnlab.run.concurrent import training_state
from dqnlab.run.state import TrainingState


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


def measure_num_envs(
    counts: list[int],
    env: str = "breakout",
    steps: int = 2000,
    replay_capacity: int = 100_000,
    device: torch.device | None = None,
    seed: int = 0,
    rounds: int = 2,
    concurrency: tuple[str, ...] = ("none",),
) -> dict[str, Any]:
    """Training frames/s and where the time goes for each number of environments (and
    each `concurrency`), as `num_envs_{N}[_actor_learner]_{figure}` keys beside the
    machine's."""
    device = device or torch.device("cpu")
    figures: dict[str, Any] = {
        "env": env,
        **machine_figures(device),
        "replay_capacity": replay_capacity,
        "steps": steps,
        "rounds": rounds,
    }
    states: dict[str, TrainingState] = {}
    for count in counts:
        for mode in concurrency:
            config = resolve_config(
                "nature", env=env, seed=seed, replay_capacity=replay_capacity, num_envs=count,
                concurrency=mode,
            )  # fmt: skip
            state = training_state(config, device)
            _fill(state.replay, np.random.default_rng(seed))
            state.steps = config.replay_start_steps + config.epsilon_decay_steps
            measure_training(state, whole_rounds(100, count))  # warm-up
            states[row_key(count, mode)] = state
    runs: dict[str, list[float]] = {key: [] for key in states}
    parts: dict[str, list[dict[str, float]]] = {key: [] for key in states}
    for _ in range(rounds):
        for key, state in states.items():
            frames_per_second, shares = measure_training(
                state, whole_rounds(steps, len(state.envs))
            )
            if "wait" in state.seconds:
                shares["learner_waiting"] = state.seconds["wait"] / state.seconds["total"]
            runs[key].append(frames_per_second)
            parts[key].append(shares)
    for key, state in states.items():
        figures[f"{key}_train_frames_per_second"] = float(np.mean(runs[key]))
        figures[f"{key}_train_frames_per_second_runs"] = [round(f, 1) for f in runs[key]]
        for part in parts[key][0]:
            share = float(np.mean([shares[part] for shares in parts[key]]))
            figures[f"{key}_share_{part}"] = round(share, 4)
        state.close()
    base = figures.get("num_envs_1_train_frames_per_second")
    for key in states:
        if base:
            figures[f"{key}_ratio_vs_1"] = figures[f"{key}_train_frames_per_second"] / base
    return figures
