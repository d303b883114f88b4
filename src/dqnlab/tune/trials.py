"""The trials of a study: each one a dqnlab run directory (or one per seed, with `seeds` >
1) trained as `dqnlab train` trains it, told its periodic evaluations to the pruner, and
its objective told to the study.

The objective is the mean score of the run's best periodic evaluation or of its last
(`TunePlan.objective`: by default the network the run's final evaluation plays,
`final_eval_network`, so that a study ranks settings by what their runs deliver: `classic`
keeps its best network; rl-baselines3-zoo, which plays the last, reports the last
evaluation's mean); with several seeds, the mean over them, trained one after the other. The
pruner sees the first seed's evaluations alone: Optuna's pruners hold a trial's best value
so far against the others' at the same step, so a good first seed would shield a bad
second one whatever steps it is reported at. A trial the pruner stops is stopped as a stop
request stops a run (a checkpoint, then the end) and recorded PRUNED with its last
evaluation's mean.

Resume: a trial left RUNNING by a tune that was killed is carried on where its run
stopped (its newest checkpoint, the same Optuna trial, the same settings) before any new
trial starts, so no trial is run twice and none is lost. A RUNNING trial whose run
directory another process trains now (its lease is live: a parallel job) is left to it.
"""

from __future__ import annotations

import dataclasses
import statistics
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
from dqnlab.tune.study import TunePlan, trial_run_dirs, trials_dir


class TuneStopped(DqnlabError):
    """SIGINT or SIGTERM stopped a trial's run after its checkpoint (with `--jobs`, one
    trial in each job): the tune stops too, and the same command carries it on."""

    def __init__(self, signal_name: str, *numbers: int) -> None:
        if len(numbers) == 1:
            where = f"trial {numbers[0]} after saving a checkpoint"
        else:
            listed = ", ".join(map(str, numbers[:-1])) + f" and {numbers[-1]}"
            where = f"trials {listed}, each after saving a checkpoint"
        super().__init__(
            f"stopped by {signal_name} in {where}; the same command carries the study on"
        )
        self.exit_status = 130 if signal_name == "SIGINT" else 143
        self.signal_name, self.numbers = signal_name, numbers


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
    return [trial for trial in running if not _trained_now(study_dir, trial.number)]


def _trained_now(study_dir: Path, number: int) -> bool:
    """Whether a process trains one of the trial's runs now (its lease is live)."""
    name = f"trial-{number:04d}"  # the trial's own runs: name, or name-sSEED
    runs = [trials_dir(study_dir) / name, *trials_dir(study_dir).glob(f"{name}-s*")]
    return any(lease_is_live(run) for run in runs)


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
    """Train one trial's runs, one seed after the other (each from its newest checkpoint if
    it has one; a seed whose value the trial recorded already is not trained again), report
    their evaluations to the pruner, and tell the study how the trial ended."""
    try:
        base = trial_config(plan, suggest(trial, plan.space, plan.steps), threads)
    except DqnlabError as error:
        return _failed(study, trial, error)
    seeds = [base.seed + k for k in range(plan.seeds)]
    trial.set_user_attr("seeds", seeds)
    values: list[float] = []
    runs = trial_run_dirs(study_dir, trial.number, seeds)
    for k, (seed, run_dir) in enumerate(zip(seeds, runs, strict=True)):
        done = trial.user_attrs.get(f"value_seed_{seed}")
        if done is None:
            config = dataclasses.replace(base, seed=seed)
            ended = _train_one(trial, run_dir, config, pruned=k == 0, device=device)
            if isinstance(ended, Exception):
                return _failed(study, trial, ended)
            if isinstance(ended, TrialState):
                study.tell(trial, state=ended)
                return ended
            done = _objective(ended, plan.objective)
            if plan.seeds > 1:
                trial.set_user_attr(f"value_seed_{seed}", done)
        values.append(done)
    study.tell(trial, statistics.fmean(values))
    return TrialState.COMPLETE


def _train_one(
    trial: optuna.trial.Trial, run_dir: Path, config: Config, pruned: bool, device: torch.device
) -> TrainResult | TrialState | DqnlabError:
    """One run of the trial: its result, PRUNED, or the error that failed it;
    its evaluations told to the pruner when `pruned`. A run directory that holds the run
    already (a killed tune's) is resumed with the settings it was started with."""
    try:
        if is_run_dir(run_dir):
            config, resume = load_run_config(run_dir), True
        else:
            resume = prepare_run_dir(run_dir, force=False, config=config)
    except DqnlabError as error:
        return error

    def report(step: int, mean: float) -> bool:
        trial.report(mean, step)
        return trial.should_prune()

    try:
        result = train(config, run_dir, device, progress=False, tensorboard=False,
                       resume=resume, on_evaluation=report if pruned else None)  # fmt: skip
    except DqnlabError as error:
        return error
    return _ended(trial, result)


def _ended(
    trial: optuna.trial.Trial, result: TrainResult
) -> TrainResult | TrialState | DqnlabError:
    if result.interrupted == STOPPED_BY_HOOK:
        return TrialState.PRUNED
    if result.interrupted is not None:
        raise TuneStopped(result.interrupted, trial.number)  # the trial stays RUNNING
    if not result.evaluations:
        return DqnlabError(
            f"no periodic evaluation ran in {result.steps} steps (replay_start_steps is "
            "past the last one): give more --steps or search a smaller replay start"
        )
    return result


def _objective(result: TrainResult, objective: str) -> float:
    """The run's value: its best periodic evaluation's mean, or its last one's."""
    means = [mean for _, mean in result.evaluations]
    return max(means) if objective == "best" else means[-1]


def _failed(study: optuna.Study, trial: optuna.trial.Trial, error: DqnlabError) -> TrialState:
    """A trial whose settings or run failed: recorded FAIL with the reason, the tune goes on."""
    trial.set_user_attr("error", str(error))
    study.tell(trial, state=TrialState.FAIL)
    return TrialState.FAIL
