"""`flush_denormals`: denormal floats flushed to zero in every PyTorch thread, as training
sets it from its settings, and why (an optimizer's averages stick at denormal values)."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from dqnlab.config import resolve_config
from dqnlab.run.denormals import (
    apply_denormals,
    denormals_kept,
    flushes_everywhere,
    set_flush_denormals,
)
from dqnlab.run.rundir import load_run_config, prepare_run_dir
from dqnlab.run.train import train

CPU = torch.device("cpu")
SMALLEST_NORMAL = torch.finfo(torch.float32).tiny


@pytest.fixture(autouse=True)
def two_threads_then_the_default() -> Iterator[None]:
    """Two PyTorch threads (a parallel operation is split between them); the process's
    default mode again after each test."""
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    set_flush_denormals(resolve_config("classic", env="CartPole-v1").flush_denormals)
    torch.set_num_threads(threads)


def test_every_thread_flushes_or_none_does() -> None:
    assert set_flush_denormals(True) is True and flushes_everywhere()
    assert set_flush_denormals(False) is False and not flushes_everywhere()
    # PyTorch's own switch sets the calling thread alone: the check sees the other half.
    torch.set_flush_denormal(True)
    assert not flushes_everywhere()


_BESIDE_ANOTHER_RUNTIME = """
import ctypes, sys, torch
torch.set_num_threads(2)
(torch.ones(1 << 20) * 1.0).sum()  # PyTorch's pool made, its threads computing with denormals
ctypes.CDLL(sys.argv[1])  # another package's OpenMP runtime, loaded after PyTorch's
from dqnlab.run.denormals import flushes_everywhere, set_flush_denormals
print(set_flush_denormals(True), flushes_everywhere(), set_flush_denormals(False),
      flushes_everywhere())
"""


def test_pytorch_s_pool_is_reached_beside_another_package_s_openmp_runtime() -> None:
    """pygame's wheel bundles a libgomp of its own (found when the whole suite ran): a
    parallel region of that runtime would not reach PyTorch's threads. In a new process,
    whose PyTorch threads have never flushed."""
    pygame = pytest.importorskip("pygame")
    bundled = sorted((Path(pygame.__file__).parent.parent / "pygame.libs").glob("libgomp*"))
    if not bundled:
        pytest.skip("this pygame brings no OpenMP runtime of its own")
    done = subprocess.run(
        [sys.executable, "-c", _BESIDE_ANOTHER_RUNTIME, str(bundled[0])],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["True", "True", "False", "False"]


def test_the_mode_is_kept_for_a_peer_and_given_back() -> None:
    set_flush_denormals(True)
    with denormals_kept():
        assert not flushes_everywhere()
    assert flushes_everywhere()


def _adam_first_moment_after_the_gradient_stops(flush: bool) -> torch.Tensor:
    """Adam's first moment of weights whose gradient was 1 once and zero for 1,000 steps
    after: 0.1 x 0.9^1000 is far below float32's smallest denormal (1.4e-45)."""
    set_flush_denormals(flush)
    weights = torch.zeros(4, requires_grad=True)
    adam = torch.optim.Adam([weights], lr=1e-3, fused=True)
    weights.grad = torch.ones(4)
    adam.step()
    weights.grad = torch.zeros(4)
    for _ in range(1000):
        adam.step()
    return adam.state[weights]["exp_avg"]


def test_without_flushing_an_average_sticks_at_a_denormal_value() -> None:
    """The cause: 0.9 x a few units of the last place rounds back to itself."""
    stuck = _adam_first_moment_after_the_gradient_stops(flush=False)
    assert (stuck != 0).all() and (stuck.abs() < SMALLEST_NORMAL).all()
    assert (_adam_first_moment_after_the_gradient_stops(flush=True) == 0).all()


@pytest.mark.parametrize("flush", [False, True])
def test_training_sets_the_mode_of_its_settings_and_records_them(
    tmp_path: Path, flush: bool
) -> None:
    set_flush_denormals(not flush)
    config = resolve_config(
        "classic", env="CartPole-v1", total_steps=200, replay_start_steps=100,
        eval_period_steps=0, heldout_transitions=0, mlp_hidden_sizes=[8], threads=2,
        flush_denormals=flush,
    )  # fmt: skip
    prepare_run_dir(tmp_path / "run", force=False, config=config)
    train(config, tmp_path / "run", CPU, progress=False, tensorboard=False)
    assert flushes_everywhere() is flush
    assert load_run_config(tmp_path / "run").flush_denormals is flush
    assert apply_denormals(config) is flush
