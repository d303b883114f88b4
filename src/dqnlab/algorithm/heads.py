"""Heads of the DQN family's Q-networks: dueling streams, noisy linear layers, C51 logits,
and a user's own head (`head = module:factory`).

A head is a part: a module that maps a torso's features (batch, features) to outputs per
action, (batch, actions, outputs_per_action): one Q-value per action, the logits of each
action's return distribution with C51, quantiles for QR-DQN... Its optional method
`q_values(outputs)` gives the Q-values (batch, actions) that acting, evaluation and the
TD loss use; without it they are the mean over the outputs (the Q-value itself for one
output, the expectation of equally weighted quantiles). The loss part reads the outputs
themselves through the network's `outputs(observations)`.

A head factory is called as `factory(in_features, num_actions, config, hidden_width)`:
the torso's feature count, the action count, the run's settings and the width of the
hidden layer the network setting puts before its outputs (the Nature CNN's 512; None for a
user's torso), which a head may use or ignore. `standard_head` is the factory of
`head = "auto"`: `QHead`, or `CategoricalHead` with C51, whose parts compose (any head may
be dueling, noisy and distributional at once, which is Rainbow's head; Hessel et al. 2018,
dqn-family.md 6.1). `networks.py` puts a head on a torso.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from dqnlab.config import Config
from dqnlab.errors import ConfigError
from dqnlab.parts import check_head_options, load_object, load_part

# Wang et al. 2016 rescale the combined gradient entering the last convolutional layer by
# 1/sqrt(2), as both streams send one into the torso (dqn-family.md 2.1, secondary copies).
DUELING_TORSO_GRADIENT_SCALE = 1.0 / math.sqrt(2.0)


# Up to this many rows without a gradient, a noisy layer applies its noise as two products
# rather than composing its weights. Break-even estimate for a 3136 x 512 layer: the second
# product costs 2 x rows FLOPs per weight, the composition about 12 bytes of memory traffic
# per weight more; at about 100 GFLOP/s and 15 GB/s they cross near 40 rows (measured on the
# AMD EPYC, 2026-12-05: a batch of 32 gained nothing, one row gained; docs/benchmark.md).
FACTORISED_MAX_ROWS = 8


class NoisyLinear(nn.Module):
    """A linear layer with factorised Gaussian noise (Fortunato et al. 2018, NoisyNets).

    In train mode the layer uses w = mu_w + sigma_w * eps_w and b = mu_b + sigma_b * eps_b,
    with the factorised noise eps_w = f(eps_out) f(eps_in)^T, eps_b = f(eps_out),
    f(x) = sign(x) sqrt(|x|) and eps_in (in_features,), eps_out (out_features,) drawn from
    N(0, 1). In eval mode (`module.eval()`) it uses the mean weights mu: evaluation, the
    held-out statistics and `dqnlab inspect` see no noise (Dopamine's `NoisyNetwork` turns
    the noise off when evaluating too; dqn-family.md 6.3).

    Initialisation as in the paper's factorised case: mu ~ U(+-1/sqrt(in_features)) and
    sigma = sigma0 / sqrt(in_features), for weights and biases alike. The paper and
    Rainbow use sigma0 = 0.5 (Rainbow's footnote: 0.1 "may be helpful" when the noise is
    drawn on the CPU); dqn_zoo (`networks.noisy_linear`, noisy_weight_init) and Dopamine
    (`dopamine/jax/networks.py::NoisyNetwork`) use 0.1, and dqn_zoo draws eps from a normal
    truncated at +-2; CleanRL's `rainbow_atari.py::NoisyLinear` uses 0.5 with independent,
    not factorised, noise and a bias sigma of 0.5/sqrt(out_features) (dqn-family.md 6.3,
    8.6).

    The noise changes only when `resample_noise` is called (`sample_noise` calls it on every
    noisy layer of a network), with a generator the caller owns and checkpoints: drawing it
    inside `forward` would take it from torch's global stream and tie it to how often the
    network is called. Until first drawn the noise is zero. The noise buffers are not
    persistent (not in the state dict): they are not learned, a target-network copy through
    `load_state_dict` leaves the target's own noise in place, and network files stay the
    size of mu and sigma. A caller that must resume exactly draws fresh noise right before
    each use from its restored generator (noise drawn before a checkpoint is not saved).

    Acting (no gradient, a few rows: `FACTORISED_MAX_ROWS`) applies the noise as two
    products, x mu_w^T + ((x * f(eps_in)) sigma_w^T) * f(eps_out), instead of composing the
    weights: for a few rows each product reads its matrix once and nothing of the weights'
    size is written, where composing reads three such matrices and writes a fourth. The
    same function of the same noise, rounded otherwise than the composed weights (no preset
    with noisy layers is pinned). For a minibatch the second product's FLOPs cost what the
    composition saves, so the update composes, as before, bit for bit. Noise drawn for
    acting leaves the outer product f(eps_out) f(eps_in)^T unwritten until a composing
    pass needs it (`resample_noise(weights=False)`).
    """

    weight_epsilon: torch.Tensor
    bias_epsilon: torch.Tensor
    input_epsilon: torch.Tensor

    def __init__(self, in_features: int, out_features: int, sigma0: float) -> None:
        super().__init__()
        self.in_features = in_features
        self.out_features = out_features
        self.sigma0 = sigma0
        self.weight_mu = nn.Parameter(torch.empty(out_features, in_features))
        self.weight_sigma = nn.Parameter(torch.empty(out_features, in_features))
        self.bias_mu = nn.Parameter(torch.empty(out_features))
        self.bias_sigma = nn.Parameter(torch.empty(out_features))
        # f(eps_in), f(eps_out) (the bias noise) and their outer product, drawn in place.
        self.register_buffer("input_epsilon", torch.zeros(in_features), persistent=False)
        self.register_buffer("bias_epsilon", torch.zeros(out_features), persistent=False)
        self.register_buffer(
            "weight_epsilon", torch.zeros(out_features, in_features), persistent=False
        )
        bound = 1.0 / math.sqrt(in_features)
        nn.init.uniform_(self.weight_mu, -bound, bound)
        nn.init.uniform_(self.bias_mu, -bound, bound)
        nn.init.constant_(self.weight_sigma, sigma0 * bound)
        nn.init.constant_(self.bias_sigma, sigma0 * bound)
        self._weight_noise_drawn = True  # weight_epsilon is the outer product of the vectors
        # The matrix a pass with a gradient composed, and what it was composed from: each
        # part's storage and version (any change in place, the optimizer's too, bumps it).
        self._last_composed: tuple[tuple[tuple[int, int], ...], torch.Tensor] | None = None

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        if not self.training:
            return F.linear(inputs, self.weight_mu, self.bias_mu)
        bias = torch.addcmul(self.bias_mu, self.bias_sigma, self.bias_epsilon)
        rows = inputs.numel() // self.in_features
        if rows <= FACTORISED_MAX_ROWS and not torch.is_grad_enabled():  # see the class
            noise = F.linear(inputs * self.input_epsilon, self.weight_sigma)
            return torch.addcmul(F.linear(inputs, self.weight_mu, bias), noise, self.bias_epsilon)
        return F.linear(inputs, self._composed_weight(), bias)

    def _composed_weight(self) -> torch.Tensor:
        """mu_w + sigma_w * eps_w. A pass without a gradient after one with it, on the same
        weights and noise, reuses that pass's matrix (Double DQN's choice of the next action
        after Q(s, a), in each update): the same values, one composition fewer."""
        if not self._weight_noise_drawn:
            self._draw_weight_noise()
        parts = (self.weight_mu, self.weight_sigma, self.weight_epsilon)
        if torch.compiler.is_compiling():  # no Python-side state in a compiled graph
            return noisy_weight(*parts)
        key = tuple((part.data_ptr(), part._version) for part in parts)
        if torch.is_grad_enabled():
            weight = noisy_weight(*parts)
            self._last_composed = (key, weight.detach())
            return weight
        if self._last_composed is not None and self._last_composed[0] == key:
            return self._last_composed[1]
        return torch.addcmul(*parts)

    @torch.no_grad()
    def resample_noise(self, generator: torch.Generator, *, weights: bool = True) -> None:
        """Draw new noise from `generator` (eps_in first, then eps_out), into the buffers;
        with `weights` False the weight noise (their outer product) is left for the first
        pass that composes the weights to write (acting's passes never read it)."""
        if generator.device.type != self.weight_epsilon.device.type:
            raise ValueError(
                f"the noise generator is on {generator.device}, the noisy layer on "
                f"{self.weight_epsilon.device}: make the generator on the network's device"
            )
        for epsilon in (self.input_epsilon, self.bias_epsilon):
            epsilon.normal_(generator=generator)
            sign = epsilon.sign()
            epsilon.abs_().sqrt_().mul_(sign)  # f(x) = sign(x) sqrt(|x|)
        self._weight_noise_drawn = False
        if weights:
            self._draw_weight_noise()

    @torch.no_grad()
    def _draw_weight_noise(self) -> None:
        torch.outer(self.bias_epsilon, self.input_epsilon, out=self.weight_epsilon)
        self._weight_noise_drawn = True

    def extra_repr(self) -> str:
        sizes = f"in_features={self.in_features}, out_features={self.out_features}"
        return f"{sizes}, sigma0={self.sigma0}"


class _NoisyWeight(torch.autograd.Function):
    """mu + sigma * epsilon, whose backward gives sigma the gradient times epsilon in one
    product: autograd's `addcmul` computes epsilon * 1 first, a pass over the whole matrix
    and an allocation of its size (7% of Rainbow's update on the CPU). The same bits:
    multiplying by one is exact."""

    @staticmethod
    def forward(
        ctx: Any, mu: torch.Tensor, sigma: torch.Tensor, epsilon: torch.Tensor
    ) -> torch.Tensor:
        ctx.save_for_backward(epsilon)
        return torch.addcmul(mu, sigma, epsilon)

    @staticmethod
    def backward(ctx: Any, gradient: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, None]:
        (epsilon,) = ctx.saved_tensors
        return gradient, gradient * epsilon, None


def noisy_weight(mu: torch.Tensor, sigma: torch.Tensor, epsilon: torch.Tensor) -> torch.Tensor:
    """The noisy weight mu + sigma * epsilon, differentiable in mu and sigma."""
    weight: torch.Tensor = _NoisyWeight.apply(mu, sigma, epsilon)
    return weight


def evaluates_with_noise(config: Config, network: nn.Module) -> bool:
    """Whether `network` plays its evaluations with fresh noise (eval_noise = "sampled", as
    dqn_zoo's Rainbow evaluates) rather than on its mean weights; "sampled" needs noisy
    layers in it."""
    if config.eval_noise == "sampled" and not has_noise(network):
        raise ConfigError(
            "eval_noise = 'sampled' draws noise for noisy layers, and this network has "
            "none (noisy = true gives the head some)"
        )
    return config.eval_noise == "sampled"


def sample_noise(network: nn.Module, generator: torch.Generator, *, weights: bool = True) -> None:
    """Resample the noise of every `NoisyLinear` in `network`, in module order, from
    `generator` (on the network's device). Allocates nothing larger than the noise vectors:
    the weight noise is written in place into preallocated buffers (with `weights` False,
    only when a pass that composes the weights needs it: `NoisyLinear.resample_noise`)."""
    for module in network.modules():
        if isinstance(module, NoisyLinear):
            module.resample_noise(generator, weights=weights)


def has_noise(network: nn.Module) -> bool:
    """Whether `network` has noisy layers, whose noise its user must draw (`sample_noise`)."""
    return any(isinstance(module, NoisyLinear) for module in network.modules())


class _ScaleGradient(torch.autograd.Function):
    """The identity forward; the gradient multiplied by `scale` backward."""

    @staticmethod
    def forward(ctx: Any, tensor: torch.Tensor, scale: float) -> torch.Tensor:
        ctx.scale = scale
        return tensor.view_as(tensor)

    @staticmethod
    def backward(ctx: Any, gradient: torch.Tensor) -> tuple[torch.Tensor, None]:
        return gradient * ctx.scale, None


def scale_gradient(tensor: torch.Tensor, scale: float) -> torch.Tensor:
    """`tensor` unchanged, with the gradient flowing back through it multiplied by `scale`."""
    output: torch.Tensor = _ScaleGradient.apply(tensor, scale)
    return output


class QHead(nn.Module):
    """Outputs per action from a torso's features: (batch, actions, outputs_per_action).

    Each stream is a hidden layer of `hidden_width` units and ReLU (none when `hidden_width`
    is None), then a linear output layer; with `noisy` every one of these layers is a
    `NoisyLinear`. On the Atari networks these are all the linear layers, as Rainbow has
    it (Hessel et al. 2018, section 2: noisy layers replace the fully connected ones); an
    MLP's or an encoder's hidden layers belong to the torso and stay plain.

    `dueling` (Wang et al. 2016; dqn-family.md 2.1): a value stream with
    `outputs_per_action` outputs and an advantage stream with actions x outputs_per_action,
    each with its own hidden layer (the paper's Atari network: FC-512 -> 1 and FC-512 ->
    |A|), combined as value + advantage - mean over actions of advantage. With C51 the
    combination is per atom, on the logits, before the softmax over atoms (Rainbow,
    dqn-family.md 6.1; dqn_zoo `networks.rainbow_atari_network` and CleanRL
    `rainbow_atari.py` likewise; Dopamine's `FullRainbowNetwork` shares one hidden layer
    between the streams). The gradient entering the torso is scaled by 1/sqrt(2), as the
    paper does; dqn_zoo, Dopamine and CleanRL do not (dqn-family.md 2.2).
    """

    def __init__(
        self,
        in_features: int,
        hidden_width: int | None,
        num_actions: int,
        outputs_per_action: int = 1,
        *,
        dueling: bool = False,
        noisy: bool = False,
        noisy_sigma0: float = 0.5,
    ) -> None:
        super().__init__()
        self.num_actions = num_actions
        self.outputs_per_action = outputs_per_action
        self.dueling = dueling
        self.noisy = noisy
        self.noisy_sigma0 = noisy_sigma0
        if dueling:
            self.value = self._stream(in_features, hidden_width, outputs_per_action)
            self.advantage = self._stream(
                in_features, hidden_width, num_actions * outputs_per_action
            )
        else:
            self.outputs = self._stream(in_features, hidden_width, num_actions * outputs_per_action)

    def _stream(self, in_features: int, hidden_width: int | None, outputs: int) -> nn.Sequential:
        layers: list[nn.Module] = []
        if hidden_width is not None:
            layers += [self._linear(in_features, hidden_width), nn.ReLU(inplace=True)]
            in_features = hidden_width
        layers.append(self._linear(in_features, outputs))
        return nn.Sequential(*layers)

    def _linear(self, in_features: int, out_features: int) -> nn.Module:
        if self.noisy:
            return NoisyLinear(in_features, out_features, self.noisy_sigma0)
        return nn.Linear(in_features, out_features)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        shape = (self.num_actions, self.outputs_per_action)
        if not self.dueling:
            return self.outputs(features).unflatten(1, shape)
        features = scale_gradient(features, DUELING_TORSO_GRADIENT_SCALE)
        value = self.value(features).unsqueeze(1)  # (batch, 1, outputs_per_action)
        advantage = self.advantage(features).unflatten(1, shape)
        return value + advantage - advantage.mean(dim=1, keepdim=True)


class CategoricalHead(QHead):
    """C51 (Bellemare et al. 2017; dqn-family.md 5.1): per action, the logits of a
    categorical distribution of the return on the atoms `support` (atoms,),
    z_i = v_min + i dz; its Q-values are the expected returns sum_i z_i p_i. The support is
    a non-persistent buffer: it follows from the configuration, which every network file
    stores, and the state dict stays that of `QHead`."""

    support: torch.Tensor

    def __init__(
        self,
        in_features: int,
        hidden_width: int | None,
        num_actions: int,
        atoms: int,
        v_min: float,
        v_max: float,
        *,
        dueling: bool = False,
        noisy: bool = False,
        noisy_sigma0: float = 0.5,
    ) -> None:
        super().__init__(
            in_features,
            hidden_width,
            num_actions,
            atoms,
            dueling=dueling,
            noisy=noisy,
            noisy_sigma0=noisy_sigma0,
        )
        self.atom_spacing = (v_max - v_min) / (atoms - 1)
        # z_i = v_min + i dz as defined, in float64 so that the last atom is v_max to float32.
        support = v_min + torch.arange(atoms, dtype=torch.float64) * self.atom_spacing
        self.register_buffer("support", support.float(), persistent=False)

    def q_values(self, logits: torch.Tensor) -> torch.Tensor:
        return (F.softmax(logits, dim=2) * self.support).sum(dim=2)

    def log_probabilities(self, logits: torch.Tensor) -> torch.Tensor:
        """log p_i per action, (batch, actions, atoms): `log_softmax` over the atoms, finite
        where log(softmax) would give -inf for a vanishing probability."""
        return F.log_softmax(logits, dim=2)


def head_q_values(head: nn.Module, outputs: torch.Tensor) -> torch.Tensor:
    """The Q-values (batch, actions) of a head's `outputs` (batch, actions, k): its own
    `q_values`, else the outputs themselves for k = 1 and their mean otherwise."""
    method = getattr(head, "q_values", None)
    if method is not None:
        q_values: torch.Tensor = method(outputs)
        return q_values
    return outputs.flatten(1) if outputs.shape[2] == 1 else outputs.mean(dim=2)


def standard_head(
    in_features: int, num_actions: int, config: Config, hidden_width: int | None
) -> QHead:
    """The head of `head = "auto"`: dueling, noisy and C51 as the settings say."""
    if config.distributional == "c51":
        return CategoricalHead(
            in_features,
            hidden_width,
            num_actions,
            config.distributional_atoms,
            config.distributional_v_min,
            config.distributional_v_max,
            dueling=config.dueling,
            noisy=config.noisy,
            noisy_sigma0=config.noisy_sigma0,
        )
    return QHead(
        in_features,
        hidden_width,
        num_actions,
        dueling=config.dueling,
        noisy=config.noisy,
        noisy_sigma0=config.noisy_sigma0,
    )


def build_head(
    config: Config, in_features: int, num_actions: int, hidden_width: int | None
) -> nn.Module:
    """The head `config.head` names, checked on a probe batch of two zero feature vectors:
    outputs (2, num_actions, k) and Q-values (2, num_actions); a user's head that fails is
    a one-line ConfigError naming the setting."""
    if config.head == "auto":
        return standard_head(in_features, num_actions, config, hidden_width)
    check_head_options(config, load_object("head", config.head))
    head = load_part("head", config.head, in_features, num_actions, config, hidden_width)
    if not isinstance(head, nn.Module):
        raise ConfigError(f"head = {config.head!r} built {type(head).__name__}, not nn.Module")
    features = torch.zeros(2, in_features)
    outputs = _probe(config.head, "", lambda: head(features), in_features)
    expected = (2, num_actions)
    if not isinstance(outputs, torch.Tensor) or outputs.ndim != 3 or outputs.shape[:2] != expected:
        got = tuple(outputs.shape) if isinstance(outputs, torch.Tensor) else type(outputs)
        raise ConfigError(
            f"head {config.head!r} gives {got} for features of shape (2, {in_features}); "
            f"expected (2, {num_actions}, outputs per action)"
        )
    q_values = _probe(config.head, "'s q_values", lambda: head_q_values(head, outputs), in_features)
    if not isinstance(q_values, torch.Tensor) or tuple(q_values.shape) != expected:
        got = tuple(q_values.shape) if isinstance(q_values, torch.Tensor) else type(q_values)
        raise ConfigError(f"head {config.head!r}'s q_values gives {got}; expected {expected}")
    return head


def _probe(name: str, what: str, call: Callable[[], Any], in_features: int) -> Any:
    """`call()` without gradients; the user's code failing is a one-line ConfigError."""
    try:
        with torch.no_grad():
            return call()
    except Exception as error:  # noqa: BLE001 - the user's code: report, don't crash
        raise ConfigError(
            f"head {name!r}{what} fails on features of shape (2, {in_features}): {error!r}"
        ) from None
