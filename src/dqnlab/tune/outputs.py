"""What a study leaves besides its trials: the best trial's settings as a preset file
(best.toml, which `dqnlab train --preset best.toml` takes), a table of the trials
(trials.csv) and Optuna's own figures (optimisation history, parameter importances)."""

from __future__ import annotations

import csv
import dataclasses
import datetime
import json
import warnings
from pathlib import Path

import optuna
from optuna.trial import TrialState

from dqnlab.config import Config, toml_value
from dqnlab.run.rundir import load_run_config
from dqnlab.tune.study import (
    BEST_FILE,
    HISTORY_FIGURE,
    IMPORTANCES_FIGURE,
    TRIALS_TABLE,
    study_path,
    trial_run_dirs,
)

# Left out of best.toml: the environment is the command's (`--env`), as in every preset, and
# the preset a run started from is recorded by the run that loads this one.
NOT_IN_PRESET = ("env", "preset")
# Written at their defaults whatever the trials ran with: how the machine runs a training, not
# what it learns (a study runs one PyTorch thread per trial; a user's GPU machine wants its own).
MACHINE_SETTINGS = ("threads",)


def write_outputs(
    study: optuna.Study, study_dir: Path, command: str, objective: str = "last"
) -> list[Path]:
    """trials.csv, best.toml (when a trial completed) and the figures; the paths written.
    `objective`: the plan's, named in best.toml's header."""
    written = [write_trials_table(study, study_dir)]
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    if complete:
        written.append(write_best_preset(study, study_dir, command, objective))
    written += write_figures(study, study_dir)
    return written


def write_trials_table(study: optuna.Study, study_dir: Path) -> Path:
    """One row per trial: number, state, value (with several seeds, their mean, and each
    seed's in seed_values), duration and each searched setting."""
    trials = study.get_trials(deepcopy=False)
    names = sorted({name for trial in trials for name in trial.params})
    path = study_path(study_dir, TRIALS_TABLE)
    partial = path.with_suffix(".csv.partial")
    with partial.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(
            ["number", "state", "value", "seed_values", "duration_seconds", *names, "error"]
        )
        for trial in trials:
            duration = trial.duration.total_seconds() if trial.duration is not None else ""
            writer.writerow(
                [trial.number, trial.state.name, "" if trial.value is None else trial.value,
                 _seed_values(trial), duration, *(trial.params.get(name, "") for name in names),
                 trial.user_attrs.get("error", "")]
            )  # fmt: skip
    partial.replace(path)
    return path


def _seed_values(trial: optuna.trial.FrozenTrial) -> str:
    """SEED:VALUE;... for the seeds of a trial of several that finished, else empty."""
    seeds = trial.user_attrs.get("seeds") or []
    values = {seed: trial.user_attrs.get(f"value_seed_{seed}") for seed in seeds}
    return ";".join(f"{seed}:{value:.6g}" for seed, value in values.items() if value is not None)


def write_best_preset(
    study: optuna.Study, study_dir: Path, command: str, objective: str = "last"
) -> Path:
    """The best complete trial's settings as its run resolved them (config.toml), every
    setting but the environment, with the study's command and the date in a header."""
    best = study.best_trial
    seeds = best.user_attrs.get("seeds")  # a study of one seed per trial may not record it
    config = load_run_config(trial_run_dirs(study_dir, best.number, seeds or [0])[0])
    path = study_path(study_dir, BEST_FILE)
    partial = path.with_suffix(".toml.partial")
    partial.write_text(preset_text(config, best, command, objective))
    partial.replace(path)
    return path


def preset_text(
    config: Config, best: optuna.trial.FrozenTrial, command: str, objective: str = "last"
) -> str:
    """A preset file of `config`, each line with its setting's doc, the searched ones
    marked; its header names the trial, its objective, the command and the date."""
    today = datetime.date.today().isoformat()
    lines = [
        f"# The best trial of a dqnlab tune study: trial {best.number}, whose {objective} "
        f"periodic evaluation's mean was {best.value:.4g}.",
        f"# Study: {command}",
        f"# Date: {today}. Train with it: dqnlab train --env ENV --preset {BEST_FILE}",
        f"# Searched: {json.dumps(best.params)}",
    ]
    for field in dataclasses.fields(Config):
        if field.name in NOT_IN_PRESET:
            continue
        searched = "  (searched)" if field.name in best.params else ""
        value = getattr(config, field.name)
        if field.name in MACHINE_SETTINGS and value != field.default:
            searched = f"  (the study's trials ran with {toml_value(value)}: a machine setting)"
            value = field.default
        lines.append(f"{field.name} = {toml_value(value)}  # {field.metadata['doc']}{searched}")
    return "\n".join(lines) + "\n"


def write_figures(study: optuna.Study, study_dir: Path) -> list[Path]:
    """Optuna's optimisation history and parameter importances (PED-ANOVA: it needs two
    complete trials and a parameter that varies), as PNG files; each one is skipped,
    without an error, where Optuna cannot draw it for this study."""
    import matplotlib
    import matplotlib.figure

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from optuna.importance import PedAnovaImportanceEvaluator
    from optuna.visualization import matplotlib as optuna_plots

    figures = {
        HISTORY_FIGURE: optuna_plots.plot_optimization_history,
        # PED-ANOVA: Optuna's default (fANOVA) needs scikit-learn, which dqnlab does not.
        IMPORTANCES_FIGURE: lambda study: optuna_plots.plot_param_importances(
            study, evaluator=PedAnovaImportanceEvaluator()
        ),
    }
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    written = []
    for name, plot in figures.items():
        if name == IMPORTANCES_FIGURE and len(complete) < 2:
            continue
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # ExperimentalWarning: the plots' API
                axes = plot(study)
        except (ValueError, RuntimeError):
            continue  # e.g. importances where no searched setting varied
        path = study_path(study_dir, name)
        figure = axes.figure  # get_figure(root=True) is matplotlib 3.10's; dqnlab allows 3.7
        assert isinstance(figure, matplotlib.figure.Figure)
        figure.savefig(path, dpi=120, bbox_inches="tight")
        plt.close(figure)
        written.append(path)
    return written
