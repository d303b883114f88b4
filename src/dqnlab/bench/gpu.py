"""The GPU path's figures in one run (`dqnlab bench gpu`, `make bench-gpu`), written to one
JSON file (issue 22, part 5).

Figures: the machine; the update's milliseconds eager and as a CUDA graph
(`update_graph`); training frames/s of the exact loop (nature preset, frames on the device,
after replay start, epsilon at its final 0.1) eager and with the graph; the same with
N = 8, 16, 32 environments (`num_envs`), and N = 16 with an actor thread (`concurrency =
"actor-learner"`, the issue's 10,000 frames/s target; eager, which that mode needs); and a
check that one
update on the GPU gives the CPU's weights within float tolerance, from the same weights on
the same minibatch. Sized to take under 8 minutes on one H100/H200 with 16 cores;
`quick` on CPU takes seconds (the CUDA-only entries then say "skipped: no CUDA").
"""

from __future__ import annotations

import copy
import dataclasses
import os
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np
import torch
from torch.utils.benchmark import Timer

from dqnlab.algorithm.agent import Agent
from dqnlab.algorithm.replay import ReplayMemory
from dqnlab.bench.measure import call_seconds, machine_figures, measure_training, whole_rounds
from dqnlab.config import Config, resolve_config
from dqnlab.errors import ConfigError
from dqnlab.run.concurrent import training_state
from dqnlab.run.state import TrainingState, replay_device

NO_CUDA = "skipped: no CUDA"
VECTOR_ENVS = (8, 16, 32)
ACTOR_LEARNER_ENVS = 16
BUDGET_SECONDS = 7 * 60  # sections not yet begun by then are skipped (the target is 8 min)
# The same minibatch from the same weights: float32 on both, TF32 off for the check. The
# gradient's sums run in another order on the GPU (cuDNN's convolution algorithms), so the
# weights agree to rounding: each within RELATIVE_TOLERANCE of the largest change one
# update made (the changes are ~lr = 2.5e-4 per weight; the weights themselves ~1e-2).
RELATIVE_TOLERANCE = 1e-3


@dataclasses.dataclass(frozen=True)
class Sizes:
    """How much each section measures."""

    replay_capacity: int
    train_steps: int
    vector_steps: int
    update_repeats: int


FULL = Sizes(replay_capacity=100_000, train_steps=5_000, vector_steps=2_000, update_repeats=200)
QUICK = Sizes(replay_capacity=2_000, train_steps=60, vector_steps=20, update_repeats=5)


def run_gpu_benchmark(
    device: torch.device,
    quick: bool = False,
    env: str = "breakout",
    seed: int = 0,
    echo: Callable[[str], object] = print,
    budget_seconds: float = BUDGET_SECONDS,
    only: frozenset[str] | None = None,
) -> dict[str, Any]:
    """All the figures (or the sections named in `only`); a section that fails records its
    error rather than ending the run, and a section not begun once `budget_seconds` have
    passed is skipped."""
    sizes = QUICK if quick else FULL
    started = time.perf_counter()
    cuda = device.type == "cuda"
    figures: dict[str, Any] = {
        "machine": gpu_machine(device),
        "env": env,
        "quick": quick,
        "sizes": dataclasses.asdict(sizes),
        "relative_tolerance": RELATIVE_TOLERANCE,
    }
    graph_modes = ("off", "cuda") if cuda else ("off",)
    on_cuda = partial(_only_on_cuda, cuda)
    sections: list[tuple[str, Callable[[], Any]]] = [
        ("cpu_matches_device", on_cuda(partial(cpu_matches_device, device, env, seed))),
        ("graph_matches_eager", on_cuda(partial(graph_matches_eager, device, env, seed))),
        ("update_ms_graph_off", partial(update_ms, device, env, seed, "off", sizes)),
        ("update_ms_graph_cuda", on_cuda(partial(update_ms, device, env, seed, "cuda", sizes))),
        ("exact_loop_graph_off", partial(exact_loop, device, env, seed, "off", sizes)),
        ("exact_loop_graph_cuda", on_cuda(partial(exact_loop, device, env, seed, "cuda", sizes))),
    ]
    for num_envs in VECTOR_ENVS:  # with the graph where there is CUDA
        measure: Callable[[], Any] = partial(
            vector_loop, device, env, seed, num_envs, sizes, graph_modes[-1]
        )
        sections.append((f"num_envs_{num_envs}", measure))
    sections.append((
        f"num_envs_{ACTOR_LEARNER_ENVS}_actor_learner",
        partial(vector_loop, device, env, seed, ACTOR_LEARNER_ENVS, sizes, "off", "actor-learner"),
    ))  # fmt: skip
    unknown = sorted((only or frozenset()) - {name for name, _ in sections})
    if unknown:
        known = ", ".join(name for name, _ in sections)
        raise ConfigError(f"--only: unknown section {', '.join(unknown)}; the sections: {known}")
    for name, measure in sections:
        if only is not None and name not in only:
            continue
        if time.perf_counter() - started > budget_seconds:
            figures[name] = "skipped: the time budget was spent"
            continue
        echo(f"dqnlab bench gpu: {name} ...")
        try:
            figures[name] = measure()
        except Exception as error:  # noqa: BLE001 - one section's failure is a figure too
            figures[name] = f"failed: {type(error).__name__}: {error}"
        echo(f"dqnlab bench gpu: {name} = {figures[name]}")
    figures["seconds"] = round(time.perf_counter() - started, 1)
    return figures


def _only_on_cuda(cuda: bool, measure: Callable[[], Any]) -> Callable[[], Any]:
    return measure if cuda else lambda: NO_CUDA


def gpu_machine(device: torch.device) -> dict[str, Any]:
    """`machine_figures` with the GPU's name and memory, and the CUDA and cuDNN versions."""
    machine = machine_figures(device)
    machine["cores"] = os.cpu_count()
    machine["cuda_available"] = torch.cuda.is_available()
    machine["cuda"] = torch.version.cuda
    if device.type == "cuda":
        properties = torch.cuda.get_device_properties(device)
        machine["gpu"] = properties.name
        machine["gpu_memory_gib"] = round(properties.total_memory / 2**30, 1)
        machine["cudnn"] = torch.backends.cudnn.version()
        machine["tf32_matmul"] = torch.backends.cuda.matmul.allow_tf32
        machine["tf32_cudnn"] = torch.backends.cudnn.allow_tf32
    return machine


def nature_config(env: str, seed: int, capacity: int, update_graph: str, **extra: Any) -> Config:
    settings: dict[str, Any] = {"replay_storage": "device", "heldout_transitions": 0, **extra}
    return resolve_config(
        "nature",
        env=env,
        seed=seed,
        replay_capacity=capacity,
        update_graph=update_graph,
        **settings,
    )


def filled_state(config: Config, device: torch.device) -> TrainingState:
    """A training state whose replay (frames on `device`) is full of random frames."""
    on_device = replay_device(config, device, (84, 84), np.dtype(np.uint8))
    replay = ReplayMemory(
        config.replay_capacity, (84, 84), np.uint8, config.history_length, config.batch_size,
        config.seed, device=on_device, streams=config.num_envs,
    )  # fmt: skip
    pool = np.random.default_rng(config.seed).integers(0, 256, size=(64, 84, 84), dtype=np.uint8)
    streams = config.num_envs  # one ring per environment, written in turn as a vector step does
    for i in range(config.replay_capacity):
        replay.add(pool[i % 64], i % 4, float(i % 3 - 1), i % 500 == 499, i % streams)
    return training_state(config, device, replay=replay)


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def update_ms(
    device: torch.device, env: str, seed: int, update_graph: str, sizes: Sizes
) -> dict[str, float]:
    """The update alone on fresh minibatches: back to back (what training sees when the
    host runs ahead), and one at a time, each waited for."""
    state = filled_state(nature_config(env, seed, sizes.replay_capacity, update_graph), device)
    agent, replay = state.agent, state.replay
    for _ in range(5):  # the graph's warm-up and capture
        agent.update(replay.sample())
    # Timer waits for the device before and after the updates, on the update's threads.
    timer = Timer(
        "agent.update(replay.sample())",
        globals={"agent": agent, "replay": replay},
        num_threads=torch.get_num_threads(),
    )
    back_to_back = timer.timeit(sizes.update_repeats).mean

    def update_waited() -> None:
        agent.update(replay.sample())
        synchronize(device)

    waited = call_seconds(update_waited, sizes.update_repeats)
    state.close()
    return {
        "back_to_back_ms": round(back_to_back * 1e3, 4),
        "waited_median_ms": round(float(np.median(waited)) * 1e3, 4),
    }


def exact_loop(
    device: torch.device, env: str, seed: int, update_graph: str, sizes: Sizes
) -> dict[str, Any]:
    """Frames/s of the Nature loop (one environment, act, store, update every 4 steps)."""
    state = filled_state(nature_config(env, seed, sizes.replay_capacity, update_graph), device)
    return _training_figures(state, sizes.train_steps)


def vector_loop(
    device: torch.device,
    env: str,
    seed: int,
    num_envs: int,
    sizes: Sizes,
    update_graph: str,
    concurrency: str = "none",
) -> dict[str, Any] | str:
    """Frames/s with `num_envs` environments acting as one batch (`num_envs`), stepped
    by the training thread or by an actor thread (`concurrency`)."""
    config = nature_config(
        env, seed, sizes.replay_capacity, update_graph, num_envs=num_envs, concurrency=concurrency
    )
    state = filled_state(config, device)
    figures = _training_figures(state, sizes.vector_steps)
    figures["update_graph"] = update_graph
    figures["concurrency"] = concurrency
    return figures


def _training_figures(state: TrainingState, steps: int) -> dict[str, Any]:
    config = state.config
    state.steps = config.replay_start_steps + config.epsilon_decay_steps  # epsilon 0.1
    steps = whole_rounds(steps, len(state.envs))
    # Agent steps, of all the environments together, in whole rounds: an actor thread acts
    # a round ahead, and the learner may only ask for whole rounds of it.
    warmed = state.steps + whole_rounds(min(100, steps), len(state.envs))
    try:  # closed on failure too: an actor thread left running aborts the process at exit
        while state.steps < warmed:
            state.advance(warmed - state.steps)
        frames_per_second, split = measure_training(state, steps)
        updates = state.agent.updates
    finally:
        state.close()
    return {
        "frames_per_second": round(frames_per_second, 1),
        "steps": steps,
        "updates": updates,
        "split": {name: round(share, 4) for name, share in split.items()},
    }


def _weights(agent: Agent) -> list[torch.Tensor]:
    return [p.detach().to("cpu", copy=True) for p in agent.online.parameters()]


def _agreement(
    before: list[torch.Tensor], reference: list[torch.Tensor], other: list[torch.Tensor]
) -> dict[str, Any]:
    """How far `other`'s weights are from `reference`'s, against the largest change that
    the update made from `before`."""
    largest_change = max(float((r - b).abs().max()) for b, r in zip(before, reference, strict=True))
    largest_difference = max(
        float((o - r).abs().max()) for r, o in zip(reference, other, strict=True)
    )
    relative = largest_difference / largest_change if largest_change else float("inf")
    return {
        "largest_weight_change": largest_change,
        "largest_weight_difference": largest_difference,
        "relative_difference": relative,
        "tolerance": RELATIVE_TOLERANCE,
        "within_tolerance": relative <= RELATIVE_TOLERANCE,
        "bit_identical": largest_difference == 0.0,
    }


def cpu_matches_device(device: torch.device, env: str, seed: int) -> dict[str, Any]:
    """One update on the CPU and one on `device`, from the same weights on the same
    minibatch (gathered on the CPU, so the frames are the same bytes), TF32 off."""
    config = nature_config(env, seed, 2_000, "off", replay_storage="host")
    state = filled_state(config, torch.device("cpu"))
    batch = state.replay.sample()
    cpu_agent = state.agent
    # The same weights (the target network starts as a copy of the online one in both).
    gpu_agent = Agent(copy.deepcopy(cpu_agent.online), cpu_agent.num_actions, config, device, 0)
    before = _weights(cpu_agent)
    saved = (torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32)
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    try:
        cpu_agent.update(batch)
        gpu_agent.update(batch)
        synchronize(device)
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = saved
    state.close()
    return _agreement(before, _weights(cpu_agent), _weights(gpu_agent))


def graph_matches_eager(device: torch.device, env: str, seed: int) -> dict[str, Any]:
    """Eight updates eager and eight through the graph (three warm-up, a capture, replays)
    from the same weights on the same minibatches, on the device."""
    results = []
    before: list[torch.Tensor] = []
    for mode in ("off", "cuda"):
        state = filled_state(nature_config(env, seed, 2_000, mode), device)
        state.replay.rng = np.random.default_rng(seed)
        before = _weights(state.agent)
        for _ in range(8):
            state.agent.update(state.replay.sample())
        synchronize(device)
        results.append(_weights(state.agent))
        state.close()
    return _agreement(before, results[0], results[1])
