"""Optimizers: DeepMind's RMSProp from the Lua code, and the seed paper's alternatives.

`build_optimizer` maps a config name to an optimizer; `DeepMindRMSprop` is the exact
update of NeuralQLearner.lua, which PyTorch does not ship.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import torch
from torch.optim import optimizer as torch_optimizer  # its global step hooks

from dqnlab.config import CHOICES

OPTIMIZER_NAMES = CHOICES["optimizer"]  # the configuration's list


class DeepMindRMSprop(torch.optim.Optimizer):
    """Centred RMSProp exactly as in DeepMind's Lua DQN (NeuralQLearner.lua, lines 265-277).

    For every parameter w with gradient Δ, and running averages g, g2 that start at zero::

        g   = decay * g  + (1 - decay) * Δ
        g2  = decay * g2 + (1 - decay) * Δ²
        w   = w - lr * Δ / sqrt(g2 - g² + eps)

    There is no momentum, no bias correction and no weight decay, and ``eps`` sits
    *inside* the square root. The Lua code steps along its backward pass's output, the
    negative of the loss gradient; g² and g2 do not depend on the sign, so subtracting
    the loss gradient, as here, is the same update.

    The defaults (lr 0.00025, decay 0.95, eps 0.01) are the Nature DQN values. They were
    tuned for Δ summed over the minibatch: use this optimizer with the *summed* clipped-δ
    loss so that eps = 0.01 weighs against the gradient statistics as it did in the Lua
    code. With a batch-mean loss Δ shrinks by the batch size and the same eps dominates
    the denominator (the equivalent there would be 0.01 / 32² ≈ 9.77e-6).

    ``torch.optim.RMSprop(centered=True)`` is a different optimizer: it divides by
    ``sqrt(g2 - g²) + eps``, eps *outside* the square root.

    Running averages are kept in the optimizer state as ``"grad_avg"`` (g) and
    ``"square_avg"`` (g2), so `state_dict` / `load_state_dict` resume a run exactly.
    """

    def __init__(
        self,
        params: Iterable[torch.Tensor] | Iterable[dict[str, Any]],
        lr: float = 0.00025,
        decay: float = 0.95,
        eps: float = 0.01,
        foreach: bool | None = None,
    ) -> None:
        """`foreach`: each operation on all tensors at once (`torch._foreach_*`): one call
        per operation rather than per parameter. On CPU these are the same kernels in a
        loop, so the same bits, and no faster (the step is bound by its passes over
        memory); on a GPU, multi-tensor kernels: a tenth of the launches. False: the
        per-parameter loop, as the Lua code reads. None: foreach for parameters on a CUDA
        device, as PyTorch's own optimizers choose."""
        _check_hyperparameters(lr=lr, decay=decay, eps=eps)
        defaults = {"lr": lr, "decay": decay, "eps": eps}
        super().__init__(params, defaults)
        self.foreach = foreach

    def __getstate__(self) -> dict[str, Any]:
        # The base class copies and pickles only its own attributes.
        return {**super().__getstate__(), "foreach": self.foreach}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.foreach = state.pop("foreach", None)
        super().__setstate__(state)

    def add_param_group(self, param_group: dict[str, Any]) -> None:
        # Per-group overrides bypass __init__, so they are checked here as well.
        super().add_param_group(param_group)
        group = self.param_groups[-1]
        _check_hyperparameters(lr=group["lr"], decay=group["decay"], eps=group["eps"])

    @torch.no_grad()
    def step(  # type: ignore[override]  # the base class declares two overloads
        self, closure: Callable[[], float] | None = None
    ) -> float | None:
        """Take one update; `closure`, if given, re-evaluates and returns the loss."""
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()

        for group in self.param_groups:
            params, grads, grad_avgs, square_avgs = self._group_tensors(group)
            if not params:
                continue
            foreach = self.foreach
            if foreach is None:
                foreach = all(param.is_cuda for param in params)
            step = _step_foreach if foreach else _step_per_parameter
            step(params, grads, grad_avgs, square_avgs, group["lr"], group["decay"], group["eps"])
        return loss

    def _group_tensors(
        self, group: dict[str, Any]
    ) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
        """The parameters of `group` that have a gradient, their gradients and their running
        averages (created at zero on first use, as the Lua code's g and g2)."""
        params, grads, grad_avgs, square_avgs = [], [], [], []
        for param in group["params"]:
            grad = param.grad
            if grad is None:
                continue
            if grad.is_sparse:
                raise RuntimeError("DeepMindRMSprop does not support sparse gradients")
            state = self.state[param]
            if len(state) == 0:  # zero start, no bias correction later
                state["grad_avg"] = torch.zeros_like(param, memory_format=torch.preserve_format)
                state["square_avg"] = torch.zeros_like(param, memory_format=torch.preserve_format)
            params.append(param)
            grads.append(grad)
            grad_avgs.append(state["grad_avg"])
            square_avgs.append(state["square_avg"])
        return params, grads, grad_avgs, square_avgs


def _step_per_parameter(
    params: list[torch.Tensor],
    grads: list[torch.Tensor],
    grad_avgs: list[torch.Tensor],
    square_avgs: list[torch.Tensor],
    lr: float,
    decay: float,
    eps: float,
) -> None:
    for tensors in zip(params, grads, grad_avgs, square_avgs, strict=True):
        for param, grad, grad_avg, square_avg in _cache_sized_pieces(tensors):
            # Same operation order as the Lua code: g:mul(0.95):add(0.05, dw).
            grad_avg.mul_(decay).add_(grad, alpha=1.0 - decay)
            square_avg.mul_(decay).addcmul_(grad, grad, value=1.0 - decay)
            # The one temporary per piece: sqrt(g2 - g² + eps), eps inside.
            denominator = torch.addcmul(square_avg, grad_avg, grad_avg, value=-1.0)
            denominator.add_(eps).sqrt_()
            param.addcdiv_(grad, denominator, value=-lr)


# Elements per piece of a large parameter (1 MiB of float32 per tensor): the step's seven
# passes over a piece's five tensors then run in the processor's L2 cache instead of
# streaming the Nature CNN's 1.6M-weight layer from memory seven times (about a quarter
# faster on a 2-core Xeon). Each element sees the same operations in the same order,
# so the bits are the same (the `nature` pin test).
_PIECE = 1 << 18


def _cache_sized_pieces(
    tensors: tuple[torch.Tensor, ...],
) -> Iterable[tuple[torch.Tensor, ...]]:
    """`tensors` (a parameter, its gradient and running averages) whole, or as flat views
    of `_PIECE` elements when all are contiguous and larger than two pieces. Whole while
    `torch.compile` traces the step (`compile_update`): Inductor fuses the step's passes
    into one loop, and pieces would only make it select each element's piece by index
    (the compiled step took 23 ms on 1.7M weights with them, on the Xeon, 2026-12-06)."""
    if (
        tensors[0].numel() <= 2 * _PIECE
        or not all(t.is_contiguous() for t in tensors)
        or torch.compiler.is_compiling()
    ):
        return (tensors,)
    flat = [t.view(-1) for t in tensors]
    return zip(*(f.split(_PIECE) for f in flat), strict=True)


def _step_foreach(
    params: list[torch.Tensor],
    grads: list[torch.Tensor],
    grad_avgs: list[torch.Tensor],
    square_avgs: list[torch.Tensor],
    lr: float,
    decay: float,
    eps: float,
) -> None:
    # The operations of `_step_per_parameter`, in its order, each on every tensor: every
    # element sees the same arithmetic, so the results are the same bits.
    torch._foreach_mul_(grad_avgs, decay)
    torch._foreach_add_(grad_avgs, grads, alpha=1.0 - decay)
    torch._foreach_mul_(square_avgs, decay)
    torch._foreach_addcmul_(square_avgs, grads, grads, value=1.0 - decay)
    denominators = torch._foreach_addcmul(square_avgs, grad_avgs, grad_avgs, value=-1.0)
    torch._foreach_add_(denominators, eps)
    torch._foreach_sqrt_(denominators)
    torch._foreach_addcdiv_(params, grads, denominators, value=-lr)


def clip_gradient_norm_(parameters: Iterable[torch.Tensor], max_norm: float) -> torch.Tensor:
    """`torch.nn.utils.clip_grad_norm_(parameters, max_norm)`, the same bits, without its
    multiplication by one on the CPU: PyTorch scales every gradient by
    min(max_norm / (norm + 1e-6), 1) even when the minimum is one, so as not to wait for a
    device to say which; on the CPU nothing waits, and a step whose norm is within bounds
    skips a pass over every gradient (Rainbow's clip 2.2 against 3.1 ms on the Xeon,
    2026-12-06; its whole update gains less, 38.5 against 38.6 ms, as Adam then reads the
    gradients from memory instead of cache). Multiplying by one changes no value (a denormal
    that it would flush to zero reads as zero in every later operation under
    `flush_denormals`). A NaN or infinite norm scales, as PyTorch does; so does anything off
    the CPU or being compiled."""
    with_gradient = [param for param in parameters if param.grad is not None]
    gradients = [param.grad for param in with_gradient if param.grad is not None]
    total_norm = torch.nn.utils.get_total_norm(gradients)
    on_cpu = all(gradient.device.type == "cpu" for gradient in gradients)
    no_wait = on_cpu and not torch.compiler.is_compiling()
    if no_wait and bool(max_norm / (total_norm + 1e-6) >= 1.0):  # the clamped coefficient: 1
        return total_norm
    torch.nn.utils.clip_grads_with_norm_(with_gradient, max_norm, total_norm)
    return total_norm


def step_function(optimizer: torch.optim.Optimizer) -> Callable[[], object]:
    """What an update calls to step `optimizer`: fused Adam's kernel directly
    (`AdamKernelStep`) for Adam, else the optimizer's own `step`."""
    if isinstance(optimizer, torch.optim.Adam):
        return AdamKernelStep(optimizer)
    return optimizer.step


class AdamKernelStep:
    """`optimizer.step()` of a fused `torch.optim.Adam` whose tensors are on the CPU, as the
    one call PyTorch's step ends in (`torch._fused_adam_`, after the step counts are
    incremented), without the Python around it: the same kernel on the same tensors with
    the same settings, so the same bits. In `classic`'s CartPole training loop the step
    took 123-131 us against 207 us through `step` (2026-12-06, the Xeon, 2 threads; its
    update is about 1.1 ms).

    Wherever the call would not be what `step` does, `step` itself runs: before the state
    exists (its first call creates it), a parameter without a gradient (step skips it),
    another group layout or setting than plain fused Adam (several groups, amsgrad,
    maximize, capturable, differentiable, a tensor learning rate, decoupled decay), mixed
    devices or dtypes, and step hooks, the optimizer's own or global."""

    def __init__(self, optimizer: torch.optim.Optimizer) -> None:
        self.optimizer = optimizer

    def __call__(self) -> None:
        optimizer = self.optimizer
        tensors = self._kernel_tensors()
        if tensors is None:
            optimizer.step()
            return
        params, grads, averages, square_averages, steps = tensors
        group = optimizer.param_groups[0]
        beta1, beta2 = group["betas"]
        with torch.no_grad():
            torch._foreach_add_(steps, 1)
            torch._fused_adam_(
                params, grads, averages, square_averages, [], steps,
                amsgrad=False, lr=group["lr"], beta1=beta1, beta2=beta2,
                weight_decay=group["weight_decay"], eps=group["eps"], maximize=False,
                grad_scale=None, found_inf=None,
            )  # fmt: skip

    def _kernel_tensors(self) -> tuple[list[torch.Tensor], ...] | None:
        """The kernel's lists (parameters, gradients, both averages, step counts), read
        afresh each call (a load replaces the state's tensors), or None where `step` must
        run instead."""
        optimizer = self.optimizer
        if len(optimizer.param_groups) != 1 or _step_hooks(optimizer):
            return None
        group = optimizer.param_groups[0]
        if not _plain_fused_adam(group):
            return None
        params = group["params"]
        grads, averages, square_averages, steps = [], [], [], []
        state = optimizer.state
        for param in params:
            grad, param_state = param.grad, state.get(param)
            if grad is None or not param_state or grad.is_sparse:
                return None
            grads.append(grad)
            averages.append(param_state["exp_avg"])
            square_averages.append(param_state["exp_avg_sq"])
            steps.append(param_state["step"])
        first = params[0] if params else None
        if first is None or any(
            p.device.type != "cpu" or p.dtype != first.dtype for p in (*params, *grads)
        ):
            return None
        return params, grads, averages, square_averages, steps


def _plain_fused_adam(group: dict[str, Any]) -> bool:
    return (
        group.get("fused") is True
        and not group["amsgrad"]
        and not group["maximize"]
        and not group["capturable"]
        and not group["differentiable"]
        and not group.get("decoupled_weight_decay", False)
        and not isinstance(group["lr"], torch.Tensor)
    )


def _step_hooks(optimizer: torch.optim.Optimizer) -> bool:
    return bool(
        optimizer._optimizer_step_pre_hooks
        or optimizer._optimizer_step_post_hooks
        or torch_optimizer._global_optimizer_pre_hooks
        or torch_optimizer._global_optimizer_post_hooks
    )


def _check_hyperparameters(lr: float, decay: float, eps: float) -> None:
    if not lr > 0.0:
        raise ValueError(f"DeepMindRMSprop: lr must be > 0, got {lr}")
    if not 0.0 <= decay < 1.0:
        raise ValueError(f"DeepMindRMSprop: decay must be in [0, 1), got {decay}")
    if not eps > 0.0:
        raise ValueError(f"DeepMindRMSprop: eps must be > 0, got {eps}")


def build_optimizer(
    name: str,
    params: Iterable[torch.Tensor] | Iterable[dict[str, Any]],
    learning_rate: float,
    rmsprop_decay: float,
    rmsprop_epsilon: float,
    adam_epsilon: float,
    capturable: bool = False,
) -> torch.optim.Optimizer:
    """Build the optimizer called `name`, one of `OPTIMIZER_NAMES`.

    - ``"deepmind_rmsprop"``: `DeepMindRMSprop`, the Nature DQN's optimizer.
    - ``"rmsprop"``: standard non-centred ("Hinton's") RMSProp, which the seed paper
      used (with lr 0.00005) because Caffe lacked DeepMind's variant; eps is added
      outside the square root, as PyTorch does.
    - ``"adam"``: Adam with `adam_epsilon`; the other hyper-parameters are PyTorch's.

    `capturable`: PyTorch's optimizers keep their step counts on the device, as a CUDA
    graph of the update needs (`update_graph`); `DeepMindRMSprop` has no step count.
    """
    if name == "deepmind_rmsprop":
        return DeepMindRMSprop(params, lr=learning_rate, decay=rmsprop_decay, eps=rmsprop_epsilon)
    if name == "rmsprop":
        return torch.optim.RMSprop(
            params,
            lr=learning_rate,
            alpha=rmsprop_decay,
            eps=rmsprop_epsilon,
            centered=False,
            momentum=0,
            capturable=capturable,
        )
    if name == "adam":
        return torch.optim.Adam(
            params, lr=learning_rate, eps=adam_epsilon, fused=True, capturable=capturable
        )
    accepted = ", ".join(sorted(OPTIMIZER_NAMES))
    raise ValueError(f"unknown optimizer {name!r}; accepted: {accepted}")
