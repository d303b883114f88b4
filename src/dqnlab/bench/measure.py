"""Timings the benchmarks share: the machine they ran on, training frames/s with the share
of each timed part, the seconds of each of a number of calls, and the median times of an
update and of sampling a minibatch.

Why not `torch.utils.benchmark.Timer` for the medians: its `blocked_autorange` times blocks
of calls, as many per block as make its own overhead under 1e-4 of the block; on a GPU that
overhead is two synchronisations, so an update of a few milliseconds would be timed tens or
hundreds at a time, back to back: another figure than the median of single updates each
waited for. `gpu.py` times the back-to-back figure with it (`Timer.timeit`)."""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import psutil
import torch

from dqnlab import __version__
from dqnlab.algorithm.agent import Agent
from dqnlab.algorithm.minibatch import Batch
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.run.denormals import flushes_everywhere
from dqnlab.run.state import TIMED_PARTS, TrainingState


def fill_replay(replay: ReplayMemory, pool: np.ndarray, actions: int) -> None:
    """Every slot of `replay` written with the frames of `pool` cycled (distinct-looking
    observations), `actions` cycled, a reward of 1 every seventh step, in episodes of 1,000
    steps, so that n-step windows meet episode ends as in play."""
    for i in range(replay.capacity):
        frame = pool[i % len(pool)]
        if i % 1000 == 999:
            replay.add_last(frame)
        else:
            replay.add(frame, i % actions, float(i % 7 == 0), False)


def random_frames(replay: ReplayMemory, rng: np.random.Generator) -> np.ndarray:
    """A pool of 64 random uint8 frames of the replay's frame shape."""
    return rng.integers(0, 256, size=(64, *replay.frame_shape), dtype=np.uint8)


def machine_figures(device: torch.device) -> dict[str, Any]:
    """What a figure depends on besides the code: versions, threads, and how loaded the
    machine was when the measurement began."""
    return {
        "device": str(device),
        "threads": torch.get_num_threads(),
        "flush_denormals": flushes_everywhere(),
        "cpu_count": psutil.cpu_count(),
        "dqnlab": __version__,
        "torch": torch.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "load_average_1min": os.getloadavg()[0],
    }


def whole_rounds(steps: int, count: int) -> int:
    """`steps` rounded up to whole rounds of `count` agent steps: an actor thread acts a
    whole round ahead (only the budget's last may be short)."""
    return -(-steps // count) * count


def measure_training(training: TrainingState, steps: int) -> tuple[float, dict[str, float]]:
    """Frames/s over `steps` agent steps (of all its environments together), and the
    fraction of time in each part."""
    frames, start = training.frames, time.perf_counter()
    training.seconds = dict.fromkeys(training.seconds, 0.0)
    end = training.steps + steps
    while training.steps < end:
        training.advance(end - training.steps)
    float(training.loss_sum)  # wait for the device
    seconds = time.perf_counter() - start
    parts = {name: training.seconds[name] / seconds for name in TIMED_PARTS}
    parts["other"] = 1.0 - sum(parts.values())  # the loop's own overhead
    return (training.frames - frames) / seconds, parts


def call_seconds(action: Callable[[], object], repeats: int) -> np.ndarray:
    """The wall seconds of each of `repeats` calls of `action`, one after another; an
    action on a device waits for it itself (`.item()`), so that each call is timed whole."""
    seconds = np.empty(repeats)
    for index in range(repeats):
        start = time.perf_counter()
        action()
        seconds[index] = time.perf_counter() - start
    return seconds


def copies_target_every_update(agent: Agent) -> bool:
    """Whether training copies the target network after every update (`drq_epsilon`:
    `target_update_steps` at most `update_period_steps`), so that every update sees a
    target that is a copy of the online network (`Agent.target_is_a_copy`)."""
    return agent.config.target_update_steps <= agent.config.update_period_steps


def update_as_in_training(agent: Agent, batch: Batch) -> None:
    """One update with the target network as training's updates see it: the copy after it
    where training copies after every update; elsewhere the update moves the online network
    away from the target, as between training's copies."""
    agent.update(batch)[0].item()  # .item() waits
    if copies_target_every_update(agent):
        agent.sync_target()


def median_update_ms(agent: Agent, batch: Batch, repeats: int = 50) -> float:
    """The median time of `repeats` updates on one minibatch (after 5 not timed), each
    waited for, in milliseconds; with the target copy after each where training copies the
    target after every update (`update_as_in_training`)."""
    for _ in range(5):
        update_as_in_training(agent, batch)
    seconds = call_seconds(lambda: update_as_in_training(agent, batch), repeats)
    return float(np.median(seconds) * 1e3)


def median_sample_us(replay: ReplayMemory, repeats: int) -> float:
    """The median time of `repeats` minibatch samples, in microseconds."""
    return float(np.median(call_seconds(replay.sample, repeats)) * 1e6)
