"""Denormal floats flushed to zero on the CPU, in every thread that computes
(`flush_denormals`).

Why: an optimizer's running averages of a weight whose gradient stays zero (a unit a ReLU
keeps off, an input that is always zero) decay geometrically, and in IEEE arithmetic they
never reach zero. Below float32's smallest normal number (1.2e-38) they become denormal,
and there a few units in the last place times the decay round back to themselves (Adam's
0.9 x 4 units = 3.6, rounded to 4; DeepMind's RMSProp's 0.95 x 10 = 9.5, rounded to 10), so
they stay for good. x86 processors compute on denormal numbers in microcode, tens of times
slower than on others. Measured on the Xeon (2026-12-06, one thread): after 20,000 steps of
`classic` on CartPole-v1, half of Adam's first moments of the 256 x 256 layer were stuck
denormals (32,005 of 65,536), and its optimizer step took 0.58 ms against 0.12 ms with them
flushed; Nature's RMSProp step on 1.6M weights with 30% of its averages stuck there took
48.9 ms against 3.6 ms.

With the processor's flush-to-zero and denormals-are-zero modes such values become zero
instead. Nothing else changes where no denormal arises: `classic` on CartPole-v1 trained
20,000 steps to the same weights, bit for bit, with and without (only the stuck moments
differ, 0 against a few units of 1e-45), 30% faster.

PyTorch's switch (`torch.set_flush_denormal`) sets the mode of the calling thread alone;
the threads of its OpenMP pool, which run ATen's, MKL's and oneDNN's parallel regions, keep
theirs, so half of a parallel operation would flush and the other half not. So the mode is
set inside one parallel region of the OpenMP runtime PyTorch loaded (its `GOMP_parallel`
entry point, which GNU's libgomp exports, and LLVM's and Intel's runtimes for GNU
compatibility): every thread of the pool runs it. Threads made later (a larger pool, a
Python thread) start from the mode of the thread that makes them. PyTorch's own copy of the
runtime is tried first (another package may bring its own), and each try is checked by a
parallel multiplication of denormals. Where PyTorch's pool cannot be reached, or the
processor has no such mode, the mode is left off.
"""

from __future__ import annotations

import contextlib
import ctypes
from collections.abc import Callable, Iterator
from pathlib import Path

import torch

from dqnlab.config import Config

_OPENMP_LIBRARIES = ("libgomp", "libiomp", "libomp")
_flushing = False  # what `set_flush_denormals` last made of this process


def apply_denormals(config: Config) -> bool:
    """Set this process's mode from `flush_denormals`; returns whether denormals are now
    flushed in every thread."""
    return set_flush_denormals(config.flush_denormals)


def set_flush_denormals(on: bool) -> bool:
    """Flush denormals to zero (`on`) or compute with them, in the calling thread and every
    thread of PyTorch's OpenMP pool; returns whether they are now flushed everywhere."""
    global _flushing
    _flushing = False
    if not torch.set_flush_denormal(on):  # no such mode on this processor
        return False
    for runtime in _openmp_runtimes():
        _in_every_pool_thread(runtime, lambda: torch.set_flush_denormal(on))
        if _flushed_share() == (1.0 if on else 0.0):  # PyTorch's pool was this runtime's
            _flushing = on
            return on
    torch.set_flush_denormal(False)  # PyTorch's pool not reached: leave the mode off
    return False


@contextlib.contextmanager
def denormals_kept() -> Iterator[None]:
    """IEEE's gradual underflow inside (a peer's code timed as its users run it), the
    process's mode again after."""
    before = _flushing
    set_flush_denormals(False)
    try:
        yield
    finally:
        set_flush_denormals(before)


def _openmp_runtimes() -> Iterator[ctypes.CDLL]:
    """The OpenMP runtimes this process loaded (from /proc/self/maps), PyTorch's own copy
    first: another package may bring its own (pygame's wheel bundles a libgomp), whose
    parallel region would not reach PyTorch's threads."""
    maps = Path("/proc/self/maps")
    if not maps.exists():
        return
    paths = {line.split()[-1] for line in maps.read_text().splitlines() if "/" in line}
    torch_libraries = Path(torch.__file__).parent / "lib"
    found = [Path(path) for path in paths if Path(path).name.startswith(_OPENMP_LIBRARIES)]
    for path in sorted(found, key=lambda path: (path.parent != torch_libraries, str(path))):
        try:
            runtime = ctypes.CDLL(str(path))
        except OSError:
            continue
        if hasattr(runtime, "GOMP_parallel"):
            yield runtime


def _in_every_pool_thread(runtime: ctypes.CDLL, action: Callable[[], object]) -> None:
    """`action()` in each thread of the calling thread's OpenMP pool, at its current size:
    one parallel region (`GOMP_parallel(fn, data, 0 threads: the pool's count, 0)`)."""

    @ctypes.CFUNCTYPE(None, ctypes.c_void_p)
    def body(_: int | None) -> None:
        action()  # each thread takes the GIL that the call released

    runtime.GOMP_parallel.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint,
                                      ctypes.c_uint]  # fmt: skip
    runtime.GOMP_parallel.restype = None
    runtime.GOMP_parallel(ctypes.cast(body, ctypes.c_void_p), None, 0, 0)


def flushes_everywhere() -> bool:
    """Whether a parallel operation flushes denormals in all of its threads."""
    return _flushed_share() == 1.0


def _flushed_share() -> float:
    """The share of a parallel operation's results that its threads flushed: each thread
    multiplies its part of the smallest denormal number by one (made from its bits, since
    converting 1e-40 to float32 in a flushing thread would give zero already)."""
    denormals = torch.ones(1 << 20, dtype=torch.int32).view(torch.float32)
    return float(((denormals * 1.0) == 0).float().mean())
