"""The `nature` preset's training, pinned: run as a script, it trains from a fixed seed for a
few hundred updates and prints the SHA-256 of everything learned (online and target
weights, optimizer state, the replay's sampling stream) with a fingerprint of this
machine's float arithmetic.

`test_nature_pin.py` runs it in a subprocess with the numerical libraries held to their
baseline code paths (`PINNED_ENVIRONMENT`), so that the same code gives the same bits on
different processors, and compares the digests with `nature_pin.json`, recorded by the
code before the DQN family was added (commit 77fcc14). A new entry for a machine whose
arithmetic differs is recorded by running this script at that commit:

    git worktree add /tmp/pin 77fcc14 && cp tests/algorithm/nature_pin.py /tmp/pin/tests/algorithm/
    cd /tmp/pin && env $(python -c "from tests.algorithm.nature_pin import environment_line; \
        print(environment_line())") PYTHONPATH=src python -m tests.algorithm.nature_pin
"""

from __future__ import annotations

import hashlib
import json
import os

# Baseline code paths of ATen, MKL and oneDNN, one thread: their results depend on the
# code path (vector width, blocking), which differs between processors.
PINNED_ENVIRONMENT = {
    "ATEN_CPU_CAPABILITY": "default",
    "MKL_CBWR": "COMPATIBLE",
    "ONEDNN_MAX_CPU_ISA": "SSE41",
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}
STEPS = 900  # replay start 100, then one update every 4 steps: 200 updates
PIN_SETTINGS = {
    "replay_capacity": 600,  # smaller than the steps: the ring wraps
    "replay_start_steps": 100,
    "target_update_steps": 120,
    "epsilon_decay_steps": 400,
    "eval_period_steps": 10_000,
    "heldout_transitions": 0,
    "seed": 7,
}


def environment_line() -> str:
    return " ".join(f"{key}={value}" for key, value in PINNED_ENVIRONMENT.items())


def arithmetic_fingerprint() -> str:
    """SHA-256 of a convolution, a matrix product and a reduction of fixed inputs: equal
    on machines whose float arithmetic (with these libraries and settings) agrees."""
    import torch

    generator = torch.Generator().manual_seed(0)
    images = torch.rand(8, 4, 84, 84, generator=generator)
    kernel = torch.rand(32, 4, 8, 8, generator=generator) - 0.5
    left = torch.rand(64, 3136, generator=generator)
    right = torch.rand(3136, 512, generator=generator)
    convolved = torch.nn.functional.conv2d(
        images.contiguous(memory_format=torch.channels_last), kernel, stride=4
    )
    digest = hashlib.sha256()
    for tensor in (convolved, left @ right, left.sum(dim=1), torch.sqrt(left[0] + 0.01)):
        digest.update(tensor.contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]


def pinned_digests() -> dict[str, str]:
    import numpy as np
    import torch

    from dqnlab.config import resolve_config
    from dqnlab.run.state import TrainingState

    torch.set_num_threads(1)
    config = resolve_config("nature", env="pong", **PIN_SETTINGS)
    try:  # denormals flushed as training flushes them (the pinned commit had no such mode)
        from dqnlab.run.denormals import apply_denormals
    except ImportError:
        pass
    else:
        assert apply_denormals(config) == config.flush_denormals
    state = TrainingState(config, torch.device("cpu"))
    for _ in range(STEPS):
        state.advance()
    agent = state.agent
    assert agent.updates == (STEPS - config.replay_start_steps) // config.update_period_steps

    def digest(tensors: list[torch.Tensor]) -> str:
        hasher = hashlib.sha256()
        for tensor in tensors:
            hasher.update(tensor.detach().contiguous().numpy().tobytes())
        return hasher.hexdigest()

    optimizer_tensors = [
        value
        for group in agent.optimizer.state_dict()["state"].values()
        for value in group.values()
        if isinstance(value, torch.Tensor)
    ]
    next_indices = state.replay.sample_indices(64)
    return {
        "online": digest(list(agent.online.state_dict().values())),
        "target": digest(list(agent.target.state_dict().values())),
        "optimizer": digest(optimizer_tensors),
        "replay_next_indices": hashlib.sha256(np.asarray(next_indices).tobytes()).hexdigest(),
        "loss_sum": repr(float(state.loss_sum)),
    }


def main() -> None:
    for key, value in PINNED_ENVIRONMENT.items():
        if os.environ.get(key) != value:
            raise SystemExit(f"run with {environment_line()} (read when torch loads)")
    print(json.dumps({"arithmetic": arithmetic_fingerprint(), **pinned_digests()}))


if __name__ == "__main__":
    main()
