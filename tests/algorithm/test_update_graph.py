"""The update on the GPU path: the same update as before on CPU, no read of a device value
per step, and (where there is CUDA) the captured graph equal to the eager update."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest
import torch
from torch import nn

from dqnlab.algorithm.agent import Agent, agent_for_input
from dqnlab.algorithm.heads import sample_noise
from dqnlab.algorithm.losses import Transitions
from dqnlab.algorithm.replay import Batch
from dqnlab.algorithm.update_graph import WARMUP_UPDATES, HostToDevice
from dqnlab.config import Config, resolve_config
from dqnlab.errors import ConfigError
from dqnlab.run.state import TrainingState

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def _previous_update(agent: Agent, batch: Batch) -> tuple[torch.Tensor, torch.Tensor | None]:
    """`Agent.update` as it was before this path (commit 56e570e), with the per-parameter
    optimizer loop: the reference the new one must match bit for bit on CPU."""
    agent.online.train()
    agent.optimizer.zero_grad(set_to_none=False)
    if batch.window is not None:
        window = torch.from_numpy(np.asarray(batch.window))
        history = window.shape[1] - 1
        observations, next_observations = window[:, :history], window[:, 1:]
    else:
        observations = torch.from_numpy(np.asarray(batch.observations))
        next_observations = torch.from_numpy(np.asarray(batch.next_observations))
    if agent.noisy:
        agent.target.train()
        sample_noise(agent.online, agent.noise_generator)
        sample_noise(agent.target, agent.noise_generator)
    rewards = torch.from_numpy(batch.rewards)
    discounts = torch.from_numpy(batch.discounts)
    output = agent.loss(
        agent.online,
        agent.target,
        Transitions(
            observations, torch.from_numpy(batch.actions), rewards,
            torch.from_numpy(batch.terminals), discounts, next_observations,
        ),
    )  # fmt: skip
    losses = output.losses
    if batch.weights is not None:
        losses = losses * torch.from_numpy(batch.weights)
    loss = losses.sum() if agent.config.loss_reduction == "sum" else losses.mean()
    loss.backward()
    if agent.config.max_gradient_norm > 0:
        nn.utils.clip_grad_norm_(agent.online.parameters(), agent.config.max_gradient_norm)
    agent.optimizer.step()
    agent.updates += 1
    return loss.detach(), output.priorities


def _batches(config: Config, count: int, shape: tuple[int, ...], seed: int) -> list[Batch]:
    rng = np.random.default_rng(seed)
    history, batch_size = config.history_length, 8
    batches = []
    for n in range(count):
        frames = rng.integers(0, 256, size=(batch_size, history + 1, *shape), dtype=np.uint8)
        window = n % 2 == 0  # both kinds: one window, or two histories
        batches.append(
            Batch(
                observations=frames[:, :history],
                actions=rng.integers(0, 3, size=batch_size).astype(np.int64),
                rewards=rng.choice([-1.0, 0.0, 1.0], size=batch_size).astype(np.float32),
                terminals=(rng.random(batch_size) < 0.2).astype(np.float32),
                next_observations=frames[:, 1:],
                window=frames if window else None,
                discounts=np.full(batch_size, config.discount**2, dtype=np.float32),
                weights=rng.random(batch_size).astype(np.float32) if n % 3 else None,
            )
        )
    return batches


@pytest.mark.parametrize("preset", ["nature", "dueling", "c51", "rainbow", "prioritized"])
def test_the_update_gives_the_same_bits_as_before_on_cpu(preset: str) -> None:
    config = resolve_config(preset, env="pong", batch_size=8)
    shape = (84, 84)
    new = agent_for_input(
        config, (config.history_length, *shape), np.dtype(np.uint8), ["a", "b", "c"],
        torch.device("cpu"), seed=3,
    )  # fmt: skip
    old = copy.deepcopy(new)
    if hasattr(old.optimizer, "foreach"):
        old.optimizer.foreach = False  # the per-parameter loop of before
    for batch in _batches(config, 4, shape, seed=11):
        new_loss, new_priorities = new.update(batch)
        old_loss, old_priorities = _previous_update(old, batch)
        assert torch.equal(new_loss, old_loss)
        assert (new_priorities is None) == (old_priorities is None)
        if new_priorities is not None and old_priorities is not None:
            assert torch.equal(new_priorities, old_priorities)
    assert new.updates == old.updates == 4
    for a, b in zip(new.online.parameters(), old.online.parameters(), strict=True):
        assert torch.equal(a, b)
    new_state, old_state = new.optimizer.state_dict()["state"], old.optimizer.state_dict()["state"]
    for key, values in new_state.items():
        for name, value in values.items():
            assert torch.equal(value, old_state[key][name]), (key, name)


def test_a_cuda_graph_on_cpu_is_refused_in_one_line_naming_the_setting() -> None:
    config = resolve_config("classic", env="CartPole-v1", update_graph="cuda")
    with pytest.raises(ConfigError, match="update_graph") as raised:
        agent_for_input(config, (1, 4), np.dtype(np.float32), ["l", "r"], torch.device("cpu"), 0)
    assert "\n" not in str(raised.value)
    with pytest.raises(ConfigError, match="update_graph.*compile_update"):
        resolve_config("nature", update_graph="cuda", compile_update=True)
    with pytest.raises(ConfigError, match="update_graph"):
        resolve_config("nature", update_graph="always")


def test_small_arrays_reach_the_device_unchanged_on_cpu() -> None:
    arrays = (np.arange(4, dtype=np.int64), None, np.ones(3, dtype=np.float32))
    actions, nothing, weights = HostToDevice(torch.device("cpu")).upload(arrays)
    assert nothing is None and actions is not None and weights is not None
    assert actions.tolist() == [0, 1, 2, 3] and weights.dtype == torch.float32


def test_packed_arrays_arrive_whole_in_buffers_that_stay_in_place() -> None:
    """The CUDA path's packing (one buffer, a view per array at an aligned offset), run on
    the CPU: every dtype and length the minibatch has, None left out, same addresses."""
    staging = HostToDevice(torch.device("cpu"), slots=2, packed=True)
    rng = np.random.default_rng(0)
    addresses = None
    for _ in range(5):
        arrays = (
            rng.integers(0, 6, size=7).astype(np.int64),
            rng.random(7).astype(np.float32),
            None,
            rng.random(7).astype(np.float32),
            np.array([True, False, True]),
        )
        sent = staging.upload(arrays)
        assert sent[2] is None
        for array, tensor in zip(arrays, sent, strict=True):
            if array is not None:
                assert tensor is not None and staging.owns(tensor)
                np.testing.assert_array_equal(tensor.numpy(), array)
        now = [t.data_ptr() for t in sent if t is not None]
        assert addresses is None or now == addresses
        addresses = now
    assert not staging.owns(torch.zeros(7))


_READS = ("item", "tolist", "numpy", "cpu", "__float__", "__int__", "__bool__")


@contextmanager
def _counting_reads(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[str]]:
    """Every call of a Tensor method that brings a value to the host (which on a GPU
    waits for the device), by name."""
    calls: list[str] = []
    for name in _READS:
        original = getattr(torch.Tensor, name)

        def counted(self, *args, _name=name, _original=original, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
            calls.append(_name)
            return _original(self, *args, **kwargs)

        monkeypatch.setattr(torch.Tensor, name, counted)
    yield calls
    monkeypatch.undo()


@pytest.mark.parametrize(("sampling", "reads_per_update"), [("uniform", 0), ("prioritized", 1)])
def test_the_training_step_reads_no_device_value_per_update(
    monkeypatch: pytest.MonkeyPatch, sampling: str, reads_per_update: int
) -> None:
    """300 agent steps of the loop with the replay's frames on the device (the CPU here),
    acting stubbed out (an action needs the network's output on the host: that read is
    the acting side's) and the per-update finiteness check off, as on a GPU: the update
    side reads nothing back, but prioritized replay's priorities (its sum tree is on the
    host: one read per update)."""
    config = resolve_config(
        "classic", env="CartPole-v1", replay_storage="device", replay_sampling=sampling,
        replay_start_steps=40, replay_capacity=500, target_update_steps=50,
    )  # fmt: skip
    state = TrainingState(config, torch.device("cpu"))
    state.check_every_update = False
    actions = np.random.default_rng(0).integers(0, 2, size=1000)
    state.agent.act = lambda frames, epsilon, training=False: int(actions[state.steps])  # type: ignore[method-assign]
    for _ in range(60):  # past replay start, so the counted steps all may update
        state.advance()
    before = state.agent.updates
    with _counting_reads(monkeypatch) as reads:
        for _ in range(300):
            state.advance()
    updates = state.agent.updates - before
    assert updates == 300 // config.update_period_steps
    assert len(reads) == reads_per_update * updates, reads[:10]
    assert state.mean_loss() is not None  # read every few hundred steps instead
    state.close()


@CUDA
def test_host_to_device_sends_each_update_into_the_same_buffers() -> None:
    staging = HostToDevice(torch.device("cuda"))
    first = staging.upload((np.arange(8, dtype=np.int64), np.full(8, 0.5, dtype=np.float32)))
    addresses = [t.data_ptr() for t in first if t is not None]
    for value in range(10):
        sent = staging.upload(
            (np.arange(8, dtype=np.int64) + value, np.full(8, value, dtype=np.float32))
        )
        assert [t.data_ptr() for t in sent if t is not None] == addresses
        actions, rewards = sent
        assert actions is not None and rewards is not None
        assert actions.tolist() == list(range(value, value + 8)) and rewards.sum() == 8 * value


@CUDA
@pytest.mark.parametrize("preset", ["nature", "rainbow", "prioritized", "dueling"])
def test_the_captured_update_equals_the_eager_one_on_cuda(preset: str) -> None:
    """The same batches from the same weights, eager and through the graph (warm-up,
    capture and replays): the same weights to float rounding (bit-identical expected, as
    the same kernels run; the tolerance allows cuDNN's choice of algorithm)."""
    results = []
    for mode in ("off", "cuda"):
        torch.manual_seed(0)
        config = resolve_config(preset, env="pong", batch_size=8, update_graph=mode)
        agent = agent_for_input(
            config, (config.history_length, 84, 84), np.dtype(np.uint8), ["a", "b", "c"],
            torch.device("cuda"), seed=3,
        )  # fmt: skip
        losses = [agent.update(batch)[0].item() for batch in _one_kind(config, 8)]
        results.append((losses, [p.detach().cpu() for p in agent.online.parameters()]))
        if mode == "cuda":
            assert agent._graph is not None and agent._graph.graph is not None
    (eager_losses, eager), (graph_losses, graphed) = results
    np.testing.assert_allclose(graph_losses, eager_losses, rtol=1e-5)
    for a, b in zip(eager, graphed, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)


def _one_kind(config: Config, count: int) -> list[Batch]:
    """Batches of one kind (windows, no weights): one graph serves them all."""
    return [
        dataclasses.replace(batch, weights=None)
        for batch in _batches(config, 2 * count, (84, 84), seed=5)[::2]
    ]


@CUDA
def test_the_graph_is_captured_again_after_a_state_is_loaded() -> None:
    config = resolve_config("nature", env="pong", batch_size=8, update_graph="cuda")
    agent = agent_for_input(
        config, (4, 84, 84), np.dtype(np.uint8), ["a", "b", "c"], torch.device("cuda"), 0
    )
    batches = _one_kind(config, WARMUP_UPDATES + 2)
    for batch in batches:
        agent.update(batch)
    assert agent._graph is not None and agent._graph.graph is not None
    agent.load_state_dict(agent.state_dict())
    assert agent._graph.graph is None  # the optimizer's tensors were replaced


@CUDA
def test_the_device_replay_and_the_graph_update_never_wait_for_the_device() -> None:
    """With frames on the device and the graph: sampling and updating (after the capture)
    run with PyTorch's synchronisation check raising on any wait."""
    config = resolve_config(
        "nature", env="pong", replay_storage="device", update_graph="cuda",
        replay_capacity=1000, replay_start_steps=100, heldout_transitions=0,
    )  # fmt: skip
    state = TrainingState(config, torch.device("cuda"))
    for _ in range(100):
        state.advance()
    for _ in range(WARMUP_UPDATES + 1):  # warm-up and capture
        state.agent.update(state.replay.sample())
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(20):
            loss, _ = state.agent.update(state.replay.sample())
            state.loss_sum += loss
            state.losses += 1
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert state.mean_loss() is not None
    state.close()
