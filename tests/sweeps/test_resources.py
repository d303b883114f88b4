"""What each run asks Ray for, and runs that no node of the cluster can hold refused."""

from __future__ import annotations

import pytest

from dqnlab.config import resolve_config
from dqnlab.errors import DqnlabError
from dqnlab.sweeps.resources import (
    PROCESS_OVERHEAD_BYTES,
    RunResources,
    check_resources,
    run_memory_bytes,
)

NODE = {"CPU": 4.0, "memory": 8e9}


def test_memory_asked_is_the_replay_plus_the_process() -> None:
    config = resolve_config("nature", {"replay_compression": "none"}, env="pong")  # 1M 84 × 84
    assert run_memory_bytes(config) > 1_000_000 * 84 * 84 + PROCESS_OVERHEAD_BYTES
    compressed = resolve_config("nature", env="pong")  # the preset's lz4
    assert compressed.replay_compression == "lz4"
    assert run_memory_bytes(compressed) < run_memory_bytes(config) / 3


def test_resources_no_node_has_are_refused_with_the_numbers() -> None:
    check_resources(RunResources(2, 0, int(4e9)), [NODE])
    with pytest.raises(DqnlabError, match=r"8 CPUs, 0 GPUs and 4.0 GB.*4 CPUs/0 GPUs/8.0 GB"):
        check_resources(RunResources(8, 0, int(4e9)), [NODE])
    with pytest.raises(DqnlabError, match="more than any node has"):
        check_resources(RunResources(1, 0, int(9e9)), [NODE])
    with pytest.raises(DqnlabError, match="--gpus-per-run 0.25: the cluster has no GPUs"):
        check_resources(RunResources(1, 0.25, int(1e9)), [NODE])
    check_resources(RunResources(1, 0.25, int(1e9)), [{**NODE, "GPU": 1.0}])
