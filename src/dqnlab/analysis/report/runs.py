"""The runs of a report: found (a run, or a sweep of runs), read (its settings, its
periodic and final evaluations) and grouped into configurations, the seeds of each.

Reading only: nothing here writes a file or plays a game.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dqnlab.config import (
    FIELD_NAMES,
    RESUMABLE_CHANGES,
    Config,
    preset_names,
    resolve_config,
    setting_text,
)
from dqnlab.errors import DqnlabError
from dqnlab.run import exported, rundir
from dqnlab.run.logs import read_csv

# Settings that never define a configuration: the seed (the runs of a configuration are
# its seeds), the settings that do not change what is learned, those a run may resume
# with (total_steps only stops the same run earlier or later; the table shows it), and
# the number of final-evaluation games (a sample size, also in the table).
NOT_GROUPED = ("seed", *RESUMABLE_CHANGES, "final_eval_episodes")
ALL_EQUAL = "all settings equal"
# Configurations that differ in more settings than this are named by their preset, when
# each is one (a variant of the DQN family against nature, say): "preset=rainbow".
MAX_LABEL_SETTINGS = 3


# Runs ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class PeriodicEvaluation:
    """One row of a run's `evaluations.csv`."""

    step: int
    frames: int  # training emulator frames at `step`
    mean: float  # mean score of the games finished within the budget (0 if none)
    episodes: int
    # Nature Fig. 2 (algorithm/heldout.py): None in runs of an older dqnlab, or before
    # the held-out transitions were drawn.
    heldout_max_q: float | None = None
    heldout_td_error: float | None = None


@dataclass
class RunResults:
    """What the report reads from one run directory."""

    run_dir: Path
    config: Config
    evaluations: list[PeriodicEvaluation]
    final_evaluation: dict[str, Any] | None  # final_evaluation.json's record
    steps: int = 0  # agent steps of its newest checkpoint (last.pt), 0 before the first

    @property
    def finished(self) -> bool:
        """Trained its whole budget (`total_steps`)."""
        return self.steps >= self.config.total_steps


def find_runs(paths: Sequence[Path]) -> list[Path]:
    """The run directories named by `paths`: a run itself, or a sweep directory whose
    subdirectories (one level down) are runs, in natural order (s2 before s10)."""
    found: list[Path] = []
    for path in paths:
        if rundir.is_run_dir(path):
            found.append(path)
        elif path.is_dir():
            children = [child for child in path.iterdir() if rundir.is_run_dir(child)]
            if not children:
                raise DqnlabError(
                    f"{path} is neither a dqnlab run directory (no {rundir.CONFIG_FILE}) nor a "
                    "directory of runs (none of its subdirectories has one)"
                )
            found.extend(sorted(children, key=lambda child: _natural_key(child.name)))
        else:
            raise DqnlabError(f"{path} is not a directory: pass run or sweep directories")
    unique: dict[Path, Path] = {}
    for path in found:
        unique.setdefault(path.resolve(), path)
    return list(unique.values())


def _natural_key(name: str) -> list[Any]:
    return [int(piece) if piece.isdigit() else piece for piece in re.split(r"(\d+)", name)]


def load_run(run_dir: Path) -> RunResults:
    config = rundir.load_run_config(run_dir)
    evaluations = []
    path = rundir.evaluations_path(run_dir)
    for row in read_csv(path) if path.is_file() else []:
        try:
            evaluations.append(
                PeriodicEvaluation(
                    int(row["step"]),
                    int(row["frames"]),
                    float(row["mean"]),
                    int(row["episodes"]),
                    _optional_number(row.get("heldout_max_q")),
                    _optional_number(row.get("heldout_td_error")),
                )
            )
        except (TypeError, ValueError):  # a line torn by a killed run: fields missing
            continue
    steps = _trained_steps(run_dir)
    return RunResults(run_dir, config, evaluations, rundir.load_final_evaluation(run_dir), steps)


def _trained_steps(run_dir: Path) -> int:
    """Agent steps of a run's newest checkpoint; for an exported folder, of the run's when
    it was exported (results.json's `trained_steps`; an older export has none: then the
    network's own step, the least the run had trained); for a run whose checkpoints are
    gone (its small files kept, as docs/ keeps a benchmark's), the step of the network its
    final evaluation played, likewise the least it had trained."""
    if not exported.is_exported_dir(run_dir):
        step = rundir.network_step(run_dir, "last")
        if step is None:
            step = (rundir.load_final_evaluation(run_dir) or {}).get("checkpoint_step")
        return int(step or 0)
    results = rundir.read_json_file(run_dir / exported.RESULTS_FILE) or {}
    if results.get("trained_steps") is not None:
        return int(results["trained_steps"])
    step = exported.read_description(exported.network_path(run_dir)).get("step")
    return int(step) if step is not None else 0


def _optional_number(text: str | None) -> float | None:
    return float(text) if text else None


# Grouping ------------------------------------------------------------------------------


@dataclass
class Group:
    """The runs of one game with the same configuration: its seeds."""

    env: str
    label: str  # "life_loss_terminal=false", or ALL_EQUAL
    settings: dict[str, Any]  # the settings in the label and their values here
    runs: list[RunResults] = field(default_factory=list)


def label_keys(runs: Sequence[RunResults]) -> list[str]:
    """The settings that differ between runs of the same game, in `Config` order.

    Runs of different games are never compared with each other: a setting that differs
    only between games (a per-game budget, say) does not label anything. A setting that
    differs within any one game labels the runs of every game, so that configurations
    are named alike across games and the summary across games can match them."""
    by_env: dict[str, list[dict[str, Any]]] = {}
    for run in runs:
        by_env.setdefault(run.config.env, []).append(_flat_settings(run.config))
    names = _flat_names(values for settings in by_env.values() for values in settings)
    differing = set()
    for settings in by_env.values():
        for name in names:
            grouped = name != "env" and name not in NOT_GROUPED
            if grouped and len({repr(values.get(name)) for values in settings}) > 1:
                differing.add(name)
    return [name for name in names if name in differing]


def _flat_settings(config: Config) -> dict[str, Any]:
    """`config.to_dict()` with the parts' own settings as `parts.PART.NAME` keys, so that a
    label names the one that differs (`parts.loss.tau=0.01`), not the whole table."""
    values = config.to_dict()
    for setting, table in values.pop("parts").items():
        for name, value in table.items():
            values[f"parts.{setting}.{name}"] = value
    return values


def _flat_names(settings: Iterable[dict[str, Any]]) -> list[str]:
    """Every setting's name in `Config` order, the parts' own settings where `parts` is."""
    dotted = sorted({name for values in settings for name in values if name.startswith("parts.")})
    names: list[str] = []
    for name in FIELD_NAMES:
        names += dotted if name == "parts" else [name]
    return names


def matching_preset(config: Config) -> str | None:
    """The shipped preset `config` is, on every setting that defines a configuration (all
    but `NOT_GROUPED`), or None."""
    values = config.to_dict()
    environment = {  # what the environment is, as `env`: no preset sets them
        key: getattr(config, key) for key in ("env_kwargs", "env_wrappers", "observation_images")
    }
    for name in preset_names():
        # At the run's budget: budget-scaled settings (epsilon_decay_fraction) as the run's.
        resolved = resolve_config(
            name, env=config.env, total_steps=config.total_steps, **environment
        )
        preset = resolved.to_dict()
        if all(values[k] == preset[k] for k in FIELD_NAMES if k not in NOT_GROUPED):
            return name
    return None


def group_runs(runs: Sequence[RunResults]) -> list[Group]:
    """Groups by game, then by the values of `label_keys`, in order of first appearance;
    named by those settings, or by their presets where more than `MAX_LABEL_SETTINGS`
    differ and every run is one of the shipped presets."""
    keys = label_keys(runs)
    presets: dict[Path, str | None] = {}
    if len(keys) > MAX_LABEL_SETTINGS:
        presets = {run.run_dir: matching_preset(run.config) for run in runs}
        if None in presets.values():
            presets = {}
    groups: dict[tuple[str, str], Group] = {}
    for run in runs:
        values = _flat_settings(run.config)
        settings = {key: values.get(key) for key in keys}
        label = ", ".join(f"{k}={setting_text(v)}" for k, v in settings.items()) or ALL_EQUAL
        if presets:
            label = f"preset={presets[run.run_dir]}"
        group = groups.setdefault((run.config.env, label), Group(run.config.env, label, settings))
        group.runs.append(run)
    return list(groups.values())
