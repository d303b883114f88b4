"""Generators for the parts that draw random numbers (`dqnlab.parts.RandomPart`): one per
part, on the training device, seeded from the agent's seed and the part's name, and saved
with the agent, so that a user's part that draws resumes exactly as the shipped ones do
(the noisy layers' and the augmentation's generators are the agent's own, from before)."""

from __future__ import annotations

import zlib
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import nn

from dqnlab.parts import RandomPart


def random_parts(named: Mapping[str, object]) -> dict[str, RandomPart]:
    """The `RandomPart`s among `named` parts and, for a network, among its modules, by
    name (`online.head`, `target.head`, `loss`), in a fixed order."""
    found: dict[str, RandomPart] = {}
    for name, part in named.items():
        if isinstance(part, nn.Module):
            for module_name, module in part.named_modules():
                if isinstance(module, RandomPart):
                    found[f"{name}.{module_name}" if module_name else name] = module
        elif isinstance(part, RandomPart):
            found[name] = part
    return found


def attach_generators(
    parts: Mapping[str, RandomPart], device: torch.device, seed: int
) -> dict[str, torch.Generator]:
    """A generator for each part, set as its `generator`: seeded from `seed` and the name."""
    generators = {}
    for name, part in parts.items():
        generator = torch.Generator(device=device)
        entropy = [seed, zlib.crc32(name.encode())]
        generator.manual_seed(int(np.random.SeedSequence(entropy).generate_state(1)[0]))
        part.generator = generator
        generators[name] = generator
    return generators


def generator_states(generators: Mapping[str, torch.Generator]) -> dict[str, torch.Tensor]:
    return {name: generator.get_state() for name, generator in generators.items()}


def restore_generators(
    generators: Mapping[str, torch.Generator], states: Mapping[str, Any]
) -> None:
    """Each generator's saved state; a part the checkpoint has no state for (a checkpoint
    from before parts could draw) keeps its fresh one."""
    for name in generators:
        if name in states:
            generators[name].set_state(states[name].cpu())
