"""A tune from start to end: the study opened (or carried on), its trials run in this
process or in `jobs` worker processes sharing the journal, then its outputs written.

With `jobs` > 1, the trials still to start are shared out among the workers before they
start (worker k runs its share, one PyTorch thread each unless `threads` is fixed;
`workers.py`), so that the study ends with exactly the trials asked for; the stale trials
of a killed tune are carried on by this process first. Ctrl-C (SIGINT to the process
group) or SIGTERM stops each worker's trial after its checkpoint; this process waits for
them and says so in one line.
"""

from __future__ import annotations

import sys
from multiprocessing.queues import SimpleQueue
from pathlib import Path

import optuna
import torch

from dqnlab.errors import DqnlabError
from dqnlab.tune.outputs import write_outputs
from dqnlab.tune.study import TunePlan, open_study
from dqnlab.tune.trials import TuneStopped, run_trial, run_trials, stale_trials
from dqnlab.tune.workers import STOPPED, run_workers, shares


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


def _run_workers(study_dir: Path, plan: TunePlan, quota: list[int], device: torch.device) -> None:
    """One spawned process per share (`workers.py`). Workers a signal stopped after their
    checkpoints stop the tune in one line with every stopped trial's number; a worker that
    failed otherwise stops it too (its trial stays RUNNING, carried on by the next tune)."""
    arguments = [(study_dir, plan, share, str(device)) for share in quota]
    stopped = run_workers(_worker, arguments, carried_on="study")
    if stopped:  # the exit status of the first job's signal
        raise TuneStopped(stopped[0][0], *sorted(number for _, number in stopped))


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
        sys.exit(STOPPED)
