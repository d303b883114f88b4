"""Tests for dqnlab.algorithm.optim against values worked out by hand."""

from __future__ import annotations

import copy
import io
import math

import pytest
import torch

from dqnlab.algorithm import optim
from dqnlab.algorithm.optim import (
    OPTIMIZER_NAMES,
    AdamKernelStep,
    DeepMindRMSprop,
    build_optimizer,
    clip_gradient_norm_,
    step_function,
)

LR = 0.00025
DECAY = 0.95
EPS = 0.01


def _scalar_parameter(value: float) -> torch.nn.Parameter:
    # float64 so that comparisons with the hand arithmetic can be tight.
    return torch.nn.Parameter(torch.tensor(value, dtype=torch.float64))


def _step_with_gradient(
    optimizer: torch.optim.Optimizer, param: torch.Tensor, gradient: float
) -> None:
    param.grad = torch.full_like(param, gradient)
    optimizer.step()


def test_three_steps_match_hand_arithmetic() -> None:
    param = _scalar_parameter(1.0)
    optimizer = DeepMindRMSprop([param], lr=LR, decay=DECAY, eps=EPS)

    # Step 1, gradient 2: g = 0.05 * 2, g2 = 0.05 * 4, g² = 0.01.
    _step_with_gradient(optimizer, param, 2.0)
    state = optimizer.state[param]
    p1 = 1.0 - 0.00025 * 2.0 / math.sqrt(0.2 - 0.01 + 0.01)
    assert state["grad_avg"].item() == pytest.approx(0.1, rel=1e-12)
    assert state["square_avg"].item() == pytest.approx(0.2, rel=1e-12)
    assert param.item() == pytest.approx(p1, rel=1e-12)

    # Step 2, gradient -1: g = 0.095 - 0.05, g2 = 0.19 + 0.05, g² = 0.045² = 0.002025.
    _step_with_gradient(optimizer, param, -1.0)
    p2 = p1 + 0.00025 * 1.0 / math.sqrt(0.24 - 0.002025 + 0.01)
    assert state["grad_avg"].item() == pytest.approx(0.045, rel=1e-12)
    assert state["square_avg"].item() == pytest.approx(0.24, rel=1e-12)
    assert param.item() == pytest.approx(p2, rel=1e-12)

    # Step 3, gradient 0.5: g = 0.04275 + 0.025, g2 = 0.228 + 0.0125, g² = 0.0045900625.
    _step_with_gradient(optimizer, param, 0.5)
    p3 = p2 - 0.00025 * 0.5 / math.sqrt(0.2405 - 0.0045900625 + 0.01)
    assert state["grad_avg"].item() == pytest.approx(0.06775, rel=1e-12)
    assert state["square_avg"].item() == pytest.approx(0.2405, rel=1e-12)
    assert param.item() == pytest.approx(p3, rel=1e-12)


def test_float32_parameter_follows_the_same_arithmetic() -> None:
    param = torch.nn.Parameter(torch.tensor([1.0, -3.0]))
    optimizer = DeepMindRMSprop([param])
    param.grad = torch.tensor([2.0, 2.0])
    optimizer.step()
    moved = 0.00025 * 2.0 / math.sqrt(0.2)
    assert param.dtype == torch.float32
    assert param.tolist() == pytest.approx([1.0 - moved, -3.0 - moved], rel=1e-6)


def test_differs_from_torch_centered_rmsprop_by_eps_placement() -> None:
    ours = _scalar_parameter(1.0)
    theirs = _scalar_parameter(1.0)
    ours_optimizer = DeepMindRMSprop([ours], lr=LR, decay=DECAY, eps=EPS)
    theirs_optimizer = torch.optim.RMSprop(
        [theirs], lr=LR, alpha=DECAY, eps=EPS, centered=True, momentum=0
    )
    _step_with_gradient(ours_optimizer, ours, 2.0)
    _step_with_gradient(theirs_optimizer, theirs, 2.0)

    # g2 - g² = 0.2 - 0.01 = 0.19 for both; only where eps goes differs.
    ours_expected = 1.0 - 0.00025 * 2.0 / math.sqrt(0.19 + 0.01)  # 0.99888197
    theirs_expected = 1.0 - 0.00025 * 2.0 / (math.sqrt(0.19) + 0.01)  # 0.99887867
    assert ours.item() == pytest.approx(ours_expected, rel=1e-12)
    assert theirs.item() == pytest.approx(theirs_expected, rel=1e-12)
    assert abs(ours.item() - theirs.item()) > 3e-6


def test_first_step_from_zero_state() -> None:
    gradients = [3.0, -0.5, 0.0, 1e-3, 40.0]
    initial = [0.1, 0.2, 0.3, 0.4, 0.5]
    param = torch.nn.Parameter(torch.tensor(initial, dtype=torch.float64))
    optimizer = DeepMindRMSprop([param], lr=LR, decay=DECAY, eps=EPS)
    param.grad = torch.tensor(gradients, dtype=torch.float64)
    optimizer.step()

    # g and g2 start at zero, with no bias correction:
    # update = lr Δ / sqrt((1-d)Δ² - (1-d)²Δ² + eps).
    one_minus_decay = 1.0 - DECAY
    expected = [
        start
        - LR * delta / math.sqrt(one_minus_decay * delta**2 - one_minus_decay**2 * delta**2 + EPS)
        for start, delta in zip(initial, gradients, strict=True)
    ]
    assert param.tolist() == pytest.approx(expected, rel=1e-12)
    assert optimizer.state[param]["grad_avg"].tolist() == pytest.approx(
        [one_minus_decay * delta for delta in gradients], rel=1e-12
    )


def test_step_with_closure_returns_loss_and_updates() -> None:
    param = _scalar_parameter(1.5)
    optimizer = DeepMindRMSprop([param], lr=LR, decay=DECAY, eps=EPS)

    def closure() -> float:
        optimizer.zero_grad()
        loss = param**2  # gradient 2 * 1.5 = 3
        loss.backward()
        return loss.item()

    loss = optimizer.step(closure)
    assert loss == pytest.approx(2.25)
    # g = 0.15, g2 = 0.05 * 9 = 0.45, g² = 0.0225.
    assert param.item() == pytest.approx(
        1.5 - 0.00025 * 3.0 / math.sqrt(0.45 - 0.0225 + 0.01), rel=1e-12
    )


def test_parameters_without_gradient_are_skipped() -> None:
    stepped = _scalar_parameter(1.0)
    frozen = _scalar_parameter(7.0)
    optimizer = DeepMindRMSprop([stepped, frozen], lr=LR, decay=DECAY, eps=EPS)
    stepped.grad = torch.tensor(2.0, dtype=torch.float64)
    assert frozen.grad is None
    optimizer.step()

    assert stepped.item() == pytest.approx(1.0 - 0.00025 * 2.0 / math.sqrt(0.2), rel=1e-12)
    assert frozen.item() == 7.0
    assert frozen not in optimizer.state


def test_param_groups_use_their_own_hyperparameters() -> None:
    default_group = _scalar_parameter(1.0)
    fast_group = _scalar_parameter(1.0)
    optimizer = DeepMindRMSprop(
        [{"params": [default_group]}, {"params": [fast_group], "lr": 0.001, "eps": 0.2}],
        lr=LR,
        decay=DECAY,
        eps=EPS,
    )
    default_group.grad = torch.tensor(2.0, dtype=torch.float64)
    fast_group.grad = torch.tensor(2.0, dtype=torch.float64)
    optimizer.step()

    # Both: g2 - g² = 0.19.
    assert default_group.item() == pytest.approx(1.0 - 0.00025 * 2.0 / math.sqrt(0.2), rel=1e-12)
    assert fast_group.item() == pytest.approx(1.0 - 0.001 * 2.0 / math.sqrt(0.39), rel=1e-12)


def _network() -> torch.nn.Module:
    torch.manual_seed(0)
    return torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.ReLU(), torch.nn.Linear(4, 2))


def _train_steps(
    network: torch.nn.Module, optimizer: torch.optim.Optimizer, inputs: list[torch.Tensor]
) -> None:
    for batch in inputs:
        optimizer.zero_grad()
        network(batch).square().sum().backward()
        optimizer.step()


def test_state_dict_round_trip_continues_identically() -> None:
    generator = torch.Generator().manual_seed(1)
    batches = [torch.randn(5, 3, generator=generator) for _ in range(6)]

    network_a = _network()
    optimizer_a = DeepMindRMSprop(network_a.parameters())
    _train_steps(network_a, optimizer_a, batches[:3])

    # Through bytes, as a checkpoint would be, so nothing is shared with A.
    buffer = io.BytesIO()
    torch.save(optimizer_a.state_dict(), buffer)
    buffer.seek(0)
    network_b = copy.deepcopy(network_a)
    optimizer_b = DeepMindRMSprop(network_b.parameters())
    optimizer_b.load_state_dict(torch.load(buffer))

    _train_steps(network_a, optimizer_a, batches[3:])
    _train_steps(network_b, optimizer_b, batches[3:])

    for param_a, param_b in zip(network_a.parameters(), network_b.parameters(), strict=True):
        assert torch.equal(param_a, param_b)
        for key in ("grad_avg", "square_avg"):
            assert torch.equal(optimizer_a.state[param_a][key], optimizer_b.state[param_b][key])

    # Without the loaded state the continuation differs, so the check above can fail.
    network_c = copy.deepcopy(network_b)
    network_fresh = copy.deepcopy(network_b)
    _train_steps(network_c, optimizer_b, batches[:1])
    _train_steps(network_fresh, DeepMindRMSprop(network_fresh.parameters()), batches[:1])
    assert not all(
        torch.equal(param_c, param_fresh)
        for param_c, param_fresh in zip(
            network_c.parameters(), network_fresh.parameters(), strict=True
        )
    )


def test_optimizer_names() -> None:
    assert OPTIMIZER_NAMES == ("deepmind_rmsprop", "rmsprop", "adam")


# Distinct values so that a mixed-up argument shows.
BUILD_ARGUMENTS = {
    "learning_rate": 0.001,
    "rmsprop_decay": 0.9,
    "rmsprop_epsilon": 0.02,
    "adam_epsilon": 1e-4,
}


def test_build_deepmind_rmsprop() -> None:
    param = _scalar_parameter(1.0)
    optimizer = build_optimizer("deepmind_rmsprop", [param], **BUILD_ARGUMENTS)
    assert type(optimizer) is DeepMindRMSprop
    group = optimizer.param_groups[0]
    assert (group["lr"], group["decay"], group["eps"]) == (0.001, 0.9, 0.02)


def test_build_rmsprop_is_non_centred_hinton_rmsprop() -> None:
    param = _scalar_parameter(1.0)
    optimizer = build_optimizer("rmsprop", [param], **BUILD_ARGUMENTS)
    assert type(optimizer) is torch.optim.RMSprop
    group = optimizer.param_groups[0]
    assert (group["lr"], group["alpha"], group["eps"]) == (0.001, 0.9, 0.02)
    assert group["centered"] is False
    assert group["momentum"] == 0
    assert group["weight_decay"] == 0

    # Hinton's RMSProp: v = 0.1 * 2² = 0.4, update = lr Δ / (sqrt(v) + eps).
    _step_with_gradient(optimizer, param, 2.0)
    assert param.item() == pytest.approx(1.0 - 0.001 * 2.0 / (math.sqrt(0.4) + 0.02), rel=1e-12)


def test_build_adam() -> None:
    param = _scalar_parameter(1.0)
    optimizer = build_optimizer("adam", [param], **BUILD_ARGUMENTS)
    assert type(optimizer) is torch.optim.Adam
    group = optimizer.param_groups[0]
    assert (group["lr"], group["eps"]) == (0.001, 1e-4)
    assert group["betas"] == (0.9, 0.999)


def test_build_unknown_name_lists_accepted_names() -> None:
    with pytest.raises(ValueError) as error:
        build_optimizer("sgd", [_scalar_parameter(1.0)], **BUILD_ARGUMENTS)
    assert str(error.value) == "unknown optimizer 'sgd'; accepted: adam, deepmind_rmsprop, rmsprop"


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"lr": 0.0}, r"lr must be > 0"),
        ({"lr": -0.00025}, r"lr must be > 0"),
        ({"lr": float("nan")}, r"lr must be > 0"),
        ({"decay": 1.0}, r"decay must be in \[0, 1\)"),
        ({"decay": -0.1}, r"decay must be in \[0, 1\)"),
        ({"eps": 0.0}, r"eps must be > 0"),
        ({"eps": -0.01}, r"eps must be > 0"),
    ],
)
def test_rejects_bad_arguments(arguments: dict[str, float], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        DeepMindRMSprop([_scalar_parameter(1.0)], **arguments)


def test_rejects_bad_argument_in_param_group() -> None:
    with pytest.raises(ValueError, match=r"decay must be in \[0, 1\)"):
        DeepMindRMSprop([{"params": [_scalar_parameter(1.0)], "decay": 1.5}])


def test_accepts_zero_decay() -> None:
    # decay 0: g = Δ, g2 = Δ², so the denominator is sqrt(eps).
    param = _scalar_parameter(1.0)
    optimizer = DeepMindRMSprop([param], lr=LR, decay=0.0, eps=EPS)
    _step_with_gradient(optimizer, param, 2.0)
    assert param.item() == pytest.approx(1.0 - 0.00025 * 2.0 / math.sqrt(0.01), rel=1e-12)


def _nature_like_parameters(seed: int) -> list[torch.nn.Parameter]:
    generator = torch.Generator().manual_seed(seed)
    shapes = [(32, 4, 8, 8), (32,), (64, 32, 4, 4), (64,), (512, 3136), (512,), (6, 512), (6,)]
    return [torch.nn.Parameter(torch.randn(shape, generator=generator) * 0.1) for shape in shapes]


def test_the_foreach_step_gives_the_per_parameter_steps_bits() -> None:
    """Each operation on all tensors at once (torch._foreach_*) is the same arithmetic per
    element, so the same bits on CPU, after steps whose gradients vary (one parameter
    without a gradient, skipped by both)."""
    runs = []
    for foreach in (True, False):
        params = _nature_like_parameters(0)
        optimizer = DeepMindRMSprop(params, foreach=foreach)
        generator = torch.Generator().manual_seed(1)
        for _ in range(5):
            for p in params[:-1]:
                p.grad = torch.randn(p.shape, generator=generator)
            optimizer.step()
        runs.append((params, optimizer.state_dict()))
    (foreach_params, foreach_state), (loop_params, loop_state) = runs
    for a, b in zip(foreach_params, loop_params, strict=True):
        assert torch.equal(a, b)
    assert foreach_state["state"].keys() == loop_state["state"].keys()
    for key, values in foreach_state["state"].items():
        for name, value in values.items():
            assert torch.equal(value, loop_state["state"][key][name])


def test_foreach_is_chosen_for_cuda_parameters_and_kept_by_copies() -> None:
    params = _nature_like_parameters(0)
    optimizer = DeepMindRMSprop(params)
    assert optimizer.foreach is None  # per parameter on CPU (no faster there), foreach on CUDA
    assert copy.deepcopy(DeepMindRMSprop(params, foreach=False)).foreach is False
    saved = io.BytesIO()
    torch.save(DeepMindRMSprop(params, foreach=True), saved)
    saved.seek(0)
    assert torch.load(saved, weights_only=False).foreach is True


def _adam_pair() -> tuple[list[torch.nn.Parameter], torch.optim.Adam, AdamKernelStep]:
    """Two copies of three parameters, one stepped by `step`, one by the kernel call."""
    generator = torch.Generator().manual_seed(1)
    shapes = [(32, 8), (32,), (5, 32)]
    params = [torch.nn.Parameter(torch.randn(*s, generator=generator)) for s in shapes]
    copies = [torch.nn.Parameter(p.detach().clone()) for p in params]
    reference = torch.optim.Adam(params, lr=2e-3, eps=1e-5, weight_decay=0.01, fused=True)
    direct = torch.optim.Adam(copies, lr=2e-3, eps=1e-5, weight_decay=0.01, fused=True)
    return [*params, *copies], reference, AdamKernelStep(direct)


def _gradients(params: list[torch.nn.Parameter], seed: int) -> None:
    generator = torch.Generator().manual_seed(seed)
    half = len(params) // 2
    for p, q in zip(params[:half], params[half:], strict=True):
        p.grad = torch.randn(p.shape, generator=generator)
        q.grad = p.grad.clone()


def _bits(tensors: list[torch.Tensor]) -> list[list[int]]:
    return [t.detach().reshape(-1).view(torch.int32).tolist() for t in tensors]


def test_the_adam_kernel_call_gives_adams_bits_across_a_load() -> None:
    params, reference, step = _adam_pair()
    half = len(params) // 2
    for update in range(12):
        _gradients(params, update)
        reference.step()
        step()
        if update == 5:  # a load replaces the state's tensors: the next call reads them
            buffer = io.BytesIO()
            torch.save(step.optimizer.state_dict(), buffer)
            buffer.seek(0)
            step.optimizer.load_state_dict(torch.load(buffer))
    assert _bits(params[:half]) == _bits(params[half:])
    for p, q in zip(params[:half], params[half:], strict=True):
        ours, theirs = reference.state[p], step.optimizer.state[q]
        assert _bits([ours["exp_avg"], ours["exp_avg_sq"]]) == _bits(
            [theirs["exp_avg"], theirs["exp_avg_sq"]]
        )
        assert ours["step"].item() == theirs["step"].item() == 12


def test_the_adam_kernel_call_leaves_what_it_cannot_do_to_step() -> None:
    """A hook, a parameter without a gradient, or another setting: Adam's own step runs
    (its hook is called; the gradient-less parameter keeps its weights and has no state)."""
    params, reference, step = _adam_pair()
    half = len(params) // 2
    _gradients(params, 0)
    reference.step(), step()  # the state exists: later calls may take the kernel path
    calls = []
    handle = step.optimizer.register_step_pre_hook(lambda *_: calls.append(1))
    _gradients(params, 1)
    reference.step(), step()
    handle.remove()
    assert calls == [1]
    _gradients(params, 2)
    params[0].grad = params[half].grad = None
    before = params[half].detach().clone()
    reference.step(), step()
    assert torch.equal(params[half], before)
    assert _bits(params[:half]) == _bits(params[half:])
    step.optimizer.param_groups[0]["amsgrad"] = True
    assert step._kernel_tensors() is None


def test_step_function_calls_adams_kernel_and_other_optimizers_step() -> None:
    params, _, _ = _adam_pair()
    assert isinstance(step_function(torch.optim.Adam(params, fused=True)), AdamKernelStep)
    rmsprop = DeepMindRMSprop(params)
    assert step_function(rmsprop) == rmsprop.step


def _with_gradients(scale: float) -> list[torch.nn.Parameter]:
    generator = torch.Generator().manual_seed(0)
    params = [torch.nn.Parameter(torch.zeros(shape)) for shape in ((64, 33), (33,), (5, 64))]
    for param in params:
        param.grad = torch.randn(param.shape, generator=generator) * scale
    return params


@pytest.mark.parametrize(("scale", "one"), [(1e-3, 0.0), (1.0, 0.0), (50.0, 0.0), (1e-3, math.nan)])
def test_the_clip_gives_torchs_bits_and_norm(scale: float, one: float) -> None:
    """Within the bound (1e-3: norm ~0.05), across it (1.0 is ~48, 50.0 ~2400, against 10)
    and with one NaN among small gradients (PyTorch makes every gradient NaN), as PyTorch's
    own clip."""
    ours, theirs = _with_gradients(scale), _with_gradients(scale)
    for params in (ours, theirs):
        assert params[1].grad is not None
        params[1].grad[3] = one
    norm = clip_gradient_norm_(ours, 10.0)
    expected = torch.nn.utils.clip_grad_norm_(theirs, 10.0)
    assert torch.equal(norm, expected) or (norm.isnan() and expected.isnan())
    for a, b in zip(ours, theirs, strict=True):
        assert a.grad is not None and b.grad is not None
        assert torch.equal(a.grad.view(torch.int32), b.grad.view(torch.int32))


def test_the_clip_leaves_gradients_within_the_bound_unwritten() -> None:
    params = _with_gradients(1e-3)
    versions = [param.grad._version for param in params if param.grad is not None]
    clip_gradient_norm_(params, 10.0)
    assert [param.grad._version for param in params if param.grad is not None] == versions
    clip_gradient_norm_(params, 1e-3)  # beyond it: scaled in place
    assert all(param.grad._version > v for param, v in zip(params, versions, strict=True))


def test_a_large_step_runs_in_pieces_eagerly_and_whole_when_compiled(monkeypatch) -> None:
    """Eagerly, cache-sized pieces (each element sees the same operations); while
    `torch.compile` traces the step (`compile_update`), whole: Inductor would otherwise
    select each element's piece by index in its one fused loop (ten times the eager time)."""
    tensors = tuple(torch.zeros(3 * optim._PIECE) for _ in range(4))
    pieces = list(optim._cache_sized_pieces(tensors))
    assert [piece[0].numel() for piece in pieces] == [optim._PIECE] * 3
    monkeypatch.setattr(torch.compiler, "is_compiling", lambda: True)
    (whole,) = optim._cache_sized_pieces(tensors)
    assert all(part is tensor for part, tensor in zip(whole, tensors, strict=True))
