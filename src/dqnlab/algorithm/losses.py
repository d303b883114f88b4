"""The loss part of the update: from a minibatch and the two networks to one loss per
transition and the priorities prioritized replay is told back.

A loss part is a class built as `Class(config)` and called as
`part(online, target, batch) -> LossOutput`, `batch` the minibatch on the training device
(`minibatch.Transitions`). The agent does the rest of the update the same way for every
part: it weights the per-transition losses by the importance weights
(prioritized replay), sums or averages them (`loss_reduction`), back-propagates, clips
the gradient norm (`max_gradient_norm`) and steps the optimizer. The shipped parts:

    TDLoss           Nature's Q-learning loss: Huber at td_error_clip on
                     r + discount (1 - terminal) value(s'), the value from the target
                     network by max (Nature) or by the online network's choice (double)
    CategoricalLoss  C51's cross-entropy against the projected target distribution
                     (Bellemare et al. 2017), the next action chosen the same two ways

A researcher's own part (`loss = "module:Class"`) is written against the same interface,
usually by subclassing one of these and overriding one method (`TDLoss.targets`, say):
`examples/munchausen.py` is a whole published variant in that form.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from dqnlab.algorithm.minibatch import Transitions
from dqnlab.config import Config
from dqnlab.errors import ConfigError
from dqnlab.parts import load_part


@dataclass(frozen=True)
class LossOutput:
    losses: torch.Tensor  # (batch,): differentiable with respect to the online network
    # (batch,) non-negative, detached: the size of each transition's error, from which
    # prioritized replay makes its priorities; None where a part has none to give.
    priorities: torch.Tensor | None


class Loss:
    """The interface of a loss part (and the base of the shipped ones)."""

    def __init__(self, config: Config) -> None:
        self.config = config

    def __call__(self, online: nn.Module, target: nn.Module, batch: Transitions) -> LossOutput:
        raise NotImplementedError

    def next_actions(
        self, online: nn.Module, next_q_target: torch.Tensor, batch: Transitions
    ) -> torch.Tensor:
        """The bootstrap action in s': the target network's greedy one (`target = "max"`),
        or the online network's (`"double"`, van Hasselt et al. 2016: the online network
        picks the action, the target network values it)."""
        if self.config.target == "double":
            return online(batch.next_observations).argmax(dim=1)
        return next_q_target.argmax(dim=1)


class TDLoss(Loss):
    """The Nature DQN's loss: per transition, the Huber loss between Q(s, a) and the TD
    target with threshold `td_error_clip`, whose gradient is the clipped TD error (the Lua
    code's clip_delta); half the squared error with td_error_clip = 0. Priorities: |TD
    error|, unclipped (dqn_zoo's prioritized agent), except under the shipped uniform
    replay, which asks for none."""

    def __call__(self, online: nn.Module, target: nn.Module, batch: Transitions) -> LossOutput:
        q_taken = online(batch.observations).gather(1, batch.actions.unsqueeze(1)).squeeze(1)
        with torch.no_grad():
            q_target = self.targets(online, target, batch)
        clip = self.config.td_error_clip
        if clip > 0:
            losses = F.huber_loss(q_taken, q_target, delta=clip, reduction="none")
        else:
            losses = 0.5 * (q_target - q_taken) ** 2
        if self.config.replay_sampling == "uniform":  # asks for none: two operations saved
            return LossOutput(losses, None)
        return LossOutput(losses, (q_target - q_taken.detach()).abs())

    def targets(self, online: nn.Module, target: nn.Module, batch: Transitions) -> torch.Tensor:
        """y = r + discount (1 - terminal) Q_target(s', a*), computed without gradients."""
        return batch.rewards + batch.discounts * (1.0 - batch.terminals) * self.next_values(
            online, target, batch
        )

    def next_values(self, online: nn.Module, target: nn.Module, batch: Transitions) -> torch.Tensor:
        next_q = target(batch.next_observations)
        # The agent passes the online network as the target where the target is an unchanged
        # copy of it (`Agent.target_is_a_copy`): the online network's choice is then the
        # greedy action of these very values, and its value their maximum.
        if self.config.target == "max" or target is online:
            return next_q.max(dim=1).values
        actions = self.next_actions(online, next_q, batch)
        return next_q.gather(1, actions.unsqueeze(1)).squeeze(1)


def project_onto_support(
    atoms: torch.Tensor, probabilities: torch.Tensor, support: torch.Tensor
) -> torch.Tensor:
    """The distribution with `probabilities` on `atoms` (batch, j), moved onto the evenly
    spaced `support` (i,): each atom is clipped to the support's range and its mass spread
    over the two nearest support points in proportion to closeness,
    m_i = sum_j clip(1 - |atom_j - z_i| / dz, 0, 1) p_j (Bellemare et al. 2017, Eq. 7, as
    Dopamine's `project_distribution` writes it). An atom exactly on a support point gives
    it all its mass, where the floor/ceil form of Algorithm 1 loses it (dqn-family.md 8.4)."""
    v_min, v_max = support[0], support[-1]
    atom_gap = (v_max - v_min) / (support.numel() - 1)
    clipped = atoms.clamp(v_min, v_max)
    distance = (clipped.unsqueeze(1) - support.view(1, -1, 1)).abs()  # (batch, i, j)
    closeness = (1.0 - distance / atom_gap).clamp(0.0, 1.0)
    return torch.bmm(closeness, probabilities.unsqueeze(2)).squeeze(2)


def categorical_projection(
    support: torch.Tensor,
    probabilities: torch.Tensor,
    rewards: torch.Tensor,
    bootstrap_discounts: torch.Tensor,
) -> torch.Tensor:
    """C51's target distribution: the atoms r + discount z_j with the next state's
    probabilities p_j, projected onto the support (`project_onto_support`).
    `probabilities` (batch, atoms); `rewards`, `bootstrap_discounts` (batch,): the
    discount of the bootstrap, 0 after a terminal."""
    atoms = rewards.unsqueeze(1) + bootstrap_discounts.unsqueeze(1) * support.unsqueeze(0)
    return project_onto_support(atoms, probabilities, support)


class CategoricalLoss(Loss):
    """C51 (Bellemare et al. 2017): the cross-entropy -sum_i m_i log p_i(s, a) between the
    projected target distribution m and the online network's distribution for the action
    taken. The next action is the target network's greedy one (C51), or the online
    network's (`target = "double"`, as Rainbow composes them). Priorities: the
    cross-entropy itself (Rainbow prioritises by the KL loss; the two differ by the
    target's entropy, which Dopamine's Rainbow also leaves in)."""

    def __call__(self, online: nn.Module, target: nn.Module, batch: Transitions) -> LossOutput:
        log_probabilities = _log_probabilities(online, batch.observations)
        index = batch.actions.view(-1, 1, 1).expand(-1, 1, log_probabilities.shape[2])
        log_taken = log_probabilities.gather(1, index).squeeze(1)  # (batch, atoms)
        with torch.no_grad():
            projected = self.target_distribution(online, target, batch)
        losses = -(projected * log_taken).sum(dim=1)
        return LossOutput(losses, losses.detach())

    def target_distribution(
        self, online: nn.Module, target: nn.Module, batch: Transitions
    ) -> torch.Tensor:
        support = _support(target)
        next_probabilities = _log_probabilities(target, batch.next_observations).exp()
        next_q = (next_probabilities * support).sum(dim=2)
        actions = self.next_actions(online, next_q, batch)
        index = actions.view(-1, 1, 1).expand(-1, 1, next_probabilities.shape[2])
        chosen = next_probabilities.gather(1, index).squeeze(1)
        bootstrap = batch.discounts * (1.0 - batch.terminals)
        return categorical_projection(support, chosen, batch.rewards, bootstrap)


def _log_probabilities(network: nn.Module, observations: torch.Tensor) -> torch.Tensor:
    method = getattr(network, "log_probabilities", None)
    if method is None:
        raise ConfigError(
            "the categorical loss needs a distributional network (distributional = c51), "
            f"and {type(network).__name__} has no log_probabilities"
        )
    result: torch.Tensor = method(observations)
    return result


def _support(network: nn.Module) -> torch.Tensor:
    support = getattr(network, "support", None)
    if not isinstance(support, torch.Tensor):
        raise ConfigError(f"{type(network).__name__} has no C51 support")
    return support


def build_loss(config: Config) -> Loss:
    """The loss part `loss` names: the shipped one for the other settings (`auto`), or a
    user's `module:Class`, built as `Class(config)`."""
    if config.loss == "auto":
        return CategoricalLoss(config) if config.distributional == "c51" else TDLoss(config)
    part = load_part("loss", config.loss, config)
    if not callable(part):
        raise ConfigError(f"loss = {config.loss!r} built {type(part).__name__}, not callable")
    return part  # type: ignore[no-any-return]


def importance_exponent_at(step: int, config: Config) -> float:
    """Prioritized replay's beta for the update at `step`: `importance_exponent_start` at
    the first update, linear to 1 at `total_steps` (Schaul et al. 2016, section 3.4:
    annealed to 1 by the end of learning)."""
    first = config.replay_start_steps
    span = max(1, config.total_steps - first)
    progress = min(1.0, max(0.0, (step - first) / span))
    start = config.importance_exponent_start
    return start + (1.0 - start) * progress
