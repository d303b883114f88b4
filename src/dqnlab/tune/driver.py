"""A tune from start to end: the study opened (or carried on), its trials run in this
process or in `jobs` worker processes sharing the journal, then its outputs written.

With `jobs` > 1, the trials still to start are shared out among the workers before they
start (worker k runs its share, one PyTorch thread each unless `threads` is fixed), so
that the study ends with exactly the trials asked for; the stale trials of a killed tune
are carried on by this process first.
"""

from __future__ import annotations

import multiprocessing
from pathlib import Path

import optuna
import torch

from dqnlab.errors import DqnlabError
from dqnlab.tune.outputs import write_outputs
from dqnlab.tune.study import TunePlan, open_study
from dqnlab.tune.trials import run_trial, run_trials, stale_trials


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
    write_outputs(study, study_dir, command)
    return study


def shares(remaining: int, jobs: int) -> list[int]:
    """`remaining` trials shared out among `jobs` workers as evenly as can be (none idle
    for nothing: a worker with no share is not started)."""
    remaining = max(0, remaining)
    split = [remaining // jobs + (1 if k < remaining % jobs else 0) for k in range(jobs)]
    return [share for share in split if share > 0]


def _run_workers(study_dir: Path, plan: TunePlan, quota: list[int], device: torch.device) -> None:
    """One spawned process per share; a worker that fails stops the tune in one line
    (its trial stays RUNNING, carried on by the next tune)."""
    context = multiprocessing.get_context("spawn")  # no forked torch threads or locks
    workers = [
        context.Process(target=_worker, args=(study_dir, plan, share, str(device), k + 1))
        for k, share in enumerate(quota)
    ]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    failed = [k + 1 for k, worker in enumerate(workers) if worker.exitcode != 0]
    if failed:
        raise DqnlabError(
            f"tune job(s) {', '.join(map(str, failed))} stopped early; the same command "
            "carries the study on"
        )


def _worker(study_dir: Path, plan: TunePlan, share: int, device: str, job: int) -> None:
    """A job: `share` new trials on one PyTorch thread, its own sampler seed."""
    study = open_study(study_dir, plan, seed_offset=job)
    for _ in range(share):
        run_trial(study, study.ask(), study_dir, plan, torch.device(device), threads=1)
