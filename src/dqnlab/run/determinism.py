"""Deterministic arithmetic: on a CUDA device the `deterministic` setting, on the CPU the
thread count (`threads`).

On the CPU, PyTorch's operations give the same bits from the same inputs at a given
number of threads, but not across counts: on a 2-core AMD EPYC (2026-12-04), four updates
with two threads gave other bits than with one for nature, double, classic, drq_epsilon
and iqn among others (c51, dueling, der and rainbow the same). So a run records its count
in every checkpoint and a resumed run takes it back. Nor across processors: ATen, MKL and
oneDNN choose their code paths (vector width, blocking) by the processor they find, and a
run resumed on another machine (a Xeon after an AMD EPYC, say) computes other bits from
the same state. So a checkpoint also records a fingerprint of this process's arithmetic
(`arithmetic_fingerprint`), and a resume whose fingerprint differs says that it will not
continue bit for bit.

On a GPU, some operations do not repeat by default: cuDNN's convolution gradients and
cuBLAS's split reductions add in an order that varies from call to call. Measured on an
H200 (2026-12-04): two `der` runs on Pong from the same seed differed in every weight
after 2,500 steps. With PyTorch's deterministic algorithms they repeat bit for bit, and so
does a resumed run.
"""

from __future__ import annotations

import hashlib
import os
import threading

import torch

from dqnlab.config import Config
from dqnlab.run.denormals import apply_denormals

# cuBLAS's documented workspace setting for reproducible results (CUDA's cuBLAS guide,
# "Results reproducibility"); PyTorch refuses deterministic matrix products without it.
CUBLAS_WORKSPACE = ":4096:8"
# PyTorch's float kernels that call MKL's vector math (VML), and the elements of one piece
# of their work (`grain_size` in ATen's UnaryOpsKernel.cpp): `warm_up_vector_math`.
VECTOR_MATH_FUNCTIONS = (
    "sqrt", "exp", "log", "log10", "sin", "cos", "tan", "asin", "acos", "atan", "tanh",
    "erf", "erfc", "erfinv",
)  # fmt: skip
VECTOR_MATH_GRAIN = 2048
# Per Python thread (each has an OpenMP pool of its own): the pool threads warmed up so far.
_warmed = threading.local()


def use_deterministic_algorithms(config: Config, device: torch.device) -> None:
    """On CUDA, with `deterministic` set, make every later operation of this process
    deterministic (an operation with no deterministic kernel then raises, naming itself,
    rather than run differently). Process-wide, as PyTorch's switch is; call it before the
    first operation on the device, since cuBLAS reads its workspace setting once."""
    if device.type != "cuda" or not config.deterministic:
        return
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", CUBLAS_WORKSPACE)
    torch.use_deterministic_algorithms(True)
    torch.backends.cudnn.deterministic = True
    torch.backends.cudnn.benchmark = False


def resume_warning(config: Config, device: torch.device) -> str | None:
    """What a resumed run on CUDA without `deterministic` must say: it continues from the
    checkpoint, but not as the uninterrupted run would have."""
    if device.type != "cuda" or config.deterministic:
        return None
    return (
        "dqnlab: warning: deterministic = false on CUDA: the resumed run continues from its "
        "checkpoint, but not bit for bit as it would have without the stop"
    )


def apply_threads(config: Config) -> int:
    """Set this process's PyTorch threads from `threads` (0: PyTorch's default count, set
    again explicitly); returns the count the run trains with.

    The count is always set through `torch.set_num_threads`, the default one too, because
    that call is also where PyTorch turns off MKL's own choice of thread count
    (`mkl_set_dynamic(false)`, ATen's ParallelOpenMP.cpp); a process that never calls it
    keeps MKL_DYNAMIC on, under which MKL may run a matrix product on fewer threads than
    asked, and a product split another way adds in another order. Intel's conditions for
    reproducible results ask for it off (oneMKL developer guide, "Reproducibility
    Conditions"). A run left at `threads = 0` therefore computes as one set to the same
    count. Until 2026-12-05 such runs kept MKL's choice on (checked: `mkl_serv_get_dynamic`
    1 before, 0 after). On the Xeon the count shows: the Nature network's 32 x 3136 by
    3136 x 512 product gives other bits at one thread than at two (2026-12-06). It was
    suspected of a Pong resume test's rare failure on a loaded Xeon, but MKL left on kept
    two threads' bits in 3,000 products under load; the cause found is MKL's vector math
    (`warm_up_vector_math`).

    Then every thread of the pool flushes denormals or not, as `flush_denormals` says
    (`denormals.py`), and makes its first calls to MKL's vector math
    (`warm_up_vector_math`)."""
    torch.set_num_threads(config.threads if config.threads > 0 else torch.get_num_threads())
    apply_denormals(config)
    warm_up_vector_math()
    return torch.get_num_threads()


def set_threads(count: int) -> None:
    """`torch.set_num_threads(count)`, and MKL's vector math warmed up where the calling
    thread's OpenMP pool grows past the threads already warmed (`warm_up_vector_math`):
    GNU's OpenMP keeps a pool's threads when it shrinks and reuses them when it grows
    again (checked by their thread ids), so only a new thread needs it."""
    torch.set_num_threads(count)
    if count > getattr(_warmed, "threads", 0):
        warm_up_vector_math()


def warm_up_vector_math() -> None:
    """Call each of MKL's vector math functions that PyTorch's CPU kernels use, once in
    every thread of the calling thread's OpenMP pool, and throw the results away.

    PyTorch computes sqrt, exp, log, the trigonometric functions, tanh and erf of a float
    tensor with MKL's vector math library (VML; checked on torch 2.15: the same bits as
    VML's high-accuracy mode), cutting it into pieces of `VECTOR_MATH_GRAIN` elements
    spread over the pool. On the Xeon (2026-12-06), under load, a pool thread's first
    such call sometimes returned square roots about 12 bits exact (relative errors up to
    3e-4, where the usual ones are within an ulp): the second half of a 3,136-element sqrt,
    the part the second thread computes, in 3 of 98 fresh processes beside two trainings
    (load about 6); the next call in the same process gave the usual bits, every time.
    With this warm-up first, none of 158 such processes; without, 9 of 159, alternating.
    The optimizers take a square root at every update (RMSProp, Adam), so the first update
    of a process could move the weights otherwise than in a process where that call went
    right: the likely cause of the Pong resume test that failed once in about twenty tries
    on a loaded Xeon, in the last bits of its losses, and the cause of the arithmetic
    fingerprint that a loaded resume found changed on the same machine (which is how it
    was found). So every process makes those first calls here, before it computes anything
    it keeps.
    """
    threads = torch.get_num_threads()
    # Half a piece: the calling thread alone. Two per thread: every thread one range.
    alone = torch.linspace(0.25, 0.75, VECTOR_MATH_GRAIN // 2)
    spread = torch.linspace(0.25, 0.75, 2 * VECTOR_MATH_GRAIN * threads)
    for name in VECTOR_MATH_FUNCTIONS:
        function = getattr(torch, name)
        function(alone)  # MKL's first call in the process, no other thread inside it
        function(spread)  # then the first call of each thread of the pool
    _warmed.threads = max(threads, getattr(_warmed, "threads", 0))


def resume_threads(config: Config, device: torch.device, trained_with: int | None) -> str | None:
    """Take back the thread count a checkpoint was written with (`trained_with`; None in
    checkpoints from before it was recorded), so that the CPU's arithmetic continues as
    it was; returns what the resume must say, if anything. A count the user set explicitly
    wins, with a warning that the run will not continue bit for bit."""
    now = torch.get_num_threads()
    if device.type != "cpu" or trained_with is None or trained_with == now:
        return None
    if config.threads == 0:
        set_threads(trained_with)
        return (
            f"dqnlab: resuming with the {trained_with} PyTorch thread(s) the run trained with "
            f"(this process had {now}): the CPU's arithmetic depends on the count"
        )
    return (
        f"dqnlab: warning: threads = {now} where the run trained with {trained_with}: the "
        "resumed run continues from its checkpoint, but not bit for bit (the CPU's "
        "arithmetic depends on the thread count)"
    )


def arithmetic_fingerprint() -> str:
    """A digest of what the update's arithmetic is made of, computed by this process at its
    thread count on fixed inputs: a convolution forward and its weight gradient (oneDNN), a
    matrix product (MKL), a reduction and an elementwise root (MKL's vector math). Equal
    where the libraries take the same code paths; a few milliseconds. The vector math is
    warmed up first, as a run does at its start, so that a process that computed nothing
    before gets the same digest (`warm_up_vector_math`)."""
    warm_up_vector_math()
    generator = torch.Generator().manual_seed(0)
    images = torch.rand(2, 4, 84, 84, generator=generator)
    kernel = (torch.rand(32, 4, 8, 8, generator=generator) - 0.5).requires_grad_()
    left = torch.rand(32, 3136, generator=generator)
    right = torch.rand(3136, 256, generator=generator)
    with torch.enable_grad():
        convolved = torch.nn.functional.conv2d(images, kernel, stride=4)
        convolved.square().sum().backward()
    digest = hashlib.sha256()
    for tensor in (convolved, kernel.grad, left @ right, left.sum(dim=1), torch.sqrt(left[0])):
        assert tensor is not None
        digest.update(tensor.detach().contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]


def resume_arithmetic(device: torch.device, recorded: str | None, now: str | None) -> str | None:
    """What a resume must say when this process's arithmetic (`now`) is not the one the
    checkpoint was written with (`recorded`; None in checkpoints from before it was
    recorded, and on a GPU, where `deterministic` decides)."""
    if device.type != "cpu" or recorded is None or now is None or recorded == now:
        return None
    return (
        "dqnlab: warning: this machine's float arithmetic is not the one the checkpoint was "
        f"written with (fingerprint {now}, the run's {recorded}: another processor, or other "
        "builds of PyTorch's libraries): the resumed run continues from its checkpoint, but "
        "not bit for bit as it would have there"
    )


def busy_cores_warning(threads: int, device: torch.device) -> str | None:
    """A warning when other processes already keep the cores busy and this training would
    add several threads to them: two trainings at once with two threads each on two cores
    ran tens of times slower than with one each (measured while building `num_envs`)."""
    if device.type != "cpu" or threads < 2 or not hasattr(os, "getloadavg"):
        return None
    load, cores = os.getloadavg()[0], usable_cores()
    if load < cores - 0.5:
        return None
    return (
        f"dqnlab: warning: the load average is {load:.1f} on {cores} cores before this run "
        f"starts: other processes keep them busy, and {threads} PyTorch threads competing "
        "with them can run many times slower; with another training beside it, give each "
        "--set threads=1"
    )


def usable_cores() -> int:
    """The cores this process may run on (its affinity where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1
