"""What each run of a sweep asks Ray for (CPUs, GPUs, host memory: its replay plus the
process), and the check that some node of the cluster can hold it."""

from __future__ import annotations

from dataclasses import dataclass

from dqnlab.config import Config
from dqnlab.errors import DqnlabError
from dqnlab.sweeps.grid import Sweep

# Host memory of a `dqnlab train` process besides its replay: peak RSS of tiny runs
# (replay of 1,000 slots) measured with `/usr/bin/time -v` (docs/benchmark.md, figures), 0.9 GB on
# CartPole and 1.1 GB on Pong, rounded up for the evaluation's worker processes.
PROCESS_OVERHEAD_BYTES = 1_500_000_000
VECTOR_SLOT_BYTES = 1024  # a vector observation's slot: up to 256 float32 features


@dataclass(frozen=True)
class RunResources:
    """What each run asks Ray for: CPUs (also its PyTorch threads), GPUs (fractions
    share one), and host memory in bytes (its replay plus the process)."""

    cpus: float
    gpus: float
    memory_bytes: int


def replay_memory_bytes(config: Config) -> int:
    """Host bytes of the run's replay: the frames (compressed where the codec's measured
    size is known) of an Atari game, a generous slot for vector observations."""
    from dqnlab.algorithm.compression import expected_frame_bytes
    from dqnlab.algorithm.replay import compresses, replay_bytes
    from dqnlab.envs import is_atari

    if not is_atari(config.env):
        return config.replay_capacity * VECTOR_SLOT_BYTES
    frame_shape = (config.screen_size, config.screen_size)
    compressed = None
    if compresses(config.replay_compression, frame_shape):
        compressed = expected_frame_bytes(config.replay_compression, config.env)
    import numpy as np

    return replay_bytes(
        config.replay_capacity, frame_shape, np.dtype(np.uint8), compressed, config.num_envs
    )


def run_memory_bytes(config: Config) -> int:
    return replay_memory_bytes(config) + PROCESS_OVERHEAD_BYTES


def sweep_resources(
    sweep: Sweep, cpus: float, gpus: float, memory_bytes: int | None = None
) -> RunResources:
    """Each run's request: the largest replay of the grid, unless `memory_bytes` says."""
    if cpus <= 0:
        raise DqnlabError(f"--cpus-per-run {cpus} must be positive")
    if gpus < 0 or gpus > 1 and gpus != int(gpus):
        raise DqnlabError(f"--gpus-per-run {gpus} must be a fraction of one GPU or whole GPUs")
    memory = memory_bytes or max(run_memory_bytes(run.config) for run in sweep.runs)
    return RunResources(cpus, gpus, memory)


def check_resources(resources: RunResources, nodes: list[dict[str, float]]) -> None:
    """Refuse up front a run that no node of the cluster can hold, with the numbers."""
    if resources.gpus > 0 and not any(node.get("GPU", 0) > 0 for node in nodes):
        raise DqnlabError(
            f"--gpus-per-run {resources.gpus:g}: the cluster has no GPUs ({len(nodes)} nodes); "
            "accepted here: --gpus-per-run 0"
        )
    fits = [
        node
        for node in nodes
        if node.get("CPU", 0) >= resources.cpus
        and node.get("GPU", 0) >= resources.gpus
        and node.get("memory", 0) >= resources.memory_bytes
    ]
    if not fits:
        largest = ", ".join(
            f"{node.get('CPU', 0):g} CPUs/{node.get('GPU', 0):g} GPUs/"
            f"{node.get('memory', 0) / 1e9:.1f} GB" for node in nodes
        )  # fmt: skip
        raise DqnlabError(
            f"each run asks for {resources.cpus:g} CPUs, {resources.gpus:g} GPUs and "
            f"{resources.memory_bytes / 1e9:.1f} GB of memory, more than any node has "
            f"(nodes: {largest or 'none'}); lower --cpus-per-run/--gpus-per-run, or "
            "replay_capacity (--set), or add larger nodes"
        )
