"""A study of `dqnlab tune` on disk: every file name of a study directory, its study.json
(what the study searches: environment, preset, budget, fixed settings, space), and the
Optuna study in a journal file beside it, so that a killed tune carries on.

    STUDY_DIR/study.json            the plan; a tune with another one is refused
    STUDY_DIR/journal.log           Optuna's JournalStorage (a file with a lock beside it)
    STUDY_DIR/trials/trial-NNNN/    each trial: a dqnlab run directory (with --seeds K > 1,
                                    one per seed: trial-NNNN-sSEED)
    STUDY_DIR/best.toml             the best trial's settings as a preset (`outputs.py`)
    STUDY_DIR/trials.csv            one row per trial
    STUDY_DIR/history.png, importances.png   Optuna's figures
    STUDY_DIR/verify/, verify.csv   with --verify N: the check on new seeds (`verify.py`)
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import optuna
from optuna.distributions import BaseDistribution
from optuna.samplers import BaseSampler, TPESampler
from optuna.storages.journal import JournalFileBackend, JournalStorage
from optuna.trial import FrozenTrial, TrialState

from dqnlab.errors import DqnlabError
from dqnlab.tune.space import SearchEntry

STUDY_FILE = "study.json"
JOURNAL_FILE = "journal.log"
TRIALS_DIR = "trials"
BEST_FILE = "best.toml"
TRIALS_TABLE = "trials.csv"
HISTORY_FIGURE = "history.png"
IMPORTANCES_FIGURE = "importances.png"
STUDY_NAME = "dqnlab-tune"
# What must match for a study directory to be carried on (the trial count may grow).
PLAN_KEYS = (
    "env", "preset", "steps", "fixed", "space", "evaluations", "pruner", "seeds", "objective"
)  # fmt: skip
# What a study.json written before a key existed holds for it.
PLAN_DEFAULTS = {"seeds": 1, "objective": "last"}
OBJECTIVES = ("best", "last")


@dataclasses.dataclass(frozen=True)
class TunePlan:
    """What a study searches; every trial is the preset with `fixed`, then its own draw
    from `space`, trained for `steps` agent steps and evaluated `evaluations` times, on
    `seeds` run seeds (the preset's seed and the next ones), its objective their mean of
    `objective`: each run's best periodic evaluation's mean, or its last one's."""

    env: str
    preset: str
    steps: int
    space: tuple[SearchEntry, ...]
    fixed: dict[str, Any] = dataclasses.field(default_factory=dict)
    evaluations: int = 10
    pruner: str = "median"
    seed: int = 0  # the sampler's
    seeds: int = 1  # runs per trial
    objective: str = "last"  # OBJECTIVES

    def record(self) -> dict[str, Any]:
        """The plan as study.json holds it."""
        return {
            "env": self.env,
            "preset": self.preset,
            "steps": self.steps,
            "fixed": self.fixed,
            "space": {entry.name: entry.as_dict() for entry in self.space},
            "evaluations": self.evaluations,
            "pruner": self.pruner,
            "seeds": self.seeds,
            "objective": self.objective,
        }


def study_path(study_dir: Path, name: str) -> Path:
    """One of the study's own files (STUDY_FILE, BEST_FILE...)."""
    return study_dir / name


def trials_dir(study_dir: Path) -> Path:
    return study_dir / TRIALS_DIR


def trial_run_dir(study_dir: Path, number: int, seed: int | None = None) -> Path:
    """A trial's run directory: trial-NNNN, or trial-NNNN-sSEED for one of several seeds."""
    suffix = "" if seed is None else f"-s{seed}"
    return trials_dir(study_dir) / f"trial-{number:04d}{suffix}"


def trial_run_dirs(study_dir: Path, number: int, seeds: list[int]) -> list[Path]:
    """Each of a trial's runs: one seed alone in trial-NNNN, several in trial-NNNN-sSEED."""
    if len(seeds) == 1:
        return [trial_run_dir(study_dir, number)]
    return [trial_run_dir(study_dir, number, seed) for seed in seeds]


def recorded_objective(study_dir: Path) -> str | None:
    """The objective of the study `study_dir` holds (an older study's: the last
    evaluation), or None where it holds none that can be read."""
    try:
        saved = json.loads(study_path(study_dir, STUDY_FILE).read_text())
    except (OSError, ValueError):
        return None
    return str(saved.get("objective", PLAN_DEFAULTS["objective"]))


def check_study_dir(study_dir: Path, plan: TunePlan) -> bool:
    """Whether `study_dir` holds this plan's study (True: carry it on). One made for
    another plan, or a non-empty directory that is not a study, is refused in one line."""
    if study_dir.exists() and not study_dir.is_dir():
        raise DqnlabError(f"--study-dir {study_dir} exists and is not a directory")
    record_path = study_path(study_dir, STUDY_FILE)
    if not record_path.exists():
        if study_dir.exists() and any(study_dir.iterdir()):
            raise DqnlabError(
                f"--study-dir {study_dir} is not empty and holds no {STUDY_FILE}: "
                "choose an empty or new directory"
            )
        return False
    try:
        saved = json.loads(record_path.read_text())
    except (OSError, ValueError) as error:
        raise DqnlabError(f"{record_path} cannot be read: {error}") from None
    wanted = json.loads(json.dumps(plan.record()))  # as JSON reads it back (tuples: lists)
    differing = [key for key in PLAN_KEYS if saved.get(key, PLAN_DEFAULTS.get(key)) != wanted[key]]
    if differing:
        shown = ", ".join(f"{key} {saved.get(key)!r}" for key in differing if key != "space")
        shown = shown or "another search space"
        raise DqnlabError(
            f"--study-dir {study_dir} holds a study made for {shown} "
            f"(it differs in {', '.join(differing)}); choose another --study-dir"
        )
    return True


class TrialSeededSampler(BaseSampler):
    """Optuna's TPE sampler whose random draws for trial N come from a stream seeded by
    (seed, N) alone: a study carried on by a new process draws what the one left alone
    would have, and never a finished trial's settings again.

    One `TPESampler(seed=...)` for the whole study, as the tune had until 2026-12-05, is
    seeded anew in every process: a tune stopped in trial 4 and carried on drew trials
    5 to 9 with the settings of trials 0 to 4 (its random start-up draws replayed, found in
    the Acrobot-v1 study), five of twenty trials spent on repeats. TPE itself keeps no state
    between trials but its random stream (its model is rebuilt from the study's finished
    trials at every draw), so a fresh one per trial loses nothing. Trials run by several
    jobs at once have distinct numbers, so distinct streams too."""

    def __init__(self, seed: int) -> None:
        self.seed = seed
        self._current: tuple[int, TPESampler] | None = None  # the trial drawing now, its TPE

    def _for(self, trial: FrozenTrial) -> TPESampler:
        if self._current is None or self._current[0] != trial.number:
            stream = np.random.SeedSequence([self.seed, trial.number]).generate_state(1)[0]
            self._current = (trial.number, TPESampler(seed=int(stream)))
        return self._current[1]

    def infer_relative_search_space(
        self, study: optuna.Study, trial: FrozenTrial
    ) -> dict[str, BaseDistribution]:
        return self._for(trial).infer_relative_search_space(study, trial)

    def sample_relative(
        self, study: optuna.Study, trial: FrozenTrial, search_space: dict[str, BaseDistribution]
    ) -> dict[str, Any]:
        return self._for(trial).sample_relative(study, trial, search_space)

    def sample_independent(
        self,
        study: optuna.Study,
        trial: FrozenTrial,
        param_name: str,
        param_distribution: BaseDistribution,
    ) -> Any:
        return self._for(trial).sample_independent(study, trial, param_name, param_distribution)

    def before_trial(self, study: optuna.Study, trial: FrozenTrial) -> None:
        self._for(trial).before_trial(study, trial)

    def after_trial(
        self,
        study: optuna.Study,
        trial: FrozenTrial,
        state: TrialState,
        values: Sequence[float] | None,
    ) -> None:
        self._for(trial).after_trial(study, trial, state, values)


def open_study(study_dir: Path, plan: TunePlan) -> optuna.Study:
    """The study in `study_dir` (created with its study.json if new), with the plan's
    pruner and TPE drawing each trial from a stream of the plan's seed and the trial's
    number (`TrialSeededSampler`)."""
    if not check_study_dir(study_dir, plan):
        study_dir.mkdir(parents=True, exist_ok=True)
        path = study_path(study_dir, STUDY_FILE)
        partial = path.with_suffix(".json.partial")
        partial.write_text(json.dumps(plan.record(), indent=2) + "\n")
        partial.replace(path)  # whole or not at all
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    storage = JournalStorage(JournalFileBackend(str(study_path(study_dir, JOURNAL_FILE))))
    return optuna.create_study(
        study_name=STUDY_NAME,
        storage=storage,
        direction="maximize",
        sampler=TrialSeededSampler(plan.seed),
        pruner=make_pruner(plan),
        load_if_exists=True,
    )


def make_pruner(plan: TunePlan) -> optuna.pruners.BasePruner:
    """`median` (rl-baselines3-zoo's: no pruning in the first 5 trials nor in the first
    third of a trial's evaluations) or `none`."""
    if plan.pruner == "none":
        return optuna.pruners.NopPruner()
    warmup_steps = plan.steps // 3
    return optuna.pruners.MedianPruner(n_startup_trials=5, n_warmup_steps=warmup_steps)
