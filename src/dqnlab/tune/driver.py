"""A tune from start to end: the study opened (or carried on), its trials run in this
process or in `jobs` worker processes sharing the journal, then its outputs written.

With `jobs` > 1, the trials still to start are shared out among the workers before they
start (worker k runs its share, one PyTorch thread each unless `threads` is fixed), so
that the study ends with exactly the trials asked for; the stale trials of a killed tune
are carried on by this process first. Ctrl-C (SIGINT to the process group) or SIGTERM
stops each worker's trial after its checkpoint; this process waits for them and says so
in one line.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import signal
import sys
from collections.abc import Iterator
from multiprocessing.queues import SimpleQueue
from pathlib import Path

import optuna
import torch

from dqnlab.errors import DqnlabError
from dqnlab.tune.outputs import write_outputs
from dqnlab.tune.study import TunePlan, open_study
from dqnlab.tune.trials import TuneStopped, run_trial, run_trials, stale_trials


def tune(
    study_dir: Path,
    plan: TunePlan,
    trials: int,
    device: torch.device,
    command: str,
    jobs: int = 1,
) -> optuna.Study:
    """Run the study in `study_dir` until it holds `trials` trials; write its outputs."""
    if trials < 1:
        raise DqnlabError(f"--trials {trials}: a study needs at least one trial")
    if jobs < 1:
        raise DqnlabError(f"--jobs {jobs}: at least one")
    study = open_study(study_dir, plan)
    if jobs == 1:
        run_trials(study, study_dir, plan, trials, device)
    else:
        for frozen in stale_trials(study, study_dir):
            run_trial(study, optuna.trial.Trial(study, frozen._trial_id), study_dir, plan, device)
        _run_workers(study_dir, plan, shares(trials - len(study.get_trials()), jobs), device)
    write_outputs(study, study_dir, command, plan.objective)
    return study


def shares(remaining: int, jobs: int) -> list[int]:
    """`remaining` trials shared out among `jobs` workers as evenly as can be (none idle
    for nothing: a worker with no share is not started)."""
    remaining = max(0, remaining)
    split = [remaining // jobs + (1 if k < remaining % jobs else 0) for k in range(jobs)]
    return [share for share in split if share > 0]


def _run_workers(study_dir: Path, plan: TunePlan, quota: list[int], device: torch.device) -> None:
    """One spawned process per share. A worker stopped by a signal after its checkpoint
    tells this process, which then stops in one line with every stopped trial's number;
    a worker that fails otherwise stops the tune in one line too (its trial stays RUNNING,
    carried on by the next tune)."""
    context = multiprocessing.get_context("spawn")  # no forked torch threads or locks
    stops: SimpleQueue = context.SimpleQueue()
    workers = [
        context.Process(target=_worker, args=(study_dir, plan, share, str(device), stops))
        for share in quota
    ]
    for worker in workers:
        worker.start()
    with _signals_left_to_workers():
        for worker in workers:
            worker.join()
    stopped: list[tuple[str, int]] = []
    while not stops.empty():
        stopped.append(stops.get())
    failed = [k + 1 for k, worker in enumerate(workers) if worker.exitcode not in (0, _STOPPED)]
    if failed:
        raise DqnlabError(
            f"tune job(s) {', '.join(map(str, failed))} stopped early; the same command "
            "carries the study on"
        )
    if stopped:  # the exit status of the first job's signal
        raise TuneStopped(stopped[0][0], *sorted(number for _, number in stopped))


_STOPPED = 3  # a worker's exit status after a signal stopped its trial at a checkpoint


@contextlib.contextmanager
def _signals_left_to_workers() -> Iterator[None]:
    """While the workers run, Ctrl-C and SIGTERM are theirs to handle (each stops its trial
    after a checkpoint); this process waits for them rather than stopping first."""
    previous = {number: signal.signal(number, signal.SIG_IGN)
                for number in (signal.SIGINT, signal.SIGTERM)}  # fmt: skip
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def _worker(study_dir: Path, plan: TunePlan, share: int, device: str, stops: SimpleQueue) -> None:
    """A job: `share` new trials on one PyTorch thread (each drawn from its own number's
    stream). A signal stops it after its trial's checkpoint, which it tells the tune's
    process."""
    study = open_study(study_dir, plan)
    try:
        for _ in range(share):
            run_trial(study, study.ask(), study_dir, plan, torch.device(device), threads=1)
    except TuneStopped as stop:
        stops.put((stop.signal_name, stop.numbers[0]))
        sys.exit(_STOPPED)
