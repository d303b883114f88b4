"""The `threads` setting: the CPU's arithmetic depends on the thread count, so a run records
its count in every checkpoint and a resume takes it back (or says it will not be exact);
a resume where the arithmetic itself differs (another processor) says so; a warning
when the cores are already busy; and MKL's vector math warmed up before a run computes."""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from dqnlab.config import Config, resolve_config
from dqnlab.errors import ConfigError
from dqnlab.run import determinism
from dqnlab.run.determinism import (
    arithmetic_fingerprint,
    busy_cores_warning,
    resume_arithmetic,
    resume_threads,
)
from tests.run.test_resume import (
    CARTPOLE,
    assert_identical,
    final_state,
    finish,
    wait_for_checkpoint,
)

CPU = torch.device("cpu")


@pytest.fixture(autouse=True)
def _restore_threads() -> Iterator[None]:
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def _config(threads: int, total_steps: int) -> Config:
    # The classic preset's MLP of 256 x 256 at batch 64: large enough for the matrix
    # products to split across threads (a tiny network gives the same bits at any count).
    return resolve_config(
        "classic", env="CartPole-v1", seed=5, total_steps=total_steps, threads=threads,
        replay_start_steps=100, eval_period_steps=1000, eval_steps=100,
        checkpoint_period_steps=100, final_eval_after_training=False,
    )  # fmt: skip


def _dqnlab(threads: int, *args: str, **environment: str) -> subprocess.Popen[str]:
    """`dqnlab` in a process whose PyTorch default is `threads` (OMP_NUM_THREADS)."""
    return subprocess.Popen(
        [sys.executable, "-m", "dqnlab", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "OMP_NUM_THREADS": str(threads), **environment},
    )  # fmt: skip


# oneDNN held to SSE4.1 convolves by another code path than on any processor with AVX: a
# stand-in, on one machine, for a run resumed on another processor.
OTHER_PROCESSOR = {"ONEDNN_MAX_CPU_ISA": "SSE41"}


def _fingerprint_in_process(**environment: str) -> str:
    code = "from dqnlab.run.determinism import arithmetic_fingerprint as f; print(f())"
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True,
        env={**os.environ, "OMP_NUM_THREADS": "1", **environment},
    ).stdout.strip()  # fmt: skip


def test_a_resume_takes_back_the_thread_count_the_run_trained_with(tmp_path: Path) -> None:
    """Trained in a process of one thread (`threads = 0`: the default there), killed, and
    resumed in a process of two: the resume sets one thread again and ends where the run
    left alone ends (with two threads its updates give other bits on this CPU)."""
    args = [*CARTPOLE[: CARTPOLE.index("--steps")], "--steps", "1000",
            *CARTPOLE[CARTPOLE.index("--steps") + 2 :]]  # fmt: skip
    reference, resumed = tmp_path / "reference", tmp_path / "resumed"
    code, stderr = finish(_dqnlab(1, "train", *args, "--run-dir", str(reference)))
    assert code == 0, stderr
    process = _dqnlab(1, "train", *args, "--run-dir", str(resumed))
    assert wait_for_checkpoint(resumed, process, after=300), "the run ended before a kill"
    process.send_signal(signal.SIGKILL)
    process.wait()
    code, stderr = finish(_dqnlab(2, "resume", str(resumed), "--no-progress", "--device", "cpu"))
    assert code == 0, stderr
    assert "resuming with the 1 PyTorch thread(s) the run trained with" in stderr
    assert "float arithmetic" not in stderr  # the same machine, the same libraries
    state, replay = final_state(reference)
    state_resumed, replay_resumed = final_state(resumed)
    assert state_resumed["threads"] == 1
    assert_identical(state["learner"], state_resumed["learner"], "learner")
    assert_identical(replay, replay_resumed, "replay")


def test_a_resume_where_the_arithmetic_differs_says_it_will_not_be_exact(tmp_path: Path) -> None:
    """Trained where oneDNN convolves at SSE4.1, resumed where it does not: the checkpoint
    recorded the first process's fingerprint, and the resume names both."""
    other, here = _fingerprint_in_process(**OTHER_PROCESSOR), _fingerprint_in_process()
    if other == here:
        pytest.skip("oneDNN takes the same code path at SSE4.1 on this processor")
    run = tmp_path / "run"
    process = _dqnlab(1, "train", *CARTPOLE, "--run-dir", str(run), **OTHER_PROCESSOR)
    assert wait_for_checkpoint(run, process, after=300), "the run ended before a kill"
    process.send_signal(signal.SIGKILL)
    process.wait()
    code, stderr = finish(_dqnlab(1, "resume", str(run), "--no-progress", "--device", "cpu"))
    assert code == 0, stderr
    assert (
        f"float arithmetic is not the one the checkpoint was written with (fingerprint {here}, "
        f"the run's {other}" in stderr
    ), stderr
    state, _ = final_state(run)
    assert state["arithmetic"] == here  # what this process's checkpoints record from now on


def test_the_arithmetic_is_compared_on_the_cpu_only_and_where_it_was_recorded() -> None:
    now = arithmetic_fingerprint()
    assert now == arithmetic_fingerprint() and len(now) == 16
    assert resume_arithmetic(CPU, now, now) is None
    assert resume_arithmetic(CPU, None, now) is None  # a checkpoint from before it was recorded
    assert resume_arithmetic(torch.device("cuda"), "0" * 16, now) is None
    said = resume_arithmetic(CPU, "0" * 16, now)
    assert said is not None and "not bit for bit" in said


def test_a_count_set_otherwise_at_resume_wins_and_says_it_will_not_be_exact() -> None:
    torch.set_num_threads(2)
    said = resume_threads(_config(threads=2, total_steps=600), CPU, trained_with=1)
    assert said is not None and "not bit for bit" in said
    assert torch.get_num_threads() == 2
    said = resume_threads(_config(threads=0, total_steps=600), CPU, trained_with=1)
    assert said is not None and "resuming with the 1" in said
    assert torch.get_num_threads() == 1
    # Nothing to say: the same count, or a checkpoint from before the count was recorded.
    assert resume_threads(_config(threads=0, total_steps=600), CPU, trained_with=1) is None
    assert resume_threads(_config(threads=0, total_steps=600), CPU, trained_with=None) is None


def test_busy_cores_are_warned_of_only_for_several_threads_on_the_cpu(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(determinism, "usable_cores", lambda: 2)
    monkeypatch.setattr(determinism.os, "getloadavg", lambda: (2.1, 2.0, 1.0))
    warning = busy_cores_warning(2, CPU)
    assert warning is not None and "2.1 on 2 cores" in warning and "threads=1" in warning
    assert busy_cores_warning(1, CPU) is None
    assert busy_cores_warning(2, torch.device("cuda")) is None
    monkeypatch.setattr(determinism.os, "getloadavg", lambda: (0.3, 0.5, 1.0))
    assert busy_cores_warning(2, CPU) is None


def test_threads_below_zero_is_refused_in_one_line() -> None:
    with pytest.raises(ConfigError, match="threads = -1 must be zero or more"):
        _config(threads=-1, total_steps=600)


# Reads MKL's switch in a fresh process: PyTorch's pip builds for x86 link MKL into
# libtorch_cpu and export this service function; other builds have no MKL to ask.
MKL_DYNAMIC_PROBE = """
import ctypes, os, sys, torch
from dqnlab.config import resolve_config
from dqnlab.run.determinism import apply_threads
library = ctypes.CDLL(os.path.join(os.path.dirname(torch.__file__), "lib", "libtorch_cpu.so"))
if not hasattr(library, "mkl_serv_get_dynamic"):
    sys.exit(3)
before = library.mkl_serv_get_dynamic()
apply_threads(resolve_config("classic", env="CartPole-v1", threads=int(sys.argv[1])))
print(before, library.mkl_serv_get_dynamic(), torch.get_num_threads())
"""


@pytest.mark.parametrize("threads", [0, 1])
def test_a_run_leaves_mkl_no_choice_of_its_thread_count(threads: int) -> None:
    # MKL_DYNAMIC lets MKL run a product on fewer threads than asked, so in another order:
    # on until something calls torch.set_num_threads, which a run at `threads = 0` did not.
    probe = subprocess.run(
        [sys.executable, "-c", MKL_DYNAMIC_PROBE, str(threads)], capture_output=True,
        text=True, env={**os.environ, "OMP_NUM_THREADS": "2"}, check=False,
    )  # fmt: skip
    if probe.returncode == 3:
        pytest.skip("this PyTorch build has no MKL to ask")
    assert probe.returncode == 0, probe.stderr
    before, after, count = probe.stdout.split()
    assert before == "1", "MKL's default changed: this test no longer shows anything"
    assert after == "0"
    assert count == str(threads or 2)


# MKL's single-precision vector math entry points (Fortran names, exported by PyTorch's
# x86 pip builds), with the mode argument: 0x2 is VML_HA, the default accuracy.
VML_NAMES = {"log": "LN"}


def test_the_warmed_up_functions_are_the_ones_pytorch_computes_with_mkl() -> None:
    # If a PyTorch release stops calling MKL for one of them, the list should say so.
    library = ctypes.CDLL(os.path.join(os.path.dirname(torch.__file__), "lib", "libtorch_cpu.so"))
    if not hasattr(library, "VMSSQRT_"):
        pytest.skip("this PyTorch build has no MKL vector math to compare with")
    values = torch.linspace(0.05, 0.95, 10_000)
    size, mode = ctypes.c_int(values.numel()), ctypes.c_longlong(0x2)
    for name in determinism.VECTOR_MATH_FUNCTIONS:
        expected = np.empty(values.numel(), dtype=np.float32)
        vml = getattr(library, f"VMS{VML_NAMES.get(name, name.upper())}_")
        vml(ctypes.byref(size), values.numpy().ctypes.data_as(ctypes.c_void_p),
            expected.ctypes.data_as(ctypes.c_void_p), ctypes.byref(mode))  # fmt: skip
        assert np.array_equal(getattr(torch, name)(values).numpy(), expected), name


def test_the_warm_up_calls_each_function_alone_then_in_every_thread(monkeypatch) -> None:
    calls: list[tuple[str, int]] = []
    for name in determinism.VECTOR_MATH_FUNCTIONS:
        function = getattr(torch, name)
        monkeypatch.setattr(
            torch, name, lambda t, n=name, f=function: calls.append((n, t.numel())) or f(t)
        )
    torch.set_num_threads(2)
    determinism.warm_up_vector_math()
    grain = determinism.VECTOR_MATH_GRAIN
    assert [name for name, _ in calls[::2]] == list(determinism.VECTOR_MATH_FUNCTIONS)
    assert [name for name, _ in calls[1::2]] == list(determinism.VECTOR_MATH_FUNCTIONS)
    assert all(size < grain for _, size in calls[::2])  # one piece: the calling thread alone
    assert all(size >= 2 * 2 * grain for _, size in calls[1::2])  # pieces for both threads


def test_set_threads_warms_up_a_pool_only_where_it_grows(monkeypatch) -> None:
    warmed: list[int] = []
    real = determinism.warm_up_vector_math
    monkeypatch.setattr(
        determinism, "warm_up_vector_math", lambda: warmed.append(torch.get_num_threads()) or real()
    )

    def counts() -> None:  # a Python thread of its own: an OpenMP pool of its own
        for count in (1, 2, 1, 2, 2):
            determinism.set_threads(count)

    thread = threading.Thread(target=counts)
    thread.start()
    thread.join()
    assert warmed == [1, 2]
