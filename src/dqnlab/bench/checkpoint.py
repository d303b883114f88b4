"""What a stop checkpoint of the `nature` preset costs early in a run (`dqnlab bench
checkpoint`): the seconds and bytes of the checkpoint that Ctrl-C writes after `steps`
agent steps, with the preset's full-size replay (1M slots), raw and compressed.

Two replays of the preset's capacity, one raw and one LZ4, are filled with the same
`steps` transitions of uniformly random play (`compression.fill_by_random_play`). Each is
then saved the way a stop saves a run that had no checkpoint yet: a fresh store, the
slots written since the replay was made, the training state (networks, optimizer, RNGs,
environments) and last.pt, every file fsynced, into a temporary run directory. The save
is timed in `rounds` alternating rounds, each into a new directory, and the median is the
figure; then the checkpoint is loaded into a fresh replay of the same kind and compared
with the one saved.
"""

from __future__ import annotations

import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dqnlab.algorithm.compression import CompressedFrames
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.bench.compression import fill_by_random_play
from dqnlab.bench.measure import machine_figures
from dqnlab.config import Config, config_fingerprint, resolve_config
from dqnlab.run import rundir
from dqnlab.run.checkpoints import CheckpointStore, written_slots
from dqnlab.run.state import TrainingState

CODECS = ("none", "lz4")
# The targets for a stop checkpoint at 25k steps of the nature preset (issue 22).
TARGET_SECONDS = 5.0
TARGET_BYTES = 250e6


def _replay(config: Config, compression: str, seed: int) -> ReplayMemory:
    return ReplayMemory(
        config.replay_capacity, (config.screen_size,) * 2, np.uint8, config.history_length,
        config.batch_size, seed, compression=compression,
    )  # fmt: skip


def _stop_checkpoint(training: TrainingState, run_dir: Path) -> float:
    """Seconds to write what a stop writes in a run without an earlier checkpoint."""
    config, replay = training.config, training.replay
    store = CheckpointStore(run_dir, keep=config.checkpoints_kept)
    env = training.env
    start = time.perf_counter()
    changed = written_slots(0, replay.writes, replay.capacity)
    state = {"learner": training.state_dict(), "run": {}}
    store.save(training.steps, state, replay.arrays, changed, config_fingerprint(config))
    payload = rundir.network_payload(
        config, (config.history_length, *env.observation_shape), env.observation_dtype,
        env.action_names, training.steps, training.agent.online, None,
    )  # fmt: skip
    rundir.save_network(rundir.network_path(run_dir, "last"), payload)
    return time.perf_counter() - start


def _bytes_under(directory: Path) -> int:
    return sum(path.stat().st_size for path in directory.rglob("*") if path.is_file())


def _frames(replay: ReplayMemory, slots: int) -> np.ndarray:
    """The first `slots` frames, raw."""
    if isinstance(replay.frames, CompressedFrames):
        chunks = -(-slots // replay.frames.chunk_slots)
        return np.concatenate([replay.frames.chunk(i) for i in range(chunks)])[:slots]
    return replay.frames[:slots]


def _load_and_compare(config: Config, run_dir: Path, saved: ReplayMemory) -> tuple[float, bool]:
    """Seconds to load the checkpoint into a fresh replay, and whether it is the same."""
    fresh = _replay(config, config.replay_compression, seed=1)
    start = time.perf_counter()
    loaded = CheckpointStore(run_dir).latest(config_fingerprint(config), into=fresh.arrays)
    seconds = time.perf_counter() - start
    assert loaded is not None
    fresh.load_state_dict(loaded.state["learner"]["replay"])
    # The slots past the filled ones are zeros in both: the written ones tell.
    size = saved.size
    same = (fresh.position, fresh.size, fresh.writes) == (saved.position, size, saved.writes)
    same = same and np.array_equal(_frames(fresh, size), _frames(saved, size))
    for name in ("actions", "rewards", "terminals", "is_last"):
        same = same and np.array_equal(getattr(fresh, name), getattr(saved, name))
    return seconds, bool(same)


def measure_stop_checkpoint(
    env: str = "pong",
    steps: int = 25_000,
    device: torch.device | None = None,
    seed: int = 0,
    rounds: int = 3,
    scratch_dir: Path | None = None,
) -> dict[str, Any]:
    """The `checkpoint_*` figures of `dqnlab bench checkpoint` (see the module
    docstring): per codec, the median seconds and the bytes of the stop checkpoint, the
    seconds of each round, the seconds to load it and whether it loads the same."""
    device = device or torch.device("cpu")
    configs = {
        codec: resolve_config("nature", env=env, seed=seed, replay_compression=codec)
        for codec in CODECS
    }
    base = configs["none"]
    figures: dict[str, Any] = {**machine_figures(device), "checkpoint_env": env}
    figures["checkpoint_steps"] = steps
    figures["checkpoint_replay_capacity"] = base.replay_capacity
    replays = {codec: _replay(config, codec, seed) for codec, config in configs.items()}
    fill_by_random_play(list(replays.values()), base, steps, seed)
    trainings = {
        codec: TrainingState(configs[codec], device, replay=replays[codec]) for codec in CODECS
    }
    for training in trainings.values():
        training.steps = steps
    figures["checkpoint_replay_slots_filled"] = replays["none"].size
    scratch = Path(tempfile.mkdtemp(prefix="dqnlab-bench-checkpoint-", dir=scratch_dir))
    seconds: dict[str, list[float]] = {codec: [] for codec in CODECS}
    try:
        for round_ in range(rounds):
            for codec, training in trainings.items():
                run_dir = scratch / f"{codec}-{round_}"
                seconds[codec].append(_stop_checkpoint(training, run_dir))
                figures[f"checkpoint_stop_bytes_{codec}"] = _bytes_under(run_dir)
                replay_dir = run_dir / "checkpoints" / "replay"
                figures[f"checkpoint_stop_replay_bytes_{codec}"] = _bytes_under(replay_dir)
                if round_ < rounds - 1:
                    shutil.rmtree(run_dir)
        for codec in CODECS:
            run_dir = scratch / f"{codec}-{rounds - 1}"
            load_seconds, same = _load_and_compare(configs[codec], run_dir, replays[codec])
            figures[f"checkpoint_stop_seconds_{codec}"] = statistics.median(seconds[codec])
            figures[f"checkpoint_stop_seconds_{codec}_runs"] = [round(s, 3) for s in seconds[codec]]
            figures[f"checkpoint_load_seconds_{codec}"] = load_seconds
            figures[f"checkpoint_loads_identical_{codec}"] = same
            figures[f"checkpoint_stop_within_targets_{codec}"] = (
                figures[f"checkpoint_stop_seconds_{codec}"] <= TARGET_SECONDS
                and figures[f"checkpoint_stop_bytes_{codec}"] <= TARGET_BYTES
            )
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
        for training in trainings.values():
            training.close()
    figures["checkpoint_target_seconds"] = TARGET_SECONDS
    figures["checkpoint_target_bytes"] = TARGET_BYTES
    return figures
