"""The agent: epsilon schedule, clipped TD loss, acting, target copies and update timing."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from dqnlab.algorithm.agent import Agent, epsilon_at, set_mode
from dqnlab.algorithm.losses import TDLoss, Transitions
from dqnlab.algorithm.networks import NatureCNN, computes_a_function
from dqnlab.algorithm.replay import Batch
from dqnlab.config import resolve_config

_NATURE = resolve_config("nature", env="pong")


def test_epsilon_schedule_of_the_nature_preset(nature) -> None:
    assert epsilon_at(0, nature) == 1.0
    assert epsilon_at(49_999, nature) == 1.0  # replay start: uniform random
    assert epsilon_at(50_000, nature) == 1.0  # anneal begins
    assert epsilon_at(550_000, nature) == pytest.approx(0.55)  # half way: 1 - 0.9/2
    assert epsilon_at(1_050_000, nature) == pytest.approx(0.1)
    assert epsilon_at(40_000_000, nature) == pytest.approx(0.1)


def td_loss(online, target, observations, actions, rewards, terminals, next_observations,
            discount, td_error_clip, reduction) -> torch.Tensor:  # fmt: skip
    """The TD loss part's per-transition losses, reduced as the agent reduces them."""
    config = dataclasses.replace(_NATURE, td_error_clip=td_error_clip)
    batch = Transitions(observations, actions, rewards, terminals,
                        torch.full_like(rewards, discount), next_observations)  # fmt: skip
    losses = TDLoss(config)(online, target, batch).losses
    return losses.sum() if reduction == "sum" else losses.mean()


class Linear1(nn.Module):
    """Q(s, a) = w_a * s for a scalar input s: easy to work out by hand."""

    def __init__(self, weights: list[float]) -> None:
        super().__init__()
        self.w = nn.Parameter(torch.tensor(weights))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.reshape(-1, 1).float() * self.w


def test_td_loss_clips_the_error_in_the_gradient_and_sums_over_the_batch() -> None:
    online = Linear1([1.0, 2.0])
    target = Linear1([3.0, 0.5])
    observations = torch.tensor([1.0, 1.0, 2.0])
    next_observations = torch.tensor([1.0, 2.0, 1.0])
    actions = torch.tensor([0, 1, 1])
    rewards = torch.tensor([0.5, 1.0, -1.0])
    terminals = torch.tensor([0.0, 0.0, 1.0])
    loss = td_loss(online, target, observations, actions, rewards, terminals,
                   next_observations, 0.9, 1.0, "sum")  # fmt: skip
    loss.backward()
    # q_taken = [1*1, 2*1, 2*2] = [1, 2, 4]
    # q_target = [0.5 + 0.9*max(3,0.5), 1 + 0.9*max(6,1), -1] = [3.2, 6.4, -1]
    # td_error = [2.2, 4.4, -5] -> clipped [1, 1, -1]; Huber: |d| - 0.5 each.
    assert loss.item() == pytest.approx((2.2 - 0.5) + (4.4 - 0.5) + (5 - 0.5))
    # dL/dw_a = -sum_i clip(d_i) * s_i over samples with action a
    # w_0: -(1 * 1) = -1 ; w_1: -(1 * 1) - (-1 * 2) = 1
    assert online.w.grad.tolist() == pytest.approx([-1.0, 1.0])
    assert target.w.grad is None


def test_td_loss_small_errors_are_not_clipped_and_mean_reduction() -> None:
    online = Linear1([1.0])
    target = Linear1([1.0])
    one = torch.tensor([1.0, 1.0])
    loss = td_loss(online, target, one, torch.tensor([0, 0]), torch.tensor([0.3, -0.4]),
                   torch.tensor([1.0, 1.0]), one, 0.99, 1.0, "mean")  # fmt: skip
    loss.backward()
    # td_error = [0.3 - 1, -0.4 - 1] = [-0.7, -1.4]: 0.5*0.49 and 1.4-0.5
    assert loss.item() == pytest.approx((0.245 + 0.9) / 2)
    assert online.w.grad.item() == pytest.approx(-(-0.7 - 1.0) / 2)


def test_acting_is_greedy_at_epsilon_zero_and_uniform_at_one(nature) -> None:
    config = dataclasses.replace(nature, history_length=1)
    agent = Agent(Linear1([0.1, 0.7, -0.2]), 3, config, torch.device("cpu"), seed=0)
    observation = np.ones((1,), dtype=np.float32)
    assert {agent.act(observation, 0.0) for _ in range(20)} == {1}
    counts = np.bincount([agent.act(observation, 1.0) for _ in range(3000)], minlength=3)
    assert np.all(np.abs(counts - 1000) < 150)


def test_ties_are_broken_at_random(nature) -> None:
    agent = Agent(Linear1([0.5, 0.5, 0.1]), 3, nature, torch.device("cpu"), seed=0)
    chosen = {agent.act(np.ones((1,), dtype=np.float32), 0.0) for _ in range(50)}
    assert chosen == {0, 1}


def test_sync_target_copies_weights(nature) -> None:
    agent = Agent(Linear1([1.0, 2.0]), 2, nature, torch.device("cpu"), seed=0)
    with torch.no_grad():
        agent.online.w.add_(5.0)
    assert agent.target.w.tolist() == [1.0, 2.0]
    agent.sync_target()
    assert agent.target.w.tolist() == [6.0, 7.0]
    assert not agent.target.w.requires_grad


def _reference_updates(network: nn.Module, batches, config, steps: int) -> list[torch.Tensor]:
    """The Nature DQN update written out plainly: default memory layout, F.huber_loss
    summed over the batch, autograd, and DeepMind's RMSProp equations (NeuralQLearner.lua),
    in float64: the exact answer that a float32 update approaches up to its rounding (a
    float32 reference would carry rounding of its own, larger than the agent's with some
    CPUs' convolution kernels)."""
    online = copy.deepcopy(network).to(memory_format=torch.contiguous_format).double()
    target = copy.deepcopy(online)
    params = list(online.parameters())
    grad_avgs = [torch.zeros_like(p) for p in params]
    square_avgs = [torch.zeros_like(p) for p in params]
    decay, lr, eps = config.rmsprop_decay, config.learning_rate, config.rmsprop_epsilon

    def q_values(net: nn.Module, frames: np.ndarray) -> torch.Tensor:
        return net.head(net.features(torch.from_numpy(frames).double() / 255.0))

    for batch in batches[:steps]:
        actions = torch.from_numpy(batch.actions)
        q_taken = q_values(online, batch.observations)[torch.arange(len(actions)), actions]
        with torch.no_grad():
            next_q = q_values(target, batch.next_observations).max(dim=1).values
            not_terminal = 1.0 - torch.from_numpy(batch.terminals).double()
            rewards = torch.from_numpy(batch.rewards).double()
            q_target = rewards + config.discount * not_terminal * next_q
        loss = F.huber_loss(q_taken, q_target, delta=config.td_error_clip, reduction="sum")
        gradients = torch.autograd.grad(loss, params)
        with torch.no_grad():
            for p, delta, g, g2 in zip(params, gradients, grad_avgs, square_avgs, strict=True):
                g.copy_(decay * g + (1 - decay) * delta)
                g2.copy_(decay * g2 + (1 - decay) * delta * delta)
                p.sub_(lr * delta / torch.sqrt(g2 - g * g + eps))
    return params


def _random_batches(count: int, seed: int, shared_window: bool = False) -> list[Batch]:
    rng = np.random.default_rng(seed)
    batches = []
    for _ in range(count):
        # Overlapping views of one window, as the replay memory returns them.
        window = rng.integers(0, 256, size=(32, 5, 84, 84), dtype=np.uint8)
        batches.append(
            Batch(
                observations=window[:, :4],
                actions=rng.integers(0, 6, size=32).astype(np.int64),
                rewards=rng.choice([-1.0, 0.0, 1.0], size=32).astype(np.float32),
                terminals=(rng.random(32) < 0.2).astype(np.float32),
                discounts=np.full(32, 0.99, dtype=np.float32),
                next_observations=window[:, 1:],
                window=window if shared_window else None,
            )
        )
    return batches


@pytest.mark.parametrize("shared_window", [False, True], ids=["two-copies", "window-once"])
@pytest.mark.parametrize(
    "compile_update", [False, pytest.param(True, marks=pytest.mark.slow, id="compiled")]
)
def test_update_matches_a_plain_reference_implementation(
    nature, compile_update, shared_window
) -> None:
    torch.manual_seed(3)
    network = NatureCNN((4, 84, 84), num_actions=6)
    initial = [p.detach().clone() for p in network.parameters()]
    expected = _reference_updates(network, _random_batches(4, seed=5), nature, steps=4)
    agent = Agent(network, 6, nature, torch.device("cpu"), seed=0, compile_update=compile_update)
    for batch in _random_batches(4, seed=5, shared_window=shared_window):
        loss, priorities = agent.update(batch)
    assert loss.shape == () and not loss.requires_grad
    assert priorities is None  # the shipped uniform replay asks the loss for none
    assert agent.updates == 4
    for actual, reference in zip(agent.online.parameters(), expected, strict=True):
        torch.testing.assert_close(actual.double(), reference, rtol=1e-5, atol=1e-8)
    # The target network keeps the initial weights until sync_target.
    for kept, start in zip(agent.target.parameters(), initial, strict=True):
        assert torch.equal(kept, start)


class _ModeCounted(nn.Module):
    """A part with a `train` of its own: it counts the calls."""

    def __init__(self) -> None:
        super().__init__()
        self.calls = 0

    def train(self, mode: bool = True) -> _ModeCounted:
        self.calls += 1
        return super().train(mode)


def test_set_mode_sets_any_module_in_the_other_mode_and_skips_the_walk_otherwise() -> None:
    network = nn.Sequential(nn.Linear(2, 2), nn.Sequential(nn.ReLU(), nn.Linear(2, 1)))
    walks = []
    network.train = lambda mode=True: walks.append(mode) or nn.Module.train(network, mode)
    set_mode(network, training=True)  # every module in train mode already: no walk
    assert walks == []
    network[1][1].eval()  # one module deep inside in the other mode: the whole walk
    set_mode(network, training=True)
    assert walks == [True] and all(module.training for module in network.modules())
    set_mode(network, training=False)
    assert walks == [True, False] and not any(module.training for module in network.modules())
    set_mode(network, training=False)
    assert walks == [True, False]
    # A module with a train of its own is called every time, as Module.train would.
    counted = nn.Sequential(nn.Linear(2, 2), _ModeCounted())
    set_mode(counted, training=True)
    set_mode(counted, training=True)
    assert counted[1].calls == 2


def _counted_passes(network: nn.Module) -> list[int]:
    calls = [0]
    network.register_forward_hook(lambda *_: calls.__setitem__(0, calls[0] + 1))
    return calls


def test_a_fresh_target_copy_is_replaced_by_the_online_network_with_the_same_bits() -> None:
    """Double DQN with the target copied after every update (drq_epsilon): the online network
    values s' in one pass instead of the online and the target networks' two, and the
    weights after four updates are the same bits as with both passes."""
    config = dataclasses.replace(_NATURE, target="double")
    torch.manual_seed(3)
    network = NatureCNN((4, 84, 84), num_actions=6)
    agents = [Agent(copy.deepcopy(network), 6, config, torch.device("cpu"), seed=0) for _ in "ab"]
    one_pass, two_passes = agents
    two_passes._online_stands_for_target = False
    assert one_pass._online_stands_for_target
    passes = {id(agent): (_counted_passes(agent.online), _counted_passes(agent.target))
              for agent in agents}  # fmt: skip
    for batch in _random_batches(4, seed=5):
        for agent in agents:
            agent.sync_target()
            agent.update(batch)
    assert [calls[0] for calls in passes[id(one_pass)]] == [8, 0]  # Q(s), Q(s') per update
    assert [calls[0] for calls in passes[id(two_passes)]] == [8, 4]
    for a, b in zip(one_pass.online.parameters(), two_passes.online.parameters(), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("optimizer", ["deepmind_rmsprop", "adam"])
def test_the_target_network_is_used_once_either_network_changed_since_the_copy(optimizer) -> None:
    """Whatever changed the weights: PyTorch's fused Adam steps without bumping the
    parameters' version counters, so only comparing the weights themselves can tell."""
    config = dataclasses.replace(_NATURE, target="double", optimizer=optimizer)
    torch.manual_seed(3)
    agent = Agent(NatureCNN((4, 84, 84), num_actions=6), 6, config, torch.device("cpu"), seed=0)
    target_passes = _counted_passes(agent.target)
    first, second, third = _random_batches(3, seed=5)
    agent.update(first)  # built as a copy: the online network stands in for it
    assert target_passes == [0]
    agent.update(second)  # the optimizer stepped since: the target
    assert target_passes == [1]
    agent.sync_target()
    with torch.no_grad():
        agent.target.features[0].bias.add_(0.0)  # in place, the same bits: still a copy
    agent.update(third)
    assert target_passes == [1]
    agent.sync_target()
    with torch.no_grad():
        agent.target.features[0].bias[0] = -agent.online.features[0].bias[0]  # one weight
    agent.update(first)
    assert target_passes == [2]
    agent.sync_target()
    with torch.no_grad():  # the same value, another bit: 0.0 and -0.0
        agent.target.features[0].bias[0] = 0.0
        agent.online.features[0].bias[0] = -0.0
    agent.update(second)
    assert target_passes == [3]


def test_only_networks_that_compute_a_function_of_their_input_may_stand_in() -> None:
    class OwnLinear(nn.Linear):
        pass

    assert computes_a_function(NatureCNN((4, 84, 84), num_actions=6))
    assert not computes_a_function(nn.Sequential(nn.Linear(4, 4), nn.Dropout(0.1)))
    assert not computes_a_function(nn.Sequential(OwnLinear(4, 4)))  # its forward may differ
    torch.manual_seed(3)
    dropout = nn.Sequential(nn.Flatten(), nn.Linear(4, 2), nn.Dropout())
    for target, network in [("max", NatureCNN((4, 84, 84), num_actions=6)), ("double", dropout)]:
        config = dataclasses.replace(_NATURE, target=target)
        assert not Agent(network, 2, config, torch.device("cpu"), seed=0)._online_stands_for_target


class _UsersNetwork(nn.Module):
    """A user's module: its forward may read the mode, so the agent sets it."""

    def __init__(self) -> None:
        super().__init__()
        self.linear = nn.Linear(4 * 84 * 84, 6)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        return self.linear(frames.flatten(1).float() / 255.0)


def test_only_a_network_that_reads_its_mode_is_switched_between_acting_and_updating() -> None:
    batch = _random_batches(1, seed=5)[0]
    torch.manual_seed(3)
    for network, switched in [(NatureCNN((4, 84, 84), num_actions=6), False),
                              (_UsersNetwork(), True)]:  # fmt: skip
        agent = Agent(network, 6, _NATURE, torch.device("cpu"), seed=0)
        walks: list[bool] = []
        agent.online.train = lambda mode=True, net=agent.online, walks=walks: (  # type: ignore[method-assign]
            walks.append(mode) or nn.Module.train(net, mode)
        )
        agent.q_values(batch.observations[:1])
        agent.update(batch)
        agent.q_values(batch.observations[:1])
        assert walks == ([False, True, False] if switched else [])
