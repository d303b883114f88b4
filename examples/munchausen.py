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
DQN with Adam at 5e-5): the part's own settings, `--set parts.loss.tau=0.01` to change one.

Use it from the repository's root (the module must be importable):

    PYTHONPATH=. dqnlab train --env CartPole-v1 --set loss=examples.munchausen:MunchausenLoss
"""

from __future__ import annotations

import torch
from torch import nn

from dqnlab.algorithm.losses import TDLoss, Transitions
from dqnlab.config import Config
from dqnlab.errors import ConfigError
from dqnlab.parts import PartSetting, part_settings


def scaled_log_policy(q_values: torch.Tensor, tau: float) -> torch.Tensor:
    """tau * log softmax(q / tau), computed stably (log_softmax subtracts the max first)."""
    return tau * torch.log_softmax(q_values / tau, dim=1)


class MunchausenLoss(TDLoss):
    """DQN's TD loss with the Munchausen target (`targets`); priorities as the TD loss."""

    SETTINGS = {
        "tau": PartSetting(0.03, "Temperature of the softmax policy of the target's Q-values"),
        "alpha": PartSetting(0.9, "Scale of the Munchausen bonus tau log pi(a|s)"),
        "l0": PartSetting(-1.0, "Floor of the clipped bonus where pi(a|s) is tiny"),
    }

    def __init__(self, config: Config) -> None:
        super().__init__(config)
        if config.n_step != 1 or config.distributional != "none":
            raise ConfigError("MunchausenLoss is written for n_step = 1, distributional = none")
        settings = part_settings("loss", MunchausenLoss, config)
        self.tau, self.alpha, self.l0 = settings["tau"], settings["alpha"], settings["l0"]
        if not (self.tau > 0 and self.l0 <= 0):
            raise ConfigError(f"parts.loss: tau = {self.tau} must be > 0, l0 = {self.l0} <= 0")

    def targets(self, online: nn.Module, target: nn.Module, batch: Transitions) -> torch.Tensor:
        next_q = target(batch.next_observations)
        next_log_policy = scaled_log_policy(next_q, self.tau)
        next_policy = torch.softmax(next_q / self.tau, dim=1)
        soft_next_value = (next_policy * (next_q - next_log_policy)).sum(dim=1)
        taken_log_policy = scaled_log_policy(target(batch.observations), self.tau).gather(
            1, batch.actions.unsqueeze(1)
        )
        bonus = self.alpha * taken_log_policy.squeeze(1).clamp(self.l0, 0.0)
        return batch.rewards + bonus + batch.discounts * (1.0 - batch.terminals) * soft_next_value
