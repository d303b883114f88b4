"""What compressing the replay (`replay_compression`) costs and saves, on one game's frames.

Two replays of the same capacity are filled, in one pass of the random policy through the
Nature pipeline, with the same transitions: one raw, one compressed. Measured on them: the
resident bytes per transition and the compression ratio, the time to sample a minibatch,
the time to compress a chunk (per agent step), training frames/s with each (alternating
rounds, so that the machine's load falls on both alike), and the bytes and seconds of a
full-replay checkpoint (optionally of a larger replay repeating the same transitions).
The compressed size of every Atari-57 game's frames, the table the memory check reads
(data/replay_compression.csv), was measured once by scripts/compression_scan.py.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dqnlab.algorithm.compression import CHUNK_SLOTS, CompressedFrames
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.bench.measure import measure_training, median_sample_us
from dqnlab.config import Config, resolve_config
from dqnlab.envs import make_env
from dqnlab.run.checkpoints import CheckpointStore
from dqnlab.run.state import TrainingState


def fill_by_random_play(
    replays: Sequence[ReplayMemory], config: Config, steps: int, seed: int
) -> None:
    """`steps` transitions of uniformly random play, the same into every replay."""
    env = make_env(config, training=True, seed=seed)
    rng = np.random.default_rng(seed)
    observation = env.reset(new_game=True).copy()
    for _ in range(steps):
        action = int(rng.integers(env.num_actions))
        following, reward, terminated, truncated = env.step(action)
        for replay in replays:
            replay.add(observation, action, float(reward), terminated)
        if terminated or truncated:
            for replay in replays:
                replay.add_last(following)
            observation = env.reset(new_game=env.game_ended).copy()
        else:
            observation = following.copy()
    env.close()


def _window_bytes(replay: ReplayMemory, indices: np.ndarray) -> bytes:
    window = replay.gather(indices).window
    assert isinstance(window, np.ndarray)
    return window.tobytes()


def _cycled(source: ReplayMemory, capacity: int, compression: str) -> ReplayMemory:
    """A replay of `capacity` slots holding `source`'s slots over and over: the bytes of
    each compressed chunk are those of real play, for timing a large checkpoint without
    playing a million steps."""
    assert isinstance(source.frames, np.ndarray)
    replay = ReplayMemory(
        capacity, source.frame_shape, source.frames.dtype, source.history_length,
        source.batch_size, 0, compression=compression,
    )  # fmt: skip
    for slot in range(capacity):
        taken = slot % source.capacity
        if source.is_last[taken]:
            replay.add_last(source.frames[taken])
        else:
            replay.add(
                source.frames[taken],
                int(source.actions[taken]),
                float(source.rewards[taken]),
                bool(source.terminals[taken]),
            )
    return replay


def _checkpoint(replay: ReplayMemory, directory: Path) -> tuple[int, float]:
    """Bytes and seconds of a checkpoint that writes every chunk of `replay`."""
    store = CheckpointStore(directory, keep=1)
    start = time.perf_counter()
    saved = store.save(0, {}, replay.arrays, None, "bench")
    seconds = time.perf_counter() - start
    replay_bytes = sum(path.stat().st_size for path in (saved.parent / "replay").iterdir())
    return replay_bytes, seconds


def measure_compression(
    env: str,
    fill_steps: int,
    train_steps: int,
    device: torch.device,
    seed: int = 0,
    rounds: int = 2,
    scratch_dir: Path | None = None,
    checkpoint_capacity: int = 0,
) -> dict[str, Any]:
    """The `compression_*` figures of `dqnlab bench throughput` (see the module
    docstring). With `checkpoint_capacity`, the checkpoints are timed on replays of that
    many slots that repeat the filled ones' transitions (`_cycled`)."""
    config = resolve_config("nature", env=env, seed=seed, replay_capacity=fill_steps)
    shape, dtype = (config.screen_size, config.screen_size), np.dtype(np.uint8)
    raw = ReplayMemory(fill_steps, shape, dtype, config.history_length, config.batch_size, seed)
    packed = ReplayMemory(
        fill_steps, shape, dtype, config.history_length, config.batch_size, seed,
        compression="lz4",
    )  # fmt: skip
    fill_by_random_play([raw, packed], config, fill_steps, seed)
    figures: dict[str, Any] = {"compression_codec": "lz4", "compression_fill_steps": fill_steps}
    figures.update(_memory_figures(raw, packed, config))
    figures.update(_checkpoint_figures(raw, packed, checkpoint_capacity, scratch_dir))
    figures.update(_training_figures(raw, packed, config, device, rounds, train_steps))
    return figures


def _memory_figures(raw: ReplayMemory, packed: ReplayMemory, config: Config) -> dict[str, Any]:
    """The compressed replay's bytes per transition, measured and projected to 1M slots,
    the time to compress a chunk, the time to sample from each replay, and whether both
    give the same minibatches."""
    assert isinstance(packed.frames, CompressedFrames)
    frames, fill_steps = packed.frames, packed.capacity
    figures: dict[str, Any] = {}
    sealed_per_slot = frames.sealed_bytes / max(frames.sealed_slots, 1)
    figures["compression_ratio"] = frames.frame_bytes / sealed_per_slot
    figures["compression_resident_bytes_per_transition"] = packed.resident_bytes / fill_steps
    # A 1M replay of this game: its compressed chunks at the measured size, one raw chunk
    # and the per-slot arrays.
    projected = 1_000_000 * (sealed_per_slot + packed.bytes_per_transition - frames.frame_bytes)
    projected += CHUNK_SLOTS * frames.frame_bytes
    figures["compression_projected_1m_resident_bytes"] = projected
    figures["replay_resident_bytes_per_transition_compressed"] = projected / 1_000_000
    figures["compression_ms_per_chunk"] = (
        1e3 * frames.chunk_seconds * CHUNK_SLOTS / max(frames.sealed_slots, 1)
    )
    figures["compression_sample_us_raw"] = median_sample_us(raw, 1000)
    figures["compression_sample_us"] = median_sample_us(packed, 1000)
    figures["compression_sample_us_added"] = (
        figures["compression_sample_us"] - figures["compression_sample_us_raw"]
    )
    figures["compression_batches_identical"] = all(
        _window_bytes(raw, indices) == _window_bytes(packed, indices)
        for indices in (raw.sample_indices(config.batch_size) for _ in range(200))
    )
    return figures


def _checkpoint_figures(
    raw: ReplayMemory, packed: ReplayMemory, checkpoint_capacity: int, scratch_dir: Path | None
) -> dict[str, Any]:
    """Bytes and seconds of a checkpoint of each replay (of `checkpoint_capacity` slots
    repeating them, if given), in a scratch directory removed after, and their ratios."""
    fill_steps = raw.capacity
    scratch = Path(tempfile.mkdtemp(prefix="dqnlab-bench-", dir=scratch_dir))
    checkpoint_capacity = checkpoint_capacity or fill_steps
    figures: dict[str, Any] = {"compression_checkpoint_capacity": checkpoint_capacity}
    try:
        for name in ("raw", "lz4"):
            replay = {"raw": raw, "lz4": packed}[name]
            if checkpoint_capacity != fill_steps:
                replay = _cycled(raw, checkpoint_capacity, "none" if name == "raw" else name)
            size, seconds = _checkpoint(replay, scratch / name)
            del replay
            figures[f"compression_checkpoint_bytes_{name}"] = size
            figures[f"compression_checkpoint_seconds_{name}"] = seconds
            shutil.rmtree(scratch / name)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    figures["compression_checkpoint_bytes_ratio"] = (
        figures["compression_checkpoint_bytes_raw"] / figures["compression_checkpoint_bytes_lz4"]
    )
    figures["compression_checkpoint_seconds_ratio"] = (
        figures["compression_checkpoint_seconds_raw"]
        / figures["compression_checkpoint_seconds_lz4"]
    )
    return figures


def _training_figures(
    raw: ReplayMemory,
    packed: ReplayMemory,
    config: Config,
    device: torch.device,
    rounds: int,
    train_steps: int,
) -> dict[str, Any]:
    """Training on each replay, after the replay start and the epsilon anneal, in
    alternating rounds: frames/s, the microseconds of each part of a step, and the
    chunks' compression against a step's time."""
    trainings = {
        name: TrainingState(config, device, replay=replay)
        for name, replay in (("raw", raw), ("lz4", packed))
    }
    for training in trainings.values():
        training.steps = config.replay_start_steps + config.epsilon_decay_steps
        for _ in range(50):
            training.advance()
    parts = ("store", "sample", "update", "total")
    runs: dict[str, list[float]] = {"raw": [], "lz4": []}
    part_seconds = {name: dict.fromkeys(parts, 0.0) for name in trainings}
    for _ in range(rounds):
        for name, training in trainings.items():
            runs[name].append(measure_training(training, train_steps)[0])
            for part in parts:
                part_seconds[name][part] += training.seconds[part]
    assert isinstance(packed.frames, CompressedFrames)
    chunk_us_per_step = 1e6 * packed.frames.chunk_seconds / max(packed.writes, 1)
    figures: dict[str, Any] = {"compression_chunk_us_per_step": chunk_us_per_step}
    figures["compression_chunk_work_fraction_of_step"] = chunk_us_per_step / (
        1e6 * config.action_repeat_frames / float(np.mean(runs["lz4"]))
    )
    for name, training in trainings.items():
        # Where the time of a step went, per part: the parts that compression changes
        # (store, sample) stand out from the machine's noise in the others.
        for part in parts:
            figures[f"compression_step_us_{part}_{name}"] = (
                1e6 * part_seconds[name][part] / (rounds * train_steps)
            )
        figures[f"compression_train_frames_per_second_{name}"] = float(np.mean(runs[name]))
        figures[f"compression_train_frames_per_second_{name}_runs"] = [
            round(f, 1) for f in runs[name]
        ]
        training.close()
    figures["compression_train_fps_change"] = (
        figures["compression_train_frames_per_second_lz4"]
        / figures["compression_train_frames_per_second_raw"]
        - 1.0
    )
    return figures
