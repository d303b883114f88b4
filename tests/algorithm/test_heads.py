"""Heads: noisy linear layers (factorised noise, initialisation, modes, the generator), the
dueling aggregation and its torso gradient scale, against values worked out by hand or by a
plain loop."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from dqnlab.algorithm.heads import (
    DUELING_TORSO_GRADIENT_SCALE,
    FACTORISED_MAX_ROWS,
    NoisyLinear,
    QHead,
    has_noise,
    noisy_weight,
    sample_noise,
    scale_gradient,
)


def f(x: float) -> float:
    """Fortunato et al.'s f(x) = sign(x) sqrt(|x|), one number at a time."""
    return math.copysign(math.sqrt(abs(x)), x)


def test_noisy_initialisation_mu_uniform_and_sigma_constant_over_sqrt_fan_in() -> None:
    torch.manual_seed(0)
    layer = NoisyLinear(200, 30, sigma0=0.5)
    bound = 1 / math.sqrt(200)
    for mu in (layer.weight_mu, layer.bias_mu):
        assert mu.abs().max() <= bound
        assert mu.abs().max() > 0.9 * bound  # spread over the whole interval
    assert torch.equal(layer.weight_sigma, torch.full((30, 200), 0.5 * bound))
    assert torch.equal(layer.bias_sigma, torch.full((30,), 0.5 * bound))
    assert NoisyLinear(16, 2, sigma0=0.1).bias_sigma[0].item() == pytest.approx(0.1 / 4)


def test_factorised_noise_is_the_outer_product_of_f_of_two_normal_vectors() -> None:
    layer = NoisyLinear(5, 3, sigma0=0.5)
    layer.resample_noise(torch.Generator().manual_seed(11))
    replay = torch.Generator().manual_seed(11)  # eps_in is drawn first, then eps_out
    eps_in = torch.empty(5).normal_(generator=replay).tolist()
    eps_out = torch.empty(3).normal_(generator=replay).tolist()
    assert layer.weight_epsilon.shape == (3, 5) and layer.bias_epsilon.shape == (3,)
    for j in range(3):
        assert layer.bias_epsilon[j].item() == pytest.approx(f(eps_out[j]), rel=1e-6)
        for i in range(5):
            expected = f(eps_out[j]) * f(eps_in[i])
            assert layer.weight_epsilon[j, i].item() == pytest.approx(expected, rel=1e-6)


def test_train_mode_adds_sigma_times_noise_and_eval_mode_uses_the_means() -> None:
    torch.manual_seed(1)
    layer = NoisyLinear(4, 2, sigma0=0.5)
    inputs = torch.randn(3, 4)
    with torch.no_grad():
        eval_expected = inputs @ layer.weight_mu.T + layer.bias_mu
        assert torch.equal(layer(inputs), layer.eval()(inputs))  # no noise before drawn
        layer.resample_noise(torch.Generator().manual_seed(2))
        weight = layer.weight_mu + layer.weight_sigma * layer.weight_epsilon
        bias = layer.bias_mu + layer.bias_sigma * layer.bias_epsilon
        torch.testing.assert_close(layer.train()(inputs), inputs @ weight.T + bias)
        torch.testing.assert_close(layer.eval()(inputs), eval_expected)
        assert not torch.allclose(layer.train()(inputs), eval_expected)


def test_acting_applies_the_noise_as_two_products_of_the_same_function() -> None:
    """A few rows without a gradient (acting) take x mu^T + ((x f(eps_in)) sigma^T)
    f(eps_out): the composed weights' function, to float rounding; a pass with a gradient,
    or a minibatch, composes the weights, writing their noise first if the draw left it out."""
    torch.manual_seed(3)
    layer = NoisyLinear(300, 40, sigma0=0.5)
    inputs = torch.randn(5, 300)
    layer.resample_noise(torch.Generator().manual_seed(4), weights=False)
    eps_in, eps_out = layer.input_epsilon.clone(), layer.bias_epsilon.clone()
    weight = layer.weight_mu + layer.weight_sigma * torch.outer(eps_out, eps_in)
    expected = inputs @ weight.T + layer.bias_mu + layer.bias_sigma * eps_out
    with torch.no_grad():
        without = layer(inputs)
    with torch.inference_mode():
        assert torch.equal(layer(inputs), without)
    torch.testing.assert_close(without, expected.detach(), rtol=1e-5, atol=1e-5)
    assert not torch.equal(layer.weight_epsilon, torch.outer(eps_out, eps_in))  # not written
    with_gradient = layer(inputs)  # composes: writes the outer product first
    assert torch.equal(layer.weight_epsilon, torch.outer(eps_out, eps_in))
    torch.testing.assert_close(with_gradient, expected, rtol=1e-5, atol=1e-5)
    with_gradient.sum().backward()
    assert layer.weight_sigma.grad is not None and layer.weight_sigma.grad.abs().sum() > 0
    minibatch = torch.randn(FACTORISED_MAX_ROWS + 1, 300)
    with torch.no_grad():  # composed: the bits of the pass with a gradient
        assert torch.equal(layer(minibatch), layer(minibatch.requires_grad_()).detach())
    # Drawn with the weights, the same generator state gives the same noise.
    again = NoisyLinear(300, 40, sigma0=0.5)
    again.resample_noise(torch.Generator().manual_seed(4))
    assert torch.equal(again.weight_epsilon, layer.weight_epsilon)


def test_the_noisy_weight_has_addcmuls_values_and_gradients_bit_for_bit() -> None:
    generator = torch.Generator().manual_seed(6)
    mu, sigma, epsilon = (torch.randn(64, 300, generator=generator) for _ in range(3))
    upstream = torch.randn(64, 300, generator=generator)
    results = []
    for compose in (noisy_weight, torch.addcmul):
        leaves = [mu.clone().requires_grad_(), sigma.clone().requires_grad_()]
        weight = compose(*leaves, epsilon)
        weight.backward(upstream)
        results.append([weight.detach(), *(leaf.grad for leaf in leaves)])
    for ours, autograds in zip(*results, strict=True):
        assert torch.equal(ours, autograds)


def test_a_pass_without_gradient_reuses_the_composed_weights_until_they_change() -> None:
    """Double DQN's next-action pass after Q(s, a) reuses the matrix the first composed;
    an optimizer step, fresh noise or new weights compose it again."""
    torch.manual_seed(7)
    layer = NoisyLinear(300, 40, sigma0=0.5)
    minibatch = torch.randn(FACTORISED_MAX_ROWS + 1, 300)
    layer.resample_noise(torch.Generator().manual_seed(8))

    def composed() -> torch.Tensor:  # what the layer computes, from scratch
        weight = torch.addcmul(layer.weight_mu, layer.weight_sigma, layer.weight_epsilon)
        bias = torch.addcmul(layer.bias_mu, layer.bias_sigma, layer.bias_epsilon)
        return F.linear(minibatch, weight, bias).detach()

    layer(minibatch).sum().backward()
    kept = layer._last_composed
    assert kept is not None
    with torch.no_grad():
        assert torch.equal(layer(minibatch), composed())
        assert layer._composed_weight() is kept[1]  # reused, not composed again
    torch.optim.SGD(layer.parameters(), lr=0.1).step()  # in place: a new version
    with torch.no_grad():
        assert layer._composed_weight() is not kept[1]
        assert torch.equal(layer(minibatch), composed())
    layer.resample_noise(torch.Generator().manual_seed(9))
    with torch.no_grad():
        assert torch.equal(layer(minibatch), composed())
    with torch.no_grad():
        layer.weight_mu.copy_(torch.randn(40, 300))  # as load_state_dict writes it
        assert torch.equal(layer(minibatch), composed())


def test_the_same_generator_state_draws_the_same_noise_in_place() -> None:
    network = nn.Sequential(NoisyLinear(4, 3, 0.5), nn.ReLU(), NoisyLinear(3, 2, 0.5))
    first, second = network[0], network[2]
    storage = [first.weight_epsilon.data_ptr(), second.weight_epsilon.data_ptr()]
    generator = torch.Generator().manual_seed(5)
    state = generator.get_state()
    sample_noise(network, generator)
    drawn = [first.weight_epsilon.clone(), second.weight_epsilon.clone()]
    sample_noise(network, generator)
    assert not torch.equal(first.weight_epsilon, drawn[0])  # fresh noise each call
    generator.set_state(state)
    sample_noise(network, generator)
    assert torch.equal(first.weight_epsilon, drawn[0])
    assert torch.equal(second.weight_epsilon, drawn[1])
    assert [first.weight_epsilon.data_ptr(), second.weight_epsilon.data_ptr()] == storage
    assert has_noise(network) and not has_noise(nn.Sequential(nn.Linear(2, 2)))


def test_noise_is_not_in_the_state_dict_and_a_copy_keeps_its_own_noise() -> None:
    online, target = NoisyLinear(4, 2, 0.5), NoisyLinear(4, 2, 0.5)
    assert sorted(online.state_dict()) == ["bias_mu", "bias_sigma", "weight_mu", "weight_sigma"]
    sample_noise(online, torch.Generator().manual_seed(0))
    sample_noise(target, torch.Generator().manual_seed(1))
    target_noise = target.weight_epsilon.clone()
    target.load_state_dict(online.state_dict())  # strict: the keys match
    assert torch.equal(target.weight_mu, online.weight_mu)
    assert torch.equal(target.weight_epsilon, target_noise)


def test_dueling_q_is_value_plus_advantage_minus_its_mean_by_hand() -> None:
    head = QHead(3, None, 3, dueling=True)
    with torch.no_grad():
        head.value[0].weight.copy_(torch.tensor([[1.0, 0.0, 0.0]]))
        head.value[0].bias.fill_(0.5)
        head.advantage[0].weight.copy_(torch.eye(3) * 2)
        head.advantage[0].bias.zero_()
        q_values = head(torch.tensor([[1.0, 2.0, 3.0]]))
    # V = 1.5, A = (2, 4, 6), mean A = 4: Q = 1.5 + (-2, 0, 2).
    assert torch.equal(q_values, torch.tensor([[[-0.5], [1.5], [3.5]]]))


def test_dueling_aggregation_is_per_atom_and_advantages_average_to_zero() -> None:
    torch.manual_seed(3)
    head = QHead(6, 8, 3, outputs_per_action=4, dueling=True)
    features = torch.randn(2, 6)
    with torch.no_grad():
        outputs = head(features)
        value = head.value(features)  # (2, 4)
        advantage = head.advantage(features).view(2, 3, 4)
    assert outputs.shape == (2, 3, 4)
    for b in range(2):
        for i in range(4):
            mean = sum(advantage[b, a, i].item() for a in range(3)) / 3
            for a in range(3):
                expected = value[b, i].item() + advantage[b, a, i].item() - mean
                assert outputs[b, a, i].item() == pytest.approx(expected, abs=1e-6)
    centred = outputs - value.unsqueeze(1)  # the aggregated advantages
    torch.testing.assert_close(centred.mean(dim=1), torch.zeros(2, 4), atol=1e-6, rtol=0)


def test_dueling_scales_the_torso_gradient_by_one_over_sqrt_two() -> None:
    torch.manual_seed(4)
    torso, head = nn.Linear(5, 6), QHead(6, 8, 3, dueling=True)
    inputs, weights = torch.randn(4, 5), torch.randn(4, 3)
    (head(torso(inputs)).flatten(1) * weights).sum().backward()
    scaled = [p.grad.clone() for p in torso.parameters()]
    head_gradients = [p.grad.clone() for p in head.parameters()]
    torso.zero_grad()
    head.zero_grad()
    features = torso(inputs)  # by hand, without the rescale
    value, advantage = head.value(features), head.advantage(features)
    ((value + advantage - advantage.mean(dim=1, keepdim=True)) * weights).sum().backward()
    for got, plain in zip(scaled, (p.grad for p in torso.parameters()), strict=True):
        torch.testing.assert_close(got, plain / math.sqrt(2), rtol=1e-6, atol=1e-7)
    for got, plain in zip(head_gradients, (p.grad for p in head.parameters()), strict=True):
        torch.testing.assert_close(got, plain)  # the streams' own gradients are unscaled
    assert math.sqrt(2) * DUELING_TORSO_GRADIENT_SCALE == pytest.approx(1.0)


def test_scale_gradient_leaves_the_values_unchanged() -> None:
    tensor = torch.randn(3, 2, requires_grad=True)
    scaled = scale_gradient(tensor, 0.25)
    assert torch.equal(scaled, tensor)
    scaled.sum().backward()
    assert torch.equal(tensor.grad, torch.full((3, 2), 0.25))


def test_every_layer_of_a_noisy_head_is_noisy() -> None:
    head = QHead(6, 8, 3, outputs_per_action=2, dueling=True, noisy=True, noisy_sigma0=0.1)
    linears = [m for m in head.modules() if isinstance(m, (nn.Linear, NoisyLinear))]
    assert len(linears) == 4 and all(isinstance(m, NoisyLinear) for m in linears)
    assert [(m.in_features, m.out_features) for m in linears] == [(6, 8), (8, 2), (6, 8), (8, 6)]
    assert all(m.sigma0 == 0.1 for m in linears)
