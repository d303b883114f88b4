"""Munchausen-IQN (Vieillard, Pietquin and Geist, NeurIPS 2020, section 4) as a dqnlab loss
part on the shipped IQN head: the Munchausen target of `examples/munchausen.py`, per
sampled fraction tau' of the next state's return distribution:

    y_tau' = r + alpha * clip(tau * log pi(a|s), l0, 0)
               + discount * (1 - terminal) * sum_a' pi(a'|s') (Z_tau'(s', a') - tau * log pi(a'|s'))

pi is the softmax at temperature tau of the target network's Q-values, each the mean over
K fractions (the head's `acting_samples`), drawn apart for s and for s'; Z_tau' is the
target network's value at N' fractions (the loss's `target_samples`). The quantile Huber
loss and the online side are IQN's. Values as the authors' code runs it
(google-research/google-research at 72d82b6, munchausen_rl/configs/atari.gin and
agents/m_iqn.py): tau 0.03, alpha 0.9, l0 -1, one-step returns, IQN's N = N' = 64, K = 32.
The authors also act on pi (`interact = 'stochastic'`); here acting stays epsilon-greedy,
the `policy` part's business.

From the repository's root (the module must be importable):

    PYTHONPATH=. dqnlab train --env CartPole-v1 --preset iqn \
        --set loss=examples.munchausen_iqn:MunchausenIQNLoss
"""

from __future__ import annotations

import torch
from torch import nn

from dqnlab.algorithm.losses import Transitions
from dqnlab.algorithm.quantile import ImplicitQuantileHead, ImplicitQuantileLoss
from dqnlab.config import Config
from dqnlab.errors import ConfigError
from dqnlab.parts import part_settings
from examples.munchausen import MunchausenLoss, scaled_log_policy


class MunchausenIQNLoss(ImplicitQuantileLoss):
    """IQN's loss (its settings kept) with Munchausen's target and three more settings."""

    SETTINGS = {**ImplicitQuantileLoss.SETTINGS, **MunchausenLoss.SETTINGS}

    def __init__(self, config: Config) -> None:
        super().__init__(config)
        if config.n_step != 1:
            raise ConfigError("MunchausenIQNLoss is written for n_step = 1, as the paper runs it")
        settings = part_settings("loss", type(self), config)
        self.tau, self.alpha, self.l0 = settings["tau"], settings["alpha"], settings["l0"]
        if not (self.tau > 0 and self.l0 <= 0):
            raise ConfigError(f"parts.loss: tau = {self.tau} must be > 0, l0 = {self.l0} <= 0")

    def target_quantiles(
        self, online: nn.Module, target: nn.Module, batch: Transitions
    ) -> torch.Tensor:
        """y at N' fractions per transition, (batch, N')."""
        head, torso = target.head, target.torso
        if not isinstance(head, ImplicitQuantileHead):
            raise ConfigError("MunchausenIQNLoss needs head = 'dqnlab.algorithm.quantile:"
                              "implicit_quantile_head'")  # fmt: skip
        next_features = torso(batch.next_observations)
        next_q = head(next_features).mean(dim=2)  # K fractions of the head's own
        next_log_policy = scaled_log_policy(next_q, self.tau)  # (batch, actions)
        next_policy = torch.softmax(next_q / self.tau, dim=1)
        fractions = self.sample_fractions(next_features.shape[0], self.target_samples,
                                          next_features.device)  # fmt: skip
        next_values = head.quantile_values(next_features, fractions)  # (batch, actions, N')
        soft = (next_policy.unsqueeze(2) * (next_values - next_log_policy.unsqueeze(2))).sum(1)
        q = head(torso(batch.observations)).mean(dim=2)
        taken = scaled_log_policy(q, self.tau).gather(1, batch.actions.unsqueeze(1)).squeeze(1)
        bonus = self.alpha * taken.clamp(self.l0, 0.0)
        bootstrap = (batch.discounts * (1.0 - batch.terminals)).unsqueeze(1)
        return (batch.rewards + bonus).unsqueeze(1) + bootstrap * soft
