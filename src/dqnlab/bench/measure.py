"""Timings both benchmarks take: training frames/s with the share of each timed part, and
the median time to sample a minibatch."""

from __future__ import annotations

import time

import numpy as np

from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.run.state import TIMED_PARTS, TrainingState


def measure_training(training: TrainingState, steps: int) -> tuple[float, dict[str, float]]:
    """Frames/s over `steps` training steps, and the fraction of time in each part."""
    frames, start = training.env.frames, time.perf_counter()
    training.seconds = dict.fromkeys(training.seconds, 0.0)
    for _ in range(steps):
        training.advance()
    float(training.loss_sum)  # wait for the device
    seconds = time.perf_counter() - start
    parts = {name: training.seconds[name] / seconds for name in TIMED_PARTS}
    parts["other"] = 1.0 - sum(parts.values())  # the loop's own overhead
    return (training.env.frames - frames) / seconds, parts


def median_sample_us(replay: ReplayMemory, repeats: int) -> float:
    """The median time of `repeats` minibatch samples, in microseconds."""
    timings = []
    for _ in range(repeats):
        start = time.perf_counter()
        replay.sample()
        timings.append(time.perf_counter() - start)
    return float(np.median(timings) * 1e6)
