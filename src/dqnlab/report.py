"""Reports: the results table and the learning curves of a set of runs.

`dqnlab report RUN_DIR...` reads each run's final evaluation (`final_evaluation.json`,
played now with the run's best network where it is missing or older than that network)
and its periodic evaluations (`evaluations.csv`). The runs of one game are grouped by the
settings that differ between them: runs whose settings differ only in `seed` (and in
settings that do not change what is learned) are the seeds of one configuration. It
writes into the output directory:

- `results.md`: the table, the scores across games, the figures, a legend and notes;
- `results.csv`: one row per game and configuration, numbers in their own columns;
- `summary.csv`: median and mean human-normalised score across games (2 games or more);
- `curves-GAME.png` and `.svg`: periodic-evaluation score against training steps.

The human-normalised score is 100 × (score − random) / (human − random), given with two
human baselines (`data/README.md`): dqn_zoo's, the set DeepMind's later code uses, and
the Nature paper's own (Extended Data Table 2). They differ for 34 of the 49 games, so
only scores normalised by the same baseline can be compared.
"""

from __future__ import annotations

import csv
import io
import re
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from dqnlab import rundir
from dqnlab.config import (
    DEFAULT_EVALUATION_SEED,
    FIELD_NAMES,
    RESUMABLE_CHANGES,
    Config,
    setting_text,
)
from dqnlab.errors import DqnlabError
from dqnlab.evaluate import final_evaluation, final_evaluation_record
from dqnlab.logs import read_csv

if TYPE_CHECKING:
    import torch

    from dqnlab.inspection import Inspection

# Roderick, MacGlashan and Tellex 2017, "Implementing the Deep Q-Network", Table 1: their
# own implementation's mean score (± s.d.) over 30 games of the best network, Nature's
# final protocol. The only games they report.
SEED_PAPER_SCORES: dict[str, tuple[float, float]] = {
    "pong": (19.7, 1.1),
    "breakout": (339.3, 86.1),
    "seaquest": (6309.0, 1027.0),
}

# Settings that never define a configuration: the seed (the runs of a configuration are
# its seeds), the settings that do not change what is learned, those a run may resume
# with (total_steps only stops the same run earlier or later; the table shows it), and
# the number of final-evaluation games (a sample size, also in the table).
NOT_GROUPED = ("seed", *RESUMABLE_CHANGES, "final_eval_episodes")
ALL_EQUAL = "all settings equal"
BASELINES = ("human", "human_nature")
RESULTS_MD, RESULTS_CSV, SUMMARY_CSV = "results.md", "results.csv", "summary.csv"
Q_VALUES_DIR = "q-values"


# Reference scores ----------------------------------------------------------------------


@dataclass(frozen=True)
class ReferenceScores:
    """One row of `data/atari_scores.csv` (None where the source has no value)."""

    game: str
    random: float
    human: float
    human_nature: float | None
    nature_dqn: float | None
    nature_dqn_std: float | None


def load_reference_scores() -> dict[str, ReferenceScores]:
    """The shipped reference scores by ale-py game id."""
    text = (resources.files("dqnlab") / "data" / "atari_scores.csv").read_text()

    def number(value: str) -> float | None:
        return float(value) if value.strip() else None

    scores = {}
    for row in csv.DictReader(io.StringIO(text)):
        random, human = number(row["random"]), number(row["human"])
        assert random is not None and human is not None, row["game"]  # filled for all 57
        scores[row["game"]] = ReferenceScores(
            row["game"],
            random,
            human,
            number(row["human_nature"]),
            number(row["nature_dqn"]),
            number(row["nature_dqn_std"]),
        )
    return scores


def human_normalised(score: float, random: float, human: float | None) -> float | None:
    """100 × (score − random) / (human − random): 0 is random play, 100 the human's score."""
    if human is None:
        return None
    return 100.0 * (score - random) / (human - random)


# Runs ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class PeriodicEvaluation:
    """One row of a run's `evaluations.csv`."""

    step: int
    frames: int  # training emulator frames at `step`
    mean: float  # mean score of the games finished within the budget (0 if none)
    episodes: int


@dataclass
class RunResults:
    """What the report reads from one run directory."""

    run_dir: Path
    config: Config
    evaluations: list[PeriodicEvaluation]
    final_evaluation: dict[str, Any] | None  # final_evaluation.json's record


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
                    int(row["step"]), int(row["frames"]), float(row["mean"]), int(row["episodes"])
                )
            )
        except (TypeError, ValueError):  # a line torn by a killed run: fields missing
            continue
    return RunResults(run_dir, config, evaluations, rundir.load_final_evaluation(run_dir))


def best_network_evaluator(
    device: torch.device, *, episodes: int | None = None, seed: int = DEFAULT_EVALUATION_SEED
) -> Callable[[Path], dict[str, Any]]:
    """The final evaluation `write_report` plays where a run has none: the best network,
    `episodes` games (None: the run's final_eval_episodes), saved as the run's
    final_evaluation.json, as `dqnlab evaluate RUN_DIR` does, so it is played once."""

    def evaluate(run_dir: Path) -> dict[str, Any]:
        result, network = final_evaluation(run_dir, "best", episodes, seed, device)
        record = final_evaluation_record(result, network.config, network.path, network.step, seed)
        rundir.save_final_evaluation(run_dir, record)
        return record

    return evaluate


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
        by_env.setdefault(run.config.env, []).append(run.config.to_dict())
    differing = set()
    for settings in by_env.values():
        for name in FIELD_NAMES:
            grouped = name != "env" and name not in NOT_GROUPED
            if grouped and len({repr(values[name]) for values in settings}) > 1:
                differing.add(name)
    return [name for name in FIELD_NAMES if name in differing]


def group_runs(runs: Sequence[RunResults]) -> list[Group]:
    """Groups by game, then by the values of `label_keys`, in order of first appearance."""
    keys = label_keys(runs)
    groups: dict[tuple[str, str], Group] = {}
    for run in runs:
        values = run.config.to_dict()
        settings = {key: values[key] for key in keys}
        label = ", ".join(f"{k}={setting_text(v)}" for k, v in settings.items()) or ALL_EQUAL
        group = groups.setdefault((run.config.env, label), Group(run.config.env, label, settings))
        group.runs.append(run)
    return list(groups.values())


# Results table -------------------------------------------------------------------------


@dataclass(frozen=True)
class ResultRow:
    """One game and configuration: the final evaluations of its seeds, and the references."""

    game: str
    configuration: str
    seeds: int  # runs with a final evaluation
    games_per_seed: tuple[int, int]  # fewest and most final-evaluation games of a seed
    total_steps: tuple[int, int]  # smallest and largest training budget (agent steps)
    score: float  # one seed: its mean over games; several: the mean of the seed means
    score_std: float  # one seed: s.d. over its games; several: s.d. of the seed means
    score_std_over: str  # "games" or "seeds"
    seed_score_min: float | None  # lowest and highest seed mean (several seeds only)
    seed_score_max: float | None
    random: float | None  # references: None for a game outside the reference table
    human: float | None
    human_nature: float | None
    hns_human: float | None  # human-normalised score of `score`, percent, per baseline
    hns_human_nature: float | None
    nature_dqn: float | None
    nature_dqn_std: float | None
    nature_dqn_hns_human: float | None
    nature_dqn_hns_human_nature: float | None
    seed_paper: float | None
    seed_paper_std: float | None
    run_dirs: tuple[Path, ...]

    def hns(self, baseline: str) -> float | None:
        return self.hns_human if baseline == "human" else self.hns_human_nature

    def nature_dqn_hns(self, baseline: str) -> float | None:
        return (
            self.nature_dqn_hns_human if baseline == "human" else self.nature_dqn_hns_human_nature
        )


def result_rows(groups: Sequence[Group], references: dict[str, ReferenceScores]) -> list[ResultRow]:
    """One row per group with at least one final evaluation.

    Standard deviations are numpy's (ddof 0), like the final evaluation's own over games.
    """
    rows = []
    for group in groups:
        runs = [run for run in group.runs if run.final_evaluation is not None]
        if not runs:
            continue
        finals = [run.final_evaluation for run in runs if run.final_evaluation is not None]
        means = np.array([float(final["mean"]) for final in finals])
        games = [int(final["episodes"]) for final in finals]
        budgets = [run.config.total_steps for run in runs]
        if len(finals) == 1:
            score, std, over = float(means[0]), float(finals[0]["std"]), "games"
            low = high = None
        else:
            score, std, over = float(means.mean()), float(means.std()), "seeds"
            low, high = float(means.min()), float(means.max())
        reference = references.get(group.env)
        seed_paper = SEED_PAPER_SCORES.get(group.env)
        nature_dqn = reference.nature_dqn if reference else None
        rows.append(
            ResultRow(
                game=group.env,
                configuration=group.label,
                seeds=len(finals),
                games_per_seed=(min(games), max(games)),
                total_steps=(min(budgets), max(budgets)),
                score=score,
                score_std=std,
                score_std_over=over,
                seed_score_min=low,
                seed_score_max=high,
                random=reference.random if reference else None,
                human=reference.human if reference else None,
                human_nature=reference.human_nature if reference else None,
                hns_human=_normalised(score, reference, "human"),
                hns_human_nature=_normalised(score, reference, "human_nature"),
                nature_dqn=nature_dqn,
                nature_dqn_std=reference.nature_dqn_std if reference else None,
                nature_dqn_hns_human=_normalised(nature_dqn, reference, "human"),
                nature_dqn_hns_human_nature=_normalised(nature_dqn, reference, "human_nature"),
                seed_paper=seed_paper[0] if seed_paper else None,
                seed_paper_std=seed_paper[1] if seed_paper else None,
                run_dirs=tuple(run.run_dir for run in runs),
            )
        )
    return rows


def _normalised(
    value: float | None, reference: ReferenceScores | None, baseline: str
) -> float | None:
    if value is None or reference is None:
        return None
    return human_normalised(value, reference.random, getattr(reference, baseline))


@dataclass(frozen=True)
class SummaryRow:
    """The median or mean human-normalised score of one configuration across games."""

    statistic: str  # "median" or "mean"
    configuration: str
    baseline: str  # "human" (dqn_zoo's) or "human_nature" (Nature ED Table 2)
    games: tuple[str, ...]  # the games that have this baseline
    hns: float  # percent
    nature_dqn_hns: float | None  # Nature DQN's, same games (None if one has no DQN score)


def summary_rows(rows: Sequence[ResultRow]) -> list[SummaryRow]:
    """Per configuration and baseline, over its games that have the baseline, when there
    are at least two of them."""
    summary = []
    configurations = list(dict.fromkeys(row.configuration for row in rows))
    for statistic, function in (("median", np.median), ("mean", np.mean)):
        for configuration in configurations:
            for baseline in BASELINES:
                cells = [
                    (row.game, row.hns(baseline), row.nature_dqn_hns(baseline))
                    for row in rows
                    if row.configuration == configuration and row.hns(baseline) is not None
                ]
                if len(cells) < 2:
                    continue
                nature = [value for _, _, value in cells if value is not None]
                summary.append(
                    SummaryRow(
                        statistic,
                        configuration,
                        baseline,
                        tuple(game for game, _, _ in cells),
                        float(function([value for _, value, _ in cells])),
                        float(function(nature)) if len(nature) == len(cells) else None,
                    )
                )
    return summary


# Learning curves -----------------------------------------------------------------------


@dataclass(frozen=True)
class CurveSeries:
    """One configuration's line: at each evaluation step, the mean over the seeds that
    have an evaluation there, and their lowest and highest (several seeds only)."""

    label: str
    seeds: int  # runs with at least one periodic evaluation
    steps: tuple[int, ...]
    mean: tuple[float, ...]
    low: tuple[float, ...] | None
    high: tuple[float, ...] | None
    seeds_at_step: tuple[int, ...]

    @property
    def legend_label(self) -> str:
        return f"{self.label} ({self.seeds} seed{'s' if self.seeds > 1 else ''})"


@dataclass
class Curve:
    """One game's figure."""

    game: str
    series: list[CurveSeries]
    # Training frames per agent step for the top axis, from the runs' evaluations.csv;
    # None where a frame is a step (non-Atari environments).
    frames_per_step: float | None
    files: list[Path] = field(default_factory=list)


def learning_curves(groups: Sequence[Group]) -> list[Curve]:
    """One curve per game with a periodic evaluation, one series per group that has one.

    The top axis converts steps to frames with one factor per game, the frames of all its
    evaluations over their steps: an Atari step is `action_repeat_frames` frames, plus
    the no-op frames of each episode start and minus the frames a game over cuts short,
    so the factor is measured rather than assumed. No top axis where a frame is a step,
    or where the configurations' factors differ by more than 5%."""
    curves: dict[str, Curve] = {}
    for group in groups:
        runs = [run for run in group.runs if run.evaluations]
        if not runs:
            continue
        by_step: dict[int, list[float]] = {}
        for run in runs:
            for point in run.evaluations:
                by_step.setdefault(point.step, []).append(point.mean)
        steps = sorted(by_step)
        values = [np.array(by_step[step]) for step in steps]
        several = len(runs) >= 2
        series = CurveSeries(
            label=group.label,
            seeds=len(runs),
            steps=tuple(steps),
            mean=tuple(float(v.mean()) for v in values),
            low=tuple(float(v.min()) for v in values) if several else None,
            high=tuple(float(v.max()) for v in values) if several else None,
            seeds_at_step=tuple(len(v) for v in values),
        )
        curves.setdefault(group.env, Curve(group.env, [], None)).series.append(series)
    for curve in curves.values():
        points = {  # each configuration's evaluations
            group.label: [p for run in group.runs for p in run.evaluations]
            for group in groups
            if group.env == curve.game
        }
        ratios = [_frames_per_step(p) for p in points.values() if p]
        # One top axis fits every line only if the configurations agree (they do not when
        # they differ in action_repeat_frames, say): otherwise steps alone.
        if any(ratio != 1.0 for ratio in ratios) and max(ratios) <= 1.05 * min(ratios):
            curve.frames_per_step = _frames_per_step([p for ps in points.values() for p in ps])
    return list(curves.values())


def _frames_per_step(points: Sequence[PeriodicEvaluation]) -> float:
    return sum(p.frames for p in points) / sum(p.step for p in points)


def curve_figure(curve: Curve) -> Figure:
    """The figure of one game: mean score of the periodic evaluations against training
    steps (bottom) and frames (top), a line per configuration, shaded min–max over seeds."""
    figure = Figure(figsize=(7.0, 4.5), layout="constrained")
    axes = figure.add_subplot()
    for series in curve.series:
        (line,) = axes.plot(
            series.steps,
            series.mean,
            marker="o" if len(series.steps) <= 30 else None,
            markersize=3,
            label=series.legend_label,
        )
        if series.low is not None and series.high is not None:
            axes.fill_between(
                series.steps,
                series.low,
                series.high,
                color=line.get_color(),
                alpha=0.2,
                linewidth=0,
            )
    axes.set_title(curve.game)
    axes.set_xlabel("training steps (agent decisions)")
    axes.set_ylabel("mean score per game (periodic evaluation)")
    axes.xaxis.set_major_formatter(FuncFormatter(lambda value, _: _count_text(value)))
    axes.grid(alpha=0.3)
    if curve.frames_per_step is not None:
        ratio = curve.frames_per_step

        def to_frames(steps: Any) -> Any:
            return np.asarray(steps) * ratio

        def to_steps(frames: Any) -> Any:
            return np.asarray(frames) / ratio

        top = axes.secondary_xaxis("top", functions=(to_frames, to_steps))
        top.set_xlabel(f"training frames (≈ {ratio:.2f} per step, measured)")
        top.xaxis.set_major_formatter(FuncFormatter(lambda value, _: _count_text(value)))
    banded = any(series.low is not None for series in curve.series)
    axes.legend(
        title="line: mean over seeds; shaded: min–max over seeds" if banded else None,
        title_fontsize="small",
        fontsize="small",
        loc="best",
    )
    return figure


def _count_text(value: float) -> str:
    """50000000 -> 50M, 250000 -> 250k: axis ticks in the units budgets are spoken in."""
    for size, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(value) >= size:
            return f"{value / size:g}{suffix}"
    return f"{value:g}"


def _file_stem(env: str, taken: set[str]) -> str:
    """`curves-ENV` with characters unsafe in a file name replaced (ALE/Pong-v5,
    module:Class), made unique."""
    stem = "curves-" + (re.sub(r"[^A-Za-z0-9_.-]+", "_", env).strip("._") or "env")
    unique, number = stem, 2
    while unique in taken:
        unique, number = f"{stem}-{number}", number + 1
    taken.add(unique)
    return unique


# The report ----------------------------------------------------------------------------


@dataclass
class Report:
    """Everything behind a report's outputs, and the files written."""

    runs: list[RunResults]
    groups: list[Group]
    rows: list[ResultRow]
    summary: list[SummaryRow]
    curves: list[Curve]
    notes: list[str]
    evaluated: list[Path]  # runs whose final evaluation was played for this report
    files: list[Path]
    inspections: list[RunInspection] = field(default_factory=list)


@dataclass
class RunInspection:
    """The Q-value inspection of one run's networks written with the report."""

    run_dir: Path
    out_dir: Path
    inspection: Inspection


def build_report(
    run_dirs: Sequence[Path],
    *,
    evaluate_missing: Callable[[Path], dict[str, Any]] | None = None,
    echo: Callable[[str], object] | None = None,
) -> Report:
    """Read the runs (RUN_DIR or sweep directories), play the missing final evaluations
    with `evaluate_missing` (None: leave those runs out of the table) and compute the
    table and the curves; writes nothing but what `evaluate_missing` saves."""
    runs = [load_run(path) for path in find_runs(run_dirs)]
    notes: list[str] = []
    evaluated = _complete_final_evaluations(runs, evaluate_missing, echo, notes)
    groups = group_runs(runs)
    notes.extend(_group_notes(groups))
    rows = result_rows(groups, load_reference_scores())
    curves = learning_curves(groups)
    for group in groups:
        for run in group.runs:
            if not run.evaluations:
                notes.append(
                    f"{run.run_dir}: no periodic evaluation yet (evaluations.csv has no "
                    "rows): it has no learning curve"
                )
            elif any(point.episodes == 0 for point in run.evaluations):
                empty = sum(point.episodes == 0 for point in run.evaluations)
                notes.append(
                    f"{run.run_dir}: {empty} periodic evaluation(s) finished no game within "
                    "eval_steps; the curve shows 0 there (DeepMind's Lua convention)"
                )
    for game in dict.fromkeys(group.env for group in groups):
        if not any(curve.game == game for curve in curves):
            notes.append(f"{game}: no run has a periodic evaluation yet: no figure")
    return Report(runs, groups, rows, summary_rows(rows), curves, notes, evaluated, [])


def write_report(
    run_dirs: Sequence[Path],
    out_dir: Path,
    *,
    evaluate_missing: Callable[[Path], dict[str, Any]] | None = None,
    echo: Callable[[str], object] | None = None,
    inspect_frames: int = 0,
    device: torch.device | None = None,
) -> Report:
    """`build_report`, then write results.md, results.csv, summary.csv (2 games or more)
    and curves-GAME.png/.svg into `out_dir`. `evaluate_missing`: see
    `best_network_evaluator`; `echo` is told of each evaluation before it starts. With
    `inspect_frames` > 0, also the Q-values of each run's best and worst networks on that
    many frames (`inspect_report_runs`), into `out_dir`/q-values/RUN/. What an earlier
    report left in `out_dir` and this one does not write again (curves of other games,
    a summary.csv, Q-values of other runs) is removed: every file is of this report."""
    report = build_report(run_dirs, evaluate_missing=evaluate_missing, echo=echo)
    out_dir.mkdir(parents=True, exist_ok=True)
    earlier = [*out_dir.glob("curves-*.png"), *out_dir.glob("curves-*.svg"), out_dir / SUMMARY_CSV]
    earlier_inspections = [p for p in (out_dir / Q_VALUES_DIR).glob("*") if p.is_dir()]
    taken: set[str] = set()
    for curve in report.curves:
        figure = curve_figure(curve)
        stem = _file_stem(curve.game, taken)
        for suffix, options in ((".png", {"dpi": 150}), (".svg", {"metadata": {"Date": None}})):
            path = out_dir / f"{stem}{suffix}"
            figure.savefig(path, **options)
            curve.files.append(path)
        report.files.extend(curve.files)
    path = out_dir / RESULTS_CSV
    _write_csv(path, [_result_record(row) for row in report.rows], RESULT_COLUMNS)
    report.files.append(path)
    if report.summary:
        path = out_dir / SUMMARY_CSV
        _write_csv(path, [_summary_record(row) for row in report.summary], SUMMARY_COLUMNS)
        report.files.append(path)
    for old in earlier:
        if old not in report.files:
            old.unlink(missing_ok=True)
    path = out_dir / RESULTS_MD
    path.write_text(format_markdown(report, out_dir))  # complete before the slow part
    report.files.append(path)
    if inspect_frames > 0:
        inspect_report_runs(report, out_dir / Q_VALUES_DIR, inspect_frames, device, echo)
        path.write_text(format_markdown(report, out_dir))
    written = {item.out_dir for item in report.inspections}
    for old_dir in earlier_inspections:
        if old_dir not in written:
            shutil.rmtree(old_dir)
    return report


def inspect_report_runs(
    report: Report,
    out_dir: Path,
    frames: int,
    device: torch.device | None = None,
    echo: Callable[[str], object] | None = None,
) -> None:
    """The seed paper's Q-value comparison for every run of the report: its best network
    against its worst after the first quarter of training (the best alone while it has
    no worst.pt), on `frames` frames of the best network's first evaluation game, each
    run into its own `out_dir`/RUN directory (`inspection.inspect_run`). A run that
    cannot be inspected gets a note instead."""
    from dqnlab.inspection import inspect_run

    taken: set[str] = set()
    for group in report.groups:
        for run in group.runs:
            if not rundir.network_path(run.run_dir, "best").is_file():
                report.notes.append(f"{run.run_dir}: no best network yet: no Q-value figure")
                continue
            has_worst = rundir.network_path(run.run_dir, "worst").is_file()
            names = ["best", "worst"] if has_worst else ["best"]
            if names == ["best"]:
                report.notes.append(
                    f"{run.run_dir}: no worst network (worst.pt is kept from the evaluations "
                    "after the first quarter of training): Q-values of the best one alone"
                )
            name = _unique_name(run.run_dir, taken)
            if echo is not None:
                echo(f"dqnlab: {run.run_dir}: Q-values of the {' and '.join(names)} networks")
            try:
                inspection = inspect_run(
                    run.run_dir, out_dir / name, frames=frames, checkpoints=names, device=device
                )
            except DqnlabError as error:
                report.notes.append(f"{run.run_dir}: no Q-value figure: {error}")
                continue
            report.inspections.append(RunInspection(run.run_dir, out_dir / name, inspection))
            report.files.extend(inspection.figure_paths)


def _unique_name(run_dir: Path, taken: set[str]) -> str:
    """The run directory's name, its parent's prefixed where two runs share a name."""
    name = re.sub(r"[^A-Za-z0-9_.=+-]+", "_", run_dir.name).strip("._") or "run"
    if name in taken:
        parent = re.sub(r"[^A-Za-z0-9_.=+-]+", "_", run_dir.resolve().parent.name).strip("._")
        name = f"{parent}-{name}"
    unique, number = name, 2
    while unique in taken:
        unique, number = f"{name}-{number}", number + 1
    taken.add(unique)
    return unique


def _complete_final_evaluations(
    runs: Sequence[RunResults],
    evaluate_missing: Callable[[Path], dict[str, Any]] | None,
    echo: Callable[[str], object] | None,
    notes: list[str],
) -> list[Path]:
    """Play the final evaluation of each run that has none, or whose saved one is of an
    older best network (the run trained on after it was played)."""
    evaluated = []
    for run in runs:
        best_step = rundir.network_step(run.run_dir, "best")
        saved = run.final_evaluation
        saved_step = saved.get("checkpoint_step") if saved is not None else None
        stale = saved_step is not None and best_step is not None and saved_step != best_step
        if saved is not None and not stale:
            continue
        why = (
            f"its final evaluation is of the best network at step {saved_step}, the best "
            f"is now the one at step {best_step}"
            if stale
            else "no final evaluation"
        )
        if best_step is None:
            notes.append(f"{run.run_dir}: {why} and no best network yet: not in the table")
        elif evaluate_missing is None:
            if stale:
                notes.append(f"{run.run_dir}: {why}; the table shows the older one")
            else:
                notes.append(f"{run.run_dir}: {why}: not in the table")
        else:
            if echo is not None:
                echo(f"dqnlab: {run.run_dir}: {why}: evaluating its best network")
            run.final_evaluation = evaluate_missing(run.run_dir)
            evaluated.append(run.run_dir)
    return evaluated


def _group_notes(groups: Sequence[Group]) -> list[str]:
    notes = []
    for group in groups:
        name = f"{group.env}, {group.label}"
        budgets = sorted({run.config.total_steps for run in group.runs})
        if len(budgets) > 1:
            notes.append(
                f"{name}: the seeds' training budgets differ (total_steps "
                f"{', '.join(map(str, budgets))}); they are grouped as one configuration "
                "all the same, since the budget does not change what is learned up to it, "
                "but their final scores come from networks trained for different times"
            )
        seeds = [run.config.seed for run in group.runs]
        repeated = sorted({seed for seed in seeds if seeds.count(seed) > 1})
        if repeated:
            notes.append(
                f"{name}: seed {', '.join(map(str, repeated))} appears in more than one run "
                "directory; each run counts as a seed"
            )
    return notes


# Output formats ------------------------------------------------------------------------

RESULT_COLUMNS = (
    "game", "configuration", "seeds", "games_per_seed_min", "games_per_seed_max",
    "total_steps_min", "total_steps_max", "score_mean", "score_std", "score_std_over",
    "seed_mean_min", "seed_mean_max", "random", "human", "human_nature",
    "hns_human_percent", "hns_human_nature_percent", "nature_dqn", "nature_dqn_std",
    "nature_dqn_hns_human_percent", "nature_dqn_hns_human_nature_percent", "seed_paper",
    "seed_paper_std", "run_dirs",
)  # fmt: skip
SUMMARY_COLUMNS = (
    "statistic", "configuration", "baseline", "games", "game_ids", "hns_percent",
    "nature_dqn_hns_percent",
)  # fmt: skip


def _result_record(row: ResultRow) -> dict[str, Any]:
    return {
        "game": row.game,
        "configuration": row.configuration,
        "seeds": row.seeds,
        "games_per_seed_min": row.games_per_seed[0],
        "games_per_seed_max": row.games_per_seed[1],
        "total_steps_min": row.total_steps[0],
        "total_steps_max": row.total_steps[1],
        "score_mean": row.score,
        "score_std": row.score_std,
        "score_std_over": row.score_std_over,
        "seed_mean_min": row.seed_score_min,
        "seed_mean_max": row.seed_score_max,
        "random": row.random,
        "human": row.human,
        "human_nature": row.human_nature,
        "hns_human_percent": row.hns_human,
        "hns_human_nature_percent": row.hns_human_nature,
        "nature_dqn": row.nature_dqn,
        "nature_dqn_std": row.nature_dqn_std,
        "nature_dqn_hns_human_percent": row.nature_dqn_hns_human,
        "nature_dqn_hns_human_nature_percent": row.nature_dqn_hns_human_nature,
        "seed_paper": row.seed_paper,
        "seed_paper_std": row.seed_paper_std,
        "run_dirs": ";".join(str(path) for path in row.run_dirs),
    }


def _summary_record(row: SummaryRow) -> dict[str, Any]:
    return {
        "statistic": row.statistic,
        "configuration": row.configuration,
        "baseline": row.baseline,
        "games": len(row.games),
        "game_ids": ";".join(row.games),
        "hns_percent": row.hns,
        "nature_dqn_hns_percent": row.nature_dqn_hns,
    }


def _write_csv(path: Path, records: list[dict[str, Any]], columns: Sequence[str]) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        for record in records:
            writer.writerow({k: "" if v is None else v for k, v in record.items()})


def _score_text(value: float | None) -> str:
    """As the Nature table prints scores: whole numbers from 1000 up, one decimal below."""
    if value is None:
        return ""
    return f"{value:.0f}" if abs(value) >= 1000 else f"{value:.1f}"


def _plus_minus(mean: float | None, std: float | None) -> str:
    if mean is None:
        return ""
    return _score_text(mean) + (f" ± {_score_text(std)}" if std is not None else "")


def _range_text(low: int, high: int, text: Callable[[float], str] = str) -> str:
    return text(low) if low == high else f"{text(low)}–{text(high)}"


def _percent_text(value: float | None) -> str:
    return "" if value is None else f"{value:.1f}"


TABLE_HEADERS = (
    "Game", "Configuration", "Seeds", "Games/seed", "Budget (steps)", "Score", "Seed means",
    "Nature DQN", "Seed paper", "HNS % (dqn_zoo human)", "HNS % (Nature human)",
)  # fmt: skip
SUMMARY_HEADERS = (
    "Across games", "Configuration", "HNS % (dqn_zoo human)", "Nature DQN, same games",
    "HNS % (Nature human)", "Nature DQN, same games",
)  # fmt: skip


def _table_cells(row: ResultRow) -> list[str]:
    low, high = row.seed_score_min, row.seed_score_max
    return [
        row.game,
        row.configuration,
        str(row.seeds),
        _range_text(*row.games_per_seed),
        _range_text(*row.total_steps, text=_count_text),
        _plus_minus(row.score, row.score_std),
        f"{_score_text(low)} to {_score_text(high)}" if low is not None else "",
        _plus_minus(row.nature_dqn, row.nature_dqn_std),
        _plus_minus(row.seed_paper, row.seed_paper_std),
        _percent_text(row.hns_human),
        _percent_text(row.hns_human_nature),
    ]


def _summary_cells(summary: Sequence[SummaryRow]) -> list[list[str]]:
    """One line per statistic and configuration, the two baselines side by side."""
    lines: dict[tuple[str, str], dict[str, SummaryRow]] = {}
    for row in summary:
        lines.setdefault((row.statistic, row.configuration), {})[row.baseline] = row
    cells = []
    for (statistic, configuration), by_baseline in lines.items():
        line = [statistic, configuration]
        for baseline in BASELINES:
            found = by_baseline.get(baseline)
            if found is None:
                line += ["", ""]
            else:
                line += [
                    f"{found.hns:.1f} ({len(found.games)} games)",
                    _percent_text(found.nature_dqn_hns),
                ]
        cells.append(line)
    return cells


def _aligned(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    widths = [max(len(cell) for cell in column) for column in zip(headers, *rows, strict=True)]
    lines = [headers, ["-" * width for width in widths], *rows]
    return "\n".join(
        "  ".join(cell.ljust(width) for cell, width in zip(line, widths, strict=True)).rstrip()
        for line in lines
    )


def format_table(report: Report) -> str:
    """The results table (and the scores across games) as aligned text for a terminal."""
    if not report.rows:
        return "no run has a final evaluation: nothing to tabulate"
    text = _aligned(TABLE_HEADERS, [_table_cells(row) for row in report.rows])
    if report.summary:
        text += "\n\n" + _aligned(SUMMARY_HEADERS, _summary_cells(report.summary))
    return text


def _markdown_table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    def line(cells: Sequence[str]) -> str:
        return "| " + " | ".join(cell.replace("|", "\\|") for cell in cells) + " |"

    return "\n".join([line(headers), line(["---"] * len(headers)), *map(line, rows)])


def format_markdown(report: Report, out_dir: Path | None = None) -> str:
    """results.md: the table, the scores across games, the figures (linked relative to
    `out_dir`), a legend, the notes and the runs."""
    parts = ["# Results", ""]
    if report.rows:
        parts += [_markdown_table(TABLE_HEADERS, [_table_cells(r) for r in report.rows]), ""]
    else:
        parts += ["No run has a final evaluation yet.", ""]
    if report.summary:
        parts += ["## Across games", ""]
        parts += [_markdown_table(SUMMARY_HEADERS, _summary_cells(report.summary)), ""]
    pictures = [
        (curve.game, path)
        for curve in report.curves
        for path in curve.files
        if path.suffix == ".png"
    ]
    if pictures:
        parts += ["## Learning curves", ""]
        for game, path in pictures:
            link = path.name if out_dir is not None and path.parent == out_dir else str(path)
            parts += [f"![{game}]({link})", ""]
    if report.inspections:
        parts += ["## Q-values", ""]
        for item in report.inspections:
            inspection = item.inspection
            networks = " against ".join(network.legend_label for network in inspection.networks)
            picture = inspection.overview_path or (
                inspection.figure_paths[0] if inspection.figure_paths else None
            )
            parts += [f"{item.run_dir}: {networks}, on {inspection.note}.", ""]
            if picture is not None:
                shown = picture.relative_to(out_dir) if out_dir is not None else picture
                parts += [f"![Q-values of {item.run_dir}]({shown.as_posix()})", ""]
    parts += ["## Legend", "", *LEGEND, ""]
    if report.notes:
        parts += ["## Notes", "", *(f"- {note}" for note in report.notes), ""]
    parts += ["## Runs", ""]
    parts += [
        _markdown_table(
            ("Game", "Configuration", "Seed", "Run", "Final evaluation"), _run_cells(report)
        )
    ]
    return "\n".join(parts) + "\n"


def _run_cells(report: Report) -> list[list[str]]:
    cells = []
    for group in report.groups:
        for run in group.runs:
            final = run.final_evaluation
            if final is None:
                text = "none"
            else:
                score = _plus_minus(float(final["mean"]), float(final["std"]))
                step = final.get("checkpoint_step")
                text = f"{score} over {final['episodes']} games, best network of step {step}"
            cells.append([group.env, group.label, str(run.config.seed), str(run.run_dir), text])
    return cells


LEGEND = [
    "- **Score**: the final evaluation of each run's best network (the network of the "
    "periodic evaluation with the highest mean): whole games of at most "
    "final_eval_max_episode_frames frames (5 minutes in the Nature protocol) at "
    "eval_epsilon, after random no-op starts. With one seed: that run's mean ± s.d. over "
    "its games. With several seeds: the mean of the seeds' means ± the s.d. of the seeds' "
    "means; **Seed means** gives the lowest and highest of them. Standard deviations are "
    "population ones (numpy, ddof 0), as the final evaluation's own.",
    "- **Configuration**: the settings that differ between runs of the same game; runs "
    "that differ only in `seed` are the seeds of one configuration. Settings that do not "
    "change what is learned, and the number of final-evaluation games, never label a "
    "configuration: "
    + ", ".join(f"`{name}`" for name in NOT_GROUPED if name != "seed")
    + ". Runs with different budgets (`total_steps`) are therefore seeds of one "
    "configuration (with a note); **Budget (steps)** gives their total_steps.",
    f"- **{ALL_EQUAL}**: every run of the game has the same settings but for the seed.",
    "- **Games/seed**: final-evaluation games per seed (Nature: 30).",
    "- **Nature DQN**: Mnih et al. 2015, Extended Data Table 2: mean ± s.d. over 30 games.",
    '- **Seed paper**: Roderick, MacGlashan and Tellex 2017, "Implementing the Deep '
    'Q-Network", Table 1 (Pong, Breakout and Seaquest only).',
    "- **HNS %**: human-normalised score, 100 × (score − random) / (human − random), "
    "with `random` from dqn_zoo (equal to Nature's) and two human baselines: **dqn_zoo "
    "human**, the set DeepMind's later code (dqn_zoo `atari_data.py`) uses, and **Nature "
    "human**, the human tester of the Nature paper (ED Table 2). They differ for 34 of the "
    "49 games (Pong 14.6 against 9.3), so compare only scores with the same baseline. "
    "Empty for games outside the reference table (non-Atari environments, Gymnasium ids "
    "such as ALE/Pong-v5) and for Nature human outside the Nature 49.",
    "- **Across games**: the median and mean HNS % of each configuration over its games "
    "that have the baseline (at least 2), with Nature DQN's over the same games where "
    "every one of them has a Nature DQN score.",
    "- **Learning curves**: the mean score of the periodic evaluations (eval_steps agent "
    "steps at eval_epsilon every eval_period_steps; the mean of the games finished within "
    "the budget) against training steps, training frames on the top axis (measured from "
    "evaluations.csv: action_repeat_frames per step plus no-op starts). One line per "
    "configuration, the mean over the seeds that have an evaluation at that step; shaded: "
    "lowest to highest seed (configurations with 2 seeds or more).",
]
