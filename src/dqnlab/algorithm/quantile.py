"""QR-DQN and IQN, shipped as parts through the same interfaces as a user's: a head factory
(`head = "dqnlab.algorithm.quantile:quantile_head"`), a loss part, settings of their own
(`parts.head.quantiles`, `parts.loss.kappa`...) and, for IQN, generators of their own
(`dqnlab.parts.RandomPart`), so that nothing in the agent knows about quantiles.

Both learn, per action, quantiles of the return distribution with the quantile Huber loss
(Dabney et al. 2018a, "Distributional Reinforcement Learning with Quantile Regression",
Eq. 9-10): for online quantile estimates theta_i at fractions tau_i and target samples
T theta_j = r + discount (1 - terminal) theta_j(s', a*),

    rho(u_ij) = |tau_i - 1{u_ij < 0}| L_kappa(u_ij) / kappa,   u_ij = T theta_j - theta_i,

summed over i and averaged over j per transition (the papers' Eq. 10 and IQN's Eq. 3, as
Dopamine's `quantile_agent` / `implicit_quantile_agent` and rlax's
`quantile_regression_loss` reduce it). The Q-value of an action is the mean of its
quantiles, by which acting and a* are greedy.

- QR-DQN: N fixed quantiles at the midpoints tau_i = (2i + 1) / 2N (i = 0..N-1, the
  paper's Lemma 2), one output per quantile and action on the network's usual head.
- IQN (Dabney et al. 2018b, "Implicit Quantile Networks for Distributional RL"): fractions
  tau ~ U(0, 1) drawn per transition; the torso's features psi(x) are multiplied by an
  embedding phi(tau) = ReLU(W cos(pi i tau) + b), i = 1..n (n = 64), then go through the
  head's hidden layer (512 on the Nature CNN) to one value per action. N fractions for the
  online estimate, N' for the target, K for acting (the policy's mean).
"""

from __future__ import annotations

import math
from typing import TypeVar

import torch
import torch.nn.functional as F
from torch import nn

from dqnlab.algorithm.heads import QHead
from dqnlab.algorithm.losses import Loss, LossOutput, Transitions
from dqnlab.config import Config
from dqnlab.errors import ConfigError
from dqnlab.parts import PartSetting, RandomPart, part_settings


def quantile_huber_losses(
    errors: torch.Tensor, fractions: torch.Tensor, kappa: float
) -> torch.Tensor:
    """Per transition, sum_i mean_j |tau_i - 1{u_ij < 0}| L_kappa(u_ij) / kappa for
    `errors` u (batch, targets j, estimates i) and `fractions` tau broadcastable to
    (batch, 1, estimates i); L_kappa is the Huber loss at threshold kappa."""
    huber = F.huber_loss(errors, torch.zeros_like(errors), delta=kappa, reduction="none")
    weights = (fractions - (errors.detach() < 0).to(errors.dtype)).abs()
    return (weights * huber / kappa).sum(dim=2).mean(dim=1)


def _gather_action(values: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """values (batch, actions, k) at each transition's action: (batch, k)."""
    index = actions.view(-1, 1, 1).expand(-1, 1, values.shape[2])
    return values.gather(1, index).squeeze(1)


# QR-DQN --------------------------------------------------------------------------------


class QuantileHead(QHead):
    """QR-DQN's head: `QHead` (plain, dueling, noisy) with N outputs per action, the
    quantiles at the fixed midpoint fractions `fractions` (N,), a non-persistent buffer.
    Its Q-values are the mean of an action's quantiles (`heads.head_q_values`)."""

    fractions: torch.Tensor

    def __init__(
        self,
        in_features: int,
        hidden_width: int | None,
        num_actions: int,
        quantiles: int,
        *,
        dueling: bool = False,
        noisy: bool = False,
        noisy_sigma0: float = 0.5,
    ) -> None:
        super().__init__(
            in_features,
            hidden_width,
            num_actions,
            quantiles,
            dueling=dueling,
            noisy=noisy,
            noisy_sigma0=noisy_sigma0,
        )
        midpoints = (2 * torch.arange(quantiles, dtype=torch.float64) + 1) / (2 * quantiles)
        self.register_buffer("fractions", midpoints.float(), persistent=False)


def quantile_head(
    in_features: int, num_actions: int, config: Config, hidden_width: int | None
) -> QuantileHead:
    """The head factory of QR-DQN (`head = "dqnlab.algorithm.quantile:quantile_head"`)."""
    quantiles = int(part_settings("head", quantile_head, config)["quantiles"])
    if quantiles < 1:
        raise ConfigError(f"parts.head.quantiles = {quantiles} must be at least 1")
    return QuantileHead(
        in_features,
        hidden_width,
        num_actions,
        quantiles,
        dueling=config.dueling,
        noisy=config.noisy,
        noisy_sigma0=config.noisy_sigma0,
    )


quantile_head.SETTINGS = {  # type: ignore[attr-defined]
    "quantiles": PartSetting(200, "Quantiles per action, N (QR-DQN: 200)"),
}
quantile_head.HEAD_OPTIONS = ("dueling", "noisy")  # type: ignore[attr-defined]


class QuantileLoss(Loss):
    """QR-DQN's loss: the quantile Huber loss between the online quantiles of the action
    taken and the target quantiles of a*, greedy in the target network's mean (`target =
    "max"`) or the online network's (`"double"`). Priorities: the loss itself."""

    SETTINGS = {"kappa": PartSetting(1.0, "Threshold kappa of the quantile Huber loss")}

    def __init__(self, config: Config) -> None:
        super().__init__(config)
        self.kappa = float(part_settings("loss", type(self), config)["kappa"])
        if self.kappa <= 0:
            raise ConfigError(f"parts.loss.kappa = {self.kappa} must be positive")

    def __call__(self, online: nn.Module, target: nn.Module, batch: Transitions) -> LossOutput:
        head = _head_of(online, QuantileHead, "quantile_head")
        estimates = _gather_action(_outputs(online, batch.observations), batch.actions)
        with torch.no_grad():
            targets = self.target_quantiles(online, target, batch)
        errors = targets.unsqueeze(2) - estimates.unsqueeze(1)  # (batch, j, i)
        losses = quantile_huber_losses(errors, head.fractions.view(1, 1, -1), self.kappa)
        return LossOutput(losses, losses.detach())

    def target_quantiles(
        self, online: nn.Module, target: nn.Module, batch: Transitions
    ) -> torch.Tensor:
        """T theta_j = r + discount (1 - terminal) theta_j(s', a*), (batch, N)."""
        next_quantiles = _outputs(target, batch.next_observations)
        actions = self.next_actions(online, next_quantiles.mean(dim=2), batch)
        bootstrap = (batch.discounts * (1.0 - batch.terminals)).unsqueeze(1)
        return batch.rewards.unsqueeze(1) + bootstrap * _gather_action(next_quantiles, actions)


# IQN -----------------------------------------------------------------------------------


class ImplicitQuantileHead(nn.Module, RandomPart):
    """IQN's head: the value of each action at fractions tau,
    f(psi(x) * phi(tau)) with phi(tau) = ReLU(Linear(cos(pi i tau), i = 1..n)), f the
    head's hidden layer (when the torso has one) and a linear output per action.

    `forward(features)` draws `acting_samples` (K) fractions per input from the part's
    generator and gives (batch, actions, K), whose mean is the Q-value acting uses;
    `quantile_values(features, fractions)` gives the values at given fractions
    (batch, samples) as (batch, actions, samples): the loss draws its own."""

    frequencies: torch.Tensor

    def __init__(
        self,
        in_features: int,
        hidden_width: int | None,
        num_actions: int,
        embedding_dim: int,
        acting_samples: int,
    ) -> None:
        super().__init__()
        self.acting_samples = acting_samples
        self.embedding = nn.Linear(embedding_dim, in_features)
        layers: list[nn.Module] = []
        width = in_features
        if hidden_width is not None:
            layers += [nn.Linear(in_features, hidden_width), nn.ReLU(inplace=True)]
            width = hidden_width
        self.outputs = nn.Sequential(*layers, nn.Linear(width, num_actions))
        # pi i for i = 1..n: dqn_zoo (networks.iqn_atari_network) and Dopamine
        # (ImplicitQuantileNetwork) both start at 1; the paper's Eq. 4 writes i = 0..n-1.
        frequencies = math.pi * torch.arange(1, embedding_dim + 1, dtype=torch.float32)
        self.register_buffer("frequencies", frequencies, persistent=False)

    def sample_fractions(self, batch: int, samples: int, device: torch.device) -> torch.Tensor:
        """tau ~ U(0, 1), (batch, samples), from the part's generator."""
        return torch.rand((batch, samples), generator=self.generator, device=device)

    def quantile_values(self, features: torch.Tensor, fractions: torch.Tensor) -> torch.Tensor:
        cosines = torch.cos(fractions.unsqueeze(2) * self.frequencies)  # (batch, samples, n)
        embedded = F.relu(self.embedding(cosines))  # (batch, samples, features)
        values = self.outputs(features.unsqueeze(1) * embedded)  # (batch, samples, actions)
        return values.transpose(1, 2)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        fractions = self.sample_fractions(features.shape[0], self.acting_samples, features.device)
        return self.quantile_values(features, fractions)


def implicit_quantile_head(
    in_features: int, num_actions: int, config: Config, hidden_width: int | None
) -> ImplicitQuantileHead:
    """The head factory of IQN (`head = "dqnlab.algorithm.quantile:implicit_quantile_head"`)."""
    settings = part_settings("head", implicit_quantile_head, config)
    embedding, acting = int(settings["embedding_dim"]), int(settings["acting_samples"])
    if embedding < 1 or acting < 1:
        raise ConfigError(
            f"parts.head: embedding_dim = {embedding} and acting_samples = {acting} must be "
            "at least 1"
        )
    return ImplicitQuantileHead(in_features, hidden_width, num_actions, embedding, acting)


implicit_quantile_head.SETTINGS = {  # type: ignore[attr-defined]
    "embedding_dim": PartSetting(64, "Cosines cos(pi i tau), i = 1..n, embedding tau (n)"),
    "acting_samples": PartSetting(32, "Fractions drawn per state to act on their mean (K)"),
}


class ImplicitQuantileLoss(Loss, RandomPart):
    """IQN's loss: the quantile Huber loss between the online values at N fractions of the
    action taken and the target values at N' other fractions of a*, each transition with
    its own fractions drawn from the part's generator; a* greedy in the target network's
    mean over K fractions (`target = "max"`; Dopamine's default) or the online network's
    (`"double"`). Priorities: the loss itself."""

    SETTINGS = {
        "kappa": PartSetting(1.0, "Threshold kappa of the quantile Huber loss"),
        "online_samples": PartSetting(64, "Fractions per transition of the online values (N)"),
        "target_samples": PartSetting(64, "Fractions per transition of the target values (N')"),
    }

    def __init__(self, config: Config) -> None:
        super().__init__(config)
        settings = part_settings("loss", type(self), config)
        self.kappa = float(settings["kappa"])
        self.online_samples = int(settings["online_samples"])
        self.target_samples = int(settings["target_samples"])
        if self.kappa <= 0 or self.online_samples < 1 or self.target_samples < 1:
            raise ConfigError(
                f"parts.loss: kappa = {self.kappa} must be positive, online_samples = "
                f"{self.online_samples} and target_samples = {self.target_samples} at least 1"
            )

    def __call__(self, online: nn.Module, target: nn.Module, batch: Transitions) -> LossOutput:
        head = _head_of(online, ImplicitQuantileHead, "implicit_quantile_head")
        features = _torso(online)(batch.observations)
        fractions = self.sample_fractions(features.shape[0], self.online_samples, features.device)
        values = head.quantile_values(features, fractions)  # (batch, actions, N)
        estimates = _gather_action(values, batch.actions)
        with torch.no_grad():
            targets = self.target_quantiles(online, target, batch)
        errors = targets.unsqueeze(2) - estimates.unsqueeze(1)  # (batch, N', N)
        losses = quantile_huber_losses(errors, fractions.unsqueeze(1), self.kappa)
        return LossOutput(losses, losses.detach())

    def target_quantiles(
        self, online: nn.Module, target: nn.Module, batch: Transitions
    ) -> torch.Tensor:
        """r + discount (1 - terminal) Z_tau'(s', a*) at N' fractions tau', (batch, N')."""
        head = _head_of(target, ImplicitQuantileHead, "implicit_quantile_head")
        features = _torso(target)(batch.next_observations)  # once, for a* and the values
        next_q = head(features).mean(dim=2)  # K fractions from the target head's generator
        actions = self.next_actions(online, next_q, batch)
        fractions = self.sample_fractions(features.shape[0], self.target_samples, features.device)
        chosen = _gather_action(head.quantile_values(features, fractions), actions)
        bootstrap = (batch.discounts * (1.0 - batch.terminals)).unsqueeze(1)
        return batch.rewards.unsqueeze(1) + bootstrap * chosen

    def sample_fractions(self, batch: int, samples: int, device: torch.device) -> torch.Tensor:
        """Fractions uniform in [0, 1), (batch, samples), from the part's generator."""
        return torch.rand((batch, samples), generator=self.generator, device=device)


HeadType = TypeVar("HeadType", bound=nn.Module)


def _head_of(network: nn.Module, kind: type[HeadType], factory: str) -> HeadType:
    """The network's head, which must be `kind`: the one `factory` builds."""
    head = getattr(network, "head", None)
    if not isinstance(head, kind):
        raise ConfigError(
            f"this loss needs the head of head = 'dqnlab.algorithm.quantile:{factory}', and "
            f"{type(network).__name__} has {type(head).__name__}"
        )
    return head


def _torso(network: nn.Module) -> nn.Module:
    torso = network.torso
    assert isinstance(torso, nn.Module)
    return torso


def _outputs(network: nn.Module, observations: torch.Tensor) -> torch.Tensor:
    """The head's outputs per action, (batch, actions, k) (`networks.QNetwork.outputs`)."""
    outputs: torch.Tensor = network.outputs(observations)  # type: ignore[operator]
    return outputs
