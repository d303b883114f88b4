"""Randomness for any part (`dqnlab.parts.RandomPart`): the agent gives each part that
draws a generator of its own, saved in checkpoints, so that a run with a user's loss and a
user's head that both draw, killed at random moments and resumed, ends bit-identical to
the same run left alone."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from dqnlab.algorithm.agent import agent_for_input
from dqnlab.algorithm.losses import TDLoss, Transitions
from dqnlab.config import Config, resolve_config
from dqnlab.parts import RandomPart
from tests.run.test_resume import CARTPOLE, assert_same_run, train_killed_and_resumed

HERE = "tests.run.test_random_parts"


class JitteredTDLoss(TDLoss, RandomPart):
    """The TD loss with N(0, 0.1) noise added to each target, drawn from its generator."""

    def targets(self, online: nn.Module, target: nn.Module, batch: Transitions) -> torch.Tensor:
        y = super().targets(online, target, batch)
        return y + 0.1 * torch.randn(y.shape, generator=self.generator, device=y.device)


class DropoutHead(nn.Module, RandomPart):
    """A linear head whose features are dropped at random (p = 0.2) in train mode."""

    def __init__(self, in_features: int, num_actions: int) -> None:
        super().__init__()
        self.linear = nn.Linear(in_features, num_actions)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        if self.training:
            keep = torch.rand(features.shape, generator=self.generator, device=features.device)
            features = features * (keep > 0.2) / 0.8
        return self.linear(features).unsqueeze(2)


def dropout_head(
    in_features: int, num_actions: int, config: Config, hidden_width: int | None
) -> nn.Module:
    return DropoutHead(in_features, num_actions)


def _agent(seed: int = 0):
    config = resolve_config(
        "classic", env="CartPole-v1", loss=f"{HERE}:JitteredTDLoss", head=f"{HERE}:dropout_head"
    )
    shape, dtype = (1, 4), np.dtype(np.float32)
    return agent_for_input(config, shape, dtype, ["left", "right"], torch.device("cpu"), seed)


def test_each_part_that_draws_gets_a_generator_of_its_own() -> None:
    agent = _agent()
    assert sorted(agent.part_generators) == ["loss", "online.head", "target.head"]
    assert agent.loss.generator is agent.part_generators["loss"]
    assert agent.online.head.generator is agent.part_generators["online.head"]
    assert agent.target.head.generator is agent.part_generators["target.head"]
    first_draws = [torch.rand(3, generator=g).tolist() for g in agent.part_generators.values()]
    assert len({tuple(draws) for draws in first_draws}) == 3  # three streams, not one
    again = _agent()  # the same seed: the same streams
    generators = again.part_generators.values()
    assert first_draws == [torch.rand(3, generator=g).tolist() for g in generators]
    other = _agent(seed=1)
    assert first_draws[0] != torch.rand(3, generator=other.part_generators["loss"]).tolist()


def test_the_generators_are_saved_and_restored_with_the_agent() -> None:
    agent = _agent()
    for generator in agent.part_generators.values():
        torch.rand(5, generator=generator)  # moved on from the seed
    state = agent.state_dict()
    assert sorted(state["part_rngs"]) == ["loss", "online.head", "target.head"]
    expected = {name: torch.rand(4, generator=g) for name, g in agent.part_generators.items()}
    restored = _agent(seed=9)
    restored.load_state_dict(state)
    for name, generator in restored.part_generators.items():
        assert torch.equal(torch.rand(4, generator=generator), expected[name]), name
    del state["part_rngs"]  # a checkpoint from before parts could draw: fresh generators
    _agent().load_state_dict(state)


def test_a_run_with_parts_that_draw_resumes_bit_identical(tmp_path: Path) -> None:
    args = [
        *CARTPOLE, "--steps", "1500", "--set", f"loss={HERE}:JitteredTDLoss",
        "--set", f"head={HERE}:dropout_head", "--set", "mlp_hidden_sizes=[32]",
        "--set", "eval_period_steps=500",
    ]  # fmt: skip
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    kills = train_killed_and_resumed(args, reference, resumed, most_kills=2)
    assert kills >= 1, "the run was too fast to be killed"
    assert_same_run(reference, resumed)
