"""The trials of a study: each one a dqnlab run directory trained as `dqnlab train` trains
it, told its periodic evaluations to the pruner, and its objective told to the study.

The objective is the mean score of the run's last periodic evaluation (what
rl-baselines3-zoo reports: the last evaluation's mean, not the best one, which would favour
lucky peaks). A trial the pruner stops is stopped as a stop request stops a run (a
checkpoint, then the end) and recorded PRUNED with its last evaluation's mean.

Resume: a trial left RUNNING by a tune that was killed is carried on where its run
stopped (its newest checkpoint, the same Optuna trial, the same settings) before any new
trial starts, so no trial is run twice and none is lost. A RUNNING trial whose run
directory another process trains now (its lease is live: a parallel job) is left to it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import optuna
import torch
from optuna.trial import TrialState

from dqnlab.config import Config, resolve_config
from dqnlab.errors import DqnlabError
from dqnlab.run.lease import lease_is_live
from dqnlab.run.rundir import is_run_dir, load_run_config, prepare_run_dir
from dqnlab.run.train import STOPPED_BY_HOOK, TrainResult, train
from dqnlab.tune.space import suggest
from dqnlab.tune.study import TunePlan, trial_run_dir


class TuneStopped(DqnlabError):
    """SIGINT or SIGTERM stopped a trial's run after its checkpoint: the tune stops too,
    and the same command carries it on."""

    def __init__(self, signal_name: str, number: int) -> None:
        super().__init__(
            f"stopped by {signal_name} in trial {number} after saving a checkpoint; "
            "the same command carries the study on"
        )
        self.exit_status = 130 if signal_name == "SIGINT" else 143


def trial_config(plan: TunePlan, overrides: dict[str, Any], threads: int | None) -> Config:
    """A trial's settings: the preset, the plan's fixed settings, the trial's draw, the
    study's budget; evaluated `plan.evaluations` times unless eval_period_steps is fixed."""
    values: dict[str, Any] = {"eval_period_steps": max(1, plan.steps // plan.evaluations)}
    if threads is not None and "threads" not in plan.fixed:
        values["threads"] = threads
    values.update(plan.fixed)
    values.update(overrides)
    return resolve_config(plan.preset, values, env=plan.env, total_steps=plan.steps)


def stale_trials(study: optuna.Study, study_dir: Path) -> list[optuna.trial.FrozenTrial]:
    """RUNNING trials no process trains now: left so by a tune that was killed."""
    running = study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
    return [t for t in running if not lease_is_live(trial_run_dir(study_dir, t.number))]


def run_trials(
    study: optuna.Study,
    study_dir: Path,
    plan: TunePlan,
    trials: int,
    device: torch.device,
    threads: int | None = None,
) -> int:
    """Carry on the stale trials, then start new ones until the study holds `trials`
    trials (any state); returns how many ran in this call."""
    ran = 0
    for frozen in stale_trials(study, study_dir):
        run_trial(study, optuna.trial.Trial(study, frozen._trial_id), study_dir, plan, device,
                  threads)  # fmt: skip
        ran += 1
    while len(study.get_trials(deepcopy=False)) < trials:
        run_trial(study, study.ask(), study_dir, plan, device, threads)
        ran += 1
    return ran


def run_trial(
    study: optuna.Study,
    trial: optuna.trial.Trial,
    study_dir: Path,
    plan: TunePlan,
    device: torch.device,
    threads: int | None = None,
) -> TrialState:
    """Train one trial's run (from its newest checkpoint if it has one), report its
    evaluations to the pruner, and tell the study how it ended."""
    run_dir = trial_run_dir(study_dir, trial.number)
    try:
        config, resume = _prepared_run(trial, run_dir, plan, threads)
    except DqnlabError as error:
        return _failed(study, trial, error)

    def report(step: int, mean: float) -> bool:
        trial.report(mean, step)
        return trial.should_prune()

    try:
        result = train(config, run_dir, device, progress=False, tensorboard=False,
                       resume=resume, on_evaluation=report)  # fmt: skip
    except DqnlabError as error:
        return _failed(study, trial, error)
    return _told(study, trial, result)


def _prepared_run(
    trial: optuna.trial.Trial, run_dir: Path, plan: TunePlan, threads: int | None
) -> tuple[Config, bool]:
    """The trial's settings and whether its run is carried on: a run directory that holds
    a run already (a killed tune's) is resumed with the settings it was started with."""
    if is_run_dir(run_dir):
        config = load_run_config(run_dir)
        return config, True
    config = trial_config(plan, suggest(trial, plan.space, plan.steps), threads)
    return config, prepare_run_dir(run_dir, force=False, config=config)


def _told(study: optuna.Study, trial: optuna.trial.Trial, result: TrainResult) -> TrialState:
    if result.interrupted == STOPPED_BY_HOOK:
        study.tell(trial, state=TrialState.PRUNED)
        return TrialState.PRUNED
    if result.interrupted is not None:
        raise TuneStopped(result.interrupted, trial.number)  # the trial stays RUNNING
    if not result.evaluations:
        error = DqnlabError(
            f"no periodic evaluation ran in {result.steps} steps (replay_start_steps is "
            "past the last one): give more --steps or search a smaller replay start"
        )
        return _failed(study, trial, error)
    study.tell(trial, result.evaluations[-1][1])
    return TrialState.COMPLETE


def _failed(study: optuna.Study, trial: optuna.trial.Trial, error: DqnlabError) -> TrialState:
    """A trial whose settings or run failed: recorded FAIL with the reason, the tune goes on."""
    trial.set_user_attr("error", str(error))
    study.tell(trial, state=TrialState.FAIL)
    return TrialState.FAIL
