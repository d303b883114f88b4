"""Writing a report: the only module of the report with side effects (playing missing
final evaluations, inspecting Q-values, writing and deleting files).

`dqnlab report RUN_DIR...` reads each run's final evaluation (`final_evaluation.json`,
played now with the run's best network where it is missing or older than that network)
and its periodic evaluations (`evaluations.csv`). The runs of one game are grouped by the
settings that differ between them: runs whose settings differ only in `seed` (and in
settings that do not change what is learned) are the seeds of one configuration. It
writes into the output directory:

- `results.md`: the table, the scores across games, the figures, a legend and notes;
- `results.csv`: one row per game and configuration, numbers in their own columns;
- `summary.csv`: median and mean human-normalised score across games (2 games or more);
- `curves-GAME.png` and `.svg`: periodic-evaluation score against training steps;
- aggregates across games (2 games or more with human-normalised scores):
  `aggregates.csv`, `aggregates.png`/`.svg` (IQM, median, mean, optimality gap with
  confidence intervals), `performance-profiles.png`/`.svg`, and with two configurations
  or more `probability-of-improvement.csv`.
"""

from __future__ import annotations

import csv
import re
import shutil
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dqnlab.analysis.report.aggregate import (
    Aggregates,
    AggregateSettings,
    aggregate_statistics,
    score_matrices,
)
from dqnlab.analysis.report.aggregate_figures import interval_figure, profile_figure
from dqnlab.analysis.report.atari100k import (
    ATARI100K_COLUMNS,
    DER_PAPER,
    Atari100kRow,
    atari100k_record,
    atari100k_rows,
    protocol_notes,
    published_matrix,
)
from dqnlab.analysis.report.curves import curve_figure, curve_notes, learning_curves
from dqnlab.analysis.report.reference import (
    REFERENCES,
    group_references,
    load_references,
    on_track_rows,
    reference_notes,
)
from dqnlab.analysis.report.runs import Group, RunResults, find_runs, group_runs, load_run
from dqnlab.analysis.report.scores import (
    load_atari100k_scores,
    load_reference_scores,
    result_rows,
    summary_rows,
)
from dqnlab.analysis.report.tables import (
    AGGREGATE_COLUMNS,
    IMPROVEMENT_COLUMNS,
    RESULT_COLUMNS,
    SUMMARY_COLUMNS,
    Report,
    RunInspection,
    _aggregate_records,
    _improvement_records,
    _result_record,
    _summary_record,
    format_markdown,
)
from dqnlab.config import DEFAULT_EVALUATION_SEED
from dqnlab.errors import DqnlabError
from dqnlab.run import rundir
from dqnlab.run.evaluate import evaluate_and_save
from dqnlab.run.lease import lease_is_live
from dqnlab.run.wandb_log import add_to_summary, final_evaluation_values

if TYPE_CHECKING:
    import torch
    from matplotlib.figure import Figure

RESULTS_MD, RESULTS_CSV, SUMMARY_CSV = "results.md", "results.csv", "summary.csv"
ATARI100K_CSV = "atari100k.csv"  # --reference der-paper
Q_VALUES_DIR = "q-values"
FIGURES = (".png", ".svg")  # each figure in both
AGGREGATES_CSV, IMPROVEMENT_CSV = "aggregates.csv", "probability-of-improvement.csv"
AGGREGATES_FIGURE, PROFILES_FIGURE = "aggregates", "performance-profiles"  # .png and .svg
AGGREGATE_FILES = (
    AGGREGATES_CSV,
    IMPROVEMENT_CSV,
    *(f"{stem}{suffix}" for stem in (AGGREGATES_FIGURE, PROFILES_FIGURE) for suffix in FIGURES),
)


def final_network_evaluator(
    device: torch.device, *, episodes: int | None = None, seed: int = DEFAULT_EVALUATION_SEED
) -> Callable[[Path], dict[str, Any]]:
    """The final evaluation `write_report` plays where a run has none: the run's
    `final_eval_network` (its best network, or with Atari 100k's protocol its last),
    `episodes` games (None: the run's final_eval_episodes), saved as the run's
    final_evaluation.json, as `dqnlab evaluate RUN_DIR` does, so it is played once."""

    def evaluate(run_dir: Path) -> dict[str, Any]:
        network = rundir.load_run_config(run_dir).final_eval_network
        return evaluate_and_save(run_dir, network, episodes, seed, device)

    return evaluate


def _file_stem(env: str, taken: set[str]) -> str:
    """`curves-ENV` with characters unsafe in a file name replaced (ALE/Pong-v5,
    module:Class), made unique."""
    stem = "curves-" + (re.sub(r"[^A-Za-z0-9_.-]+", "_", env).strip("._") or "env")
    return _unique(stem, taken)


def build_report(
    run_dirs: Sequence[Path],
    *,
    evaluate_missing: Callable[[Path], dict[str, Any]] | None = None,
    echo: Callable[[str], object] | None = None,
    reference: str = "dopamine",
    aggregate: AggregateSettings | None = None,
) -> Report:
    """Read the runs (RUN_DIR or sweep directories), play the missing final evaluations
    with `evaluate_missing` (None: leave those runs out of the table) and compute the
    table, the curves and the aggregates across games (`aggregate`: the baseline and the
    bootstrap, None: the defaults); writes nothing but what `evaluate_missing` saves.
    `reference`: "dopamine" draws behind the Atari games' curves the published curve of
    each agent that a configuration matches (`reference.reference_agent`) and sets each
    run beside its own agent's in the on-track table; "der-paper" adds the Atari 100k table
    against Data-Efficient Rainbow's published scores, those scores as a configuration of
    the aggregates, and a note for each run off the benchmark's protocol (`atari100k.py`);
    "none" leaves all of them out."""
    if reference not in REFERENCES:
        raise DqnlabError(f"--reference {reference!r} is not one of: {', '.join(REFERENCES)}")
    runs = [load_run(path) for path in find_runs(run_dirs)]
    notes = _training_notes(runs)
    evaluated = _complete_final_evaluations(runs, evaluate_missing, echo, notes)
    groups = group_runs(runs)
    notes.extend(_group_notes(groups))
    references = load_reference_scores()
    rows = result_rows(groups, references)
    settings = aggregate or AggregateSettings()
    aggregate_games, matrices, aggregate_notes = score_matrices(
        groups, references, settings.baseline
    )
    notes.extend(aggregate_notes)
    atari100k: list[Atari100kRow] = []
    if reference == "der-paper":
        atari100k = atari100k_rows(groups, load_atari100k_scores())
        notes.extend(protocol_notes(runs))
        notes.extend(_add_published_der(matrices, aggregate_games, settings.baseline))
    aggregates = aggregate_statistics(matrices, aggregate_games, settings) if matrices else None
    curves = learning_curves(groups)
    notes.extend(curve_notes(runs, groups, curves))
    on_track = []
    if reference == "dopamine":
        curves_by_agent = load_references(run.config for run in runs)
        for curve in curves:
            drawn = {series.label for series in curve.series}
            curve.references = group_references(
                [g for g in groups if g.env == curve.game and g.label in drawn], curves_by_agent
            )
        on_track = on_track_rows(
            [(run, group.label) for group in groups for run in group.runs], curves_by_agent
        )
        notes.extend(reference_notes(groups, curves_by_agent))
    summary = summary_rows(rows)
    return Report(
        runs, groups, rows, summary, curves, notes, evaluated, [],
        aggregates=aggregates, on_track=on_track, atari100k=atari100k,
    )  # fmt: skip


def _add_published_der(
    matrices: dict[str, np.ndarray], games: Sequence[str], baseline: str
) -> list[str]:
    """DER's published scores as one more configuration of the aggregates, over the same
    games, where every game is one of Atari 100k's and the baseline is dqn_zoo's human
    (the benchmark's); else a note saying why not."""
    if not matrices:
        return []
    benchmark = load_atari100k_scores()
    outside = [game for game in games if game not in benchmark]
    if outside:
        return [f"aggregates: {DER_PAPER} left out: {', '.join(outside)} not in Atari 100k"]
    if baseline != "human":
        return [f"aggregates: {DER_PAPER} left out: Atari 100k normalises by dqn_zoo's human"]
    matrices[DER_PAPER] = published_matrix(games, benchmark)
    return []


def write_report(
    run_dirs: Sequence[Path],
    out_dir: Path,
    *,
    evaluate_missing: Callable[[Path], dict[str, Any]] | None = None,
    echo: Callable[[str], object] | None = None,
    inspect_frames: int = 0,
    device: torch.device | None = None,
    reference: str = "dopamine",
    aggregate: AggregateSettings | None = None,
) -> Report:
    """`build_report`, then write results.md, results.csv, summary.csv (2 games or more),
    curves-GAME.png/.svg and the aggregates' files into `out_dir`. `evaluate_missing`: see
    `final_network_evaluator`; `echo` is told of each evaluation before it starts. With
    `inspect_frames` > 0, also the Q-values of each run's best and worst networks on that
    many frames (`inspect_report_runs`), into `out_dir`/q-values/RUN/. What an earlier
    report left in `out_dir` and this one does not write again (curves of other games,
    a summary.csv, aggregates, Q-values of other runs) is removed: every file is of this
    report."""
    report = build_report(
        run_dirs,
        evaluate_missing=evaluate_missing,
        echo=echo,
        reference=reference,
        aggregate=aggregate,
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    earlier = [*out_dir.glob("curves-*.png"), *out_dir.glob("curves-*.svg"), out_dir / SUMMARY_CSV]
    earlier.append(out_dir / ATARI100K_CSV)
    earlier += [out_dir / name for name in AGGREGATE_FILES]
    earlier_inspections = [p for p in (out_dir / Q_VALUES_DIR).glob("*") if p.is_dir()]
    taken: set[str] = set()
    for curve in report.curves:
        curve.files += _save_figure(curve_figure(curve), out_dir / _file_stem(curve.game, taken))
        report.files.extend(curve.files)
    if report.aggregates is not None:
        report.files.extend(_write_aggregates(report.aggregates, out_dir))
    report.files.extend(_write_tables(report, out_dir))
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
    send_to_wandb(report, echo)
    return report


def _write_tables(report: Report, out_dir: Path) -> list[Path]:
    """results.csv, and atari100k.csv and summary.csv where the report has their rows."""
    path = out_dir / RESULTS_CSV
    _write_csv(path, [_result_record(row) for row in report.rows], RESULT_COLUMNS)
    paths = [path]
    if report.atari100k:
        path = out_dir / ATARI100K_CSV
        _write_csv(path, [atari100k_record(row) for row in report.atari100k], ATARI100K_COLUMNS)
        paths.append(path)
    if report.summary:
        path = out_dir / SUMMARY_CSV
        _write_csv(path, [_summary_record(row) for row in report.summary], SUMMARY_COLUMNS)
        paths.append(path)
    return paths


def send_to_wandb(report: Report, echo: Callable[[str], object] | None = None) -> None:
    """Each run of the report that logs to W&B gets in its W&B run's summary its final
    evaluation and the report's figures of it: its game's learning curves and, where
    inspected, its Q-values overview (nothing for the others)."""
    for run in report.runs:
        media: dict[str, Path] = {}
        for curve in report.curves:
            pictures = [path for path in curve.files if path.suffix == ".png"]
            if curve.game == run.config.env and pictures:
                media["report/learning_curves"] = pictures[0]
        for item in report.inspections:
            if item.run_dir == run.run_dir and item.inspection.overview_path is not None:
                media["report/q_values"] = item.inspection.overview_path
        values = final_evaluation_values(run.final_evaluation) if run.final_evaluation else {}
        if add_to_summary(run.run_dir, values, media) and echo is not None:
            echo(f"dqnlab: {run.run_dir}: final evaluation and figures sent to its W&B run")


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
    run into its own `out_dir`/RUN directory (`inspection.write.inspect_run`). A run that
    cannot be inspected gets a note instead."""
    from dqnlab.analysis.inspection.write import inspect_run

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
    return _unique(name, taken)


def _unique(name: str, taken: set[str]) -> str:
    """`name`, else `name-2`, `name-3`...: the first not in `taken`, which it is added to."""
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
    older network than the run's `final_eval_network` now (the run trained on after it
    was played)."""
    evaluated = []
    for run in runs:
        if _scored_when_finished(run):
            continue
        if lease_is_live(run.run_dir):  # trained or playing its final evaluation right now
            notes.append(
                f"{run.run_dir}: another process holds it now (training, or playing its final "
                "evaluation): its final evaluation is not played here"
            )
            continue
        kind = run.config.final_eval_network  # best, or last (Atari 100k)
        network_step = rundir.network_step(run.run_dir, kind)
        saved = run.final_evaluation
        saved_step = saved.get("checkpoint_step") if saved is not None else None
        stale = saved_step is not None and network_step is not None and saved_step != network_step
        if saved is not None and not stale:
            continue
        why = (
            f"its final evaluation is of the {kind} network at step {saved_step}, the {kind} "
            f"is now the one at step {network_step}"
            if stale
            else "no final evaluation"
        )
        if network_step is None:
            notes.append(f"{run.run_dir}: {why} and no {kind} network yet: not in the table")
        elif evaluate_missing is None:
            if stale:
                notes.append(f"{run.run_dir}: {why}; the table shows the older one")
            else:
                notes.append(f"{run.run_dir}: {why}: not in the table")
        else:
            if echo is not None:
                echo(f"dqnlab: {run.run_dir}: {why}: evaluating its {kind} network")
            run.final_evaluation = evaluate_missing(run.run_dir)
            evaluated.append(run.run_dir)
    return evaluated


def _training_notes(runs: Sequence[RunResults]) -> list[str]:
    """A note for each run still training: how far it is and what its scores are of."""
    notes = []
    for run in runs:
        if _scored_when_finished(run):
            notes.append(
                f"{run.run_dir}: training (newest checkpoint at step {run.steps} of "
                f"{run.config.total_steps}): its protocol scores the last network once "
                "trained, so it is not in the tables yet"
            )
        elif not run.finished:
            notes.append(
                f"{run.run_dir}: unfinished (newest checkpoint at step {run.steps} of "
                f"{run.config.total_steps}): its scores are of its best network so far"
            )
    return notes


def _scored_when_finished(run: RunResults) -> bool:
    """Whether `run` is still training under a protocol that scores its last network
    (Atari 100k's): a network halfway through is not what the benchmark scores, so the
    report neither plays nor shows its final evaluation until training is done."""
    return run.config.final_eval_network == "last" and not run.finished


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


def _save_figure(figure: Figure, stem: Path) -> list[Path]:
    """`figure` as STEM.png and STEM.svg (without a date, so that a report written again
    from the same runs gives the same file)."""
    paths = []
    options: dict[str, dict[str, Any]] = {
        ".png": {"dpi": 150},
        ".svg": {"metadata": {"Date": None}},
    }
    for suffix in FIGURES:
        path = stem.with_name(stem.name + suffix)
        figure.savefig(path, **options[suffix])
        paths.append(path)
    return paths


def _write_aggregates(aggregates: Aggregates, out_dir: Path) -> list[Path]:
    """The aggregates' figures and CSV files (the probabilities of improvement with two
    configurations or more), recorded in `aggregates.files`."""
    aggregates.files += _save_figure(interval_figure(aggregates), out_dir / AGGREGATES_FIGURE)
    aggregates.files += _save_figure(profile_figure(aggregates), out_dir / PROFILES_FIGURE)
    path = out_dir / AGGREGATES_CSV
    _write_csv(path, _aggregate_records(aggregates), AGGREGATE_COLUMNS)
    aggregates.files.append(path)
    if aggregates.improvements:
        path = out_dir / IMPROVEMENT_CSV
        _write_csv(path, _improvement_records(aggregates), IMPROVEMENT_COLUMNS)
        aggregates.files.append(path)
    return aggregates.files


def _write_csv(path: Path, records: list[dict[str, Any]], columns: Sequence[str]) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, lineterminator="\n")
        writer.writeheader()
        for record in records:
            writer.writerow({k: "" if v is None else v for k, v in record.items()})
