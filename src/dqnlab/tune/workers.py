"""Work shared out among spawned worker processes, one PyTorch thread each: the trials of
`dqnlab tune --jobs J` and the runs of its check (`--verify N --jobs J`).

Each worker is given its share before it starts. Ctrl-C (SIGINT to the process group) or
SIGTERM stops each worker's run after its checkpoint; the worker reports what it stopped
in, and this process, which leaves the signals to the workers while they run, waits for
them all before it says so.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import signal
from collections.abc import Callable, Iterator
from typing import Any

from dqnlab.errors import DqnlabError

# A worker's exit status after a signal stopped its run at a checkpoint.
STOPPED = 3


def shares(remaining: int, jobs: int) -> list[int]:
    """`remaining` pieces of work shared out among `jobs` workers as evenly as can be (none
    idle for nothing: a worker with no share is not started)."""
    remaining = max(0, remaining)
    split = [remaining // jobs + (1 if k < remaining % jobs else 0) for k in range(jobs)]
    return [share for share in split if share > 0]


def run_workers(
    target: Callable[..., None], arguments: list[tuple[Any, ...]], carried_on: str
) -> list[tuple[str, Any]]:
    """`target(*arguments[k], stops)` in spawned process k, for each k; returns what the
    workers a signal stopped put in `stops` (the signal's name, where it stopped), in the
    order they stopped. A worker that fails otherwise is one line naming it: the same
    command carries `carried_on` on."""
    context = multiprocessing.get_context("spawn")  # no forked torch threads or locks
    stops = context.SimpleQueue()
    workers = [context.Process(target=target, args=(*args, stops)) for args in arguments]
    for worker in workers:
        worker.start()
    with _signals_left_to_workers():
        for worker in workers:
            worker.join()
    stopped = []
    while not stops.empty():
        stopped.append(stops.get())
    failed = [k + 1 for k, worker in enumerate(workers) if worker.exitcode not in (0, STOPPED)]
    if failed:
        raise DqnlabError(
            f"{carried_on} job(s) {', '.join(map(str, failed))} stopped early; the same "
            f"command carries the {carried_on} on"
        )
    return stopped


@contextlib.contextmanager
def _signals_left_to_workers() -> Iterator[None]:
    """While the workers run, Ctrl-C and SIGTERM are theirs to handle (each stops its run
    after a checkpoint); this process waits for them rather than stopping first."""
    previous = {number: signal.signal(number, signal.SIG_IGN)
                for number in (signal.SIGINT, signal.SIGTERM)}  # fmt: skip
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
