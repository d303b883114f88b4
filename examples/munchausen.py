"""Munchausen DQN (Vieillard, Pietquin and Geist, NeurIPS 2020) as a dqnlab loss part.

Munchausen-DQN changes one thing in DQN: the TD target. The agent's own policy is the
softmax of the target network's Q-values at temperature tau, and the target adds
(1) alpha times the clipped, scaled log-probability of the action taken, the "Munchausen"
bonus, and (2) a soft, entropy-regularised value of the next state in place of the max:

    y = r + alpha * clip(tau * log pi(a|s), l0, 0)
          + discount * (1 - terminal) * sum_a' pi(a'|s') (q(s', a') - tau * log pi(a'|s'))

with q and pi from the target network (paper, section 3 and Algorithm 1). Everything else
is DQN's: the loss (Huber here, as dqnlab's TD loss), replay, epsilon-greedy acting. The
paper's Atari values are tau = 0.03, alpha = 0.9, l0 = -1 (its Table 2, on Dopamine's
DQN with Adam at 5e-5).

Use it from the repository's root (the module must be importable):

    PYTHONPATH=. dqnlab train --env CartPole-v1 --set loss=examples.munchausen:MunchausenLoss
"""

from __future__ import annotations

import torch
from torch import nn

from dqnlab.algorithm.losses import TDLoss, Transitions
from dqnlab.config import Config
from dqnlab.errors import ConfigError

TEMPERATURE = 0.03  # tau
BONUS_SCALE = 0.9  # alpha
LOG_POLICY_FLOOR = -1.0  # l0: the clip keeps the bonus bounded where pi(a|s) is tiny


def scaled_log_policy(q_values: torch.Tensor) -> torch.Tensor:
    """tau * log softmax(q / tau), computed stably (log_softmax subtracts the max first)."""
    return TEMPERATURE * torch.log_softmax(q_values / TEMPERATURE, dim=1)


class MunchausenLoss(TDLoss):
    """DQN's TD loss with the Munchausen target (`targets`); priorities as the TD loss."""

    def __init__(self, config: Config) -> None:
        super().__init__(config)
        if config.n_step != 1 or config.distributional != "none":
            raise ConfigError("MunchausenLoss is written for n_step = 1, distributional = none")

    def targets(self, online: nn.Module, target: nn.Module, batch: Transitions) -> torch.Tensor:
        next_q = target(batch.next_observations)
        next_log_policy = scaled_log_policy(next_q)
        next_policy = torch.softmax(next_q / TEMPERATURE, dim=1)
        soft_next_value = (next_policy * (next_q - next_log_policy)).sum(dim=1)
        taken_log_policy = scaled_log_policy(target(batch.observations)).gather(
            1, batch.actions.unsqueeze(1)
        )
        bonus = BONUS_SCALE * taken_log_policy.squeeze(1).clamp(LOG_POLICY_FLOOR, 0.0)
        return batch.rewards + bonus + batch.discounts * (1.0 - batch.terminals) * soft_next_value
