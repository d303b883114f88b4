"""Tables: what a report holds (`Report`), and its forms as text: the CSV records and
their columns, the console table and results.md with its legend (`legend.py`), the
aggregates across games among them. Text only: `write.py` writes the files.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dqnlab.analysis.report.aggregate import (
    CONFIDENCE,
    RESAMPLED_GAMES,
    STATISTIC_NAMES,
    STATISTICS,
    Aggregates,
    Interval,
)
from dqnlab.analysis.report.atari100k import Atari100kRow, atari100k_cells, atari100k_markdown
from dqnlab.analysis.report.curves import Curve, _count_text
from dqnlab.analysis.report.legend import LEGEND, ON_TRACK_TEXT
from dqnlab.analysis.report.reference import (
    AGENTS,
    REFERENCE_PROTOCOL,
    WINDOW_FRAMES,
    OnTrackRow,
)
from dqnlab.analysis.report.runs import Group, RunResults
from dqnlab.analysis.report.scores import BASELINES, ResultRow, SummaryRow

if TYPE_CHECKING:
    from dqnlab.analysis.inspection.qvalues import Inspection

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
    on_track: list[OnTrackRow] = field(default_factory=list)
    aggregates: Aggregates | None = None  # two games or more with human-normalised scores
    atari100k: list[Atari100kRow] = field(default_factory=list)  # --reference der-paper


@dataclass
class RunInspection:
    """The Q-value inspection of one run's networks written with the report."""

    run_dir: Path
    out_dir: Path
    inspection: Inspection


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


# Aggregates across games: a table of the configurations, one of the probabilities of
# improvement (two configurations or more), each with a caption naming the baseline and
# the bootstrap.

AGGREGATE_COLUMNS = (
    "statistic", "configuration", "baseline", "games", "game_ids", "seeds_per_game",
    "resampled", "estimate_percent", "low_percent", "high_percent", "confidence",
    "bootstrap_repetitions", "bootstrap_seed",
)  # fmt: skip
IMPROVEMENT_COLUMNS = (
    "configuration", "other", "baseline", "games", "game_ids", "seeds_per_game",
    "other_seeds_per_game", "resampled", "probability", "low", "high", "confidence",
    "bootstrap_repetitions", "bootstrap_seed",
)  # fmt: skip
AGGREGATE_HEADERS = ("Configuration", "Seeds/game", "Resampled") + tuple(
    STATISTIC_NAMES[name] for name in STATISTICS
)
IMPROVEMENT_HEADERS = ("X", "Y", "P(X > Y)", "Resampled")


def _aggregate_records(aggregates: Aggregates) -> list[dict[str, Any]]:
    """One record per statistic and configuration, with the bootstrap behind it."""
    return [
        {
            "statistic": statistic,
            "configuration": item.configuration,
            **_aggregate_common(aggregates),
            "seeds_per_game": item.seeds_per_game,
            "resampled": item.resampled,
            "estimate_percent": item.statistic(statistic).estimate,
            "low_percent": item.statistic(statistic).low,
            "high_percent": item.statistic(statistic).high,
            **_bootstrap_common(aggregates),
        }
        for statistic in STATISTICS
        for item in aggregates.configurations
    ]


def _improvement_records(aggregates: Aggregates) -> list[dict[str, Any]]:
    seeds = {item.configuration: item.seeds_per_game for item in aggregates.configurations}
    return [
        {
            "configuration": item.configuration,
            "other": item.other,
            **_aggregate_common(aggregates),
            "seeds_per_game": seeds[item.configuration],
            "other_seeds_per_game": seeds[item.other],
            "resampled": item.resampled,
            "probability": item.probability.estimate,
            "low": item.probability.low,
            "high": item.probability.high,
            **_bootstrap_common(aggregates),
        }
        for item in aggregates.improvements
    ]


def _aggregate_common(aggregates: Aggregates) -> dict[str, Any]:
    return {
        "baseline": aggregates.baseline,
        "games": len(aggregates.games),
        "game_ids": ";".join(aggregates.games),
    }


def _bootstrap_common(aggregates: Aggregates) -> dict[str, Any]:
    return {
        "confidence": CONFIDENCE,
        "bootstrap_repetitions": aggregates.bootstrap_repetitions,
        "bootstrap_seed": aggregates.bootstrap_seed,
    }


def _interval_text(interval: Interval, digits: int = 1) -> str:
    return f"{interval.estimate:.{digits}f} [{interval.low:.{digits}f}, {interval.high:.{digits}f}]"


def _resampled_text(resampled: str) -> str:
    return "games" if resampled == RESAMPLED_GAMES else "runs within games"


def _aggregate_cells(aggregates: Aggregates) -> list[list[str]]:
    return [
        [item.configuration, str(item.seeds_per_game), _resampled_text(item.resampled)]
        + [_interval_text(item.statistic(statistic)) for statistic in STATISTICS]
        for item in aggregates.configurations
    ]


def _improvement_cells(aggregates: Aggregates) -> list[list[str]]:
    return [
        [
            item.configuration,
            item.other,
            _interval_text(item.probability, digits=2),
            _resampled_text(item.resampled),
        ]
        for item in aggregates.improvements
    ]


def _aggregate_caption(aggregates: Aggregates) -> str:
    return (
        f"Aggregates across {len(aggregates.games)} games, HNS % ({aggregates.baseline_name}): "
        f"estimate [interval]; {aggregates.bootstrap_text}"
    )


def _improvement_caption(aggregates: Aggregates) -> str:
    return (
        f"Probability of improvement of X over Y, HNS % ({aggregates.baseline_name}) over the "
        f"same {len(aggregates.games)} games: estimate [interval]; {aggregates.bootstrap_text}"
    )


def _aggregate_text(aggregates: Aggregates) -> str:
    text = _aggregate_caption(aggregates) + "\n"
    text += _aligned(AGGREGATE_HEADERS, _aggregate_cells(aggregates))
    if aggregates.improvements:
        text += "\n\n" + _improvement_caption(aggregates) + "\n"
        text += _aligned(IMPROVEMENT_HEADERS, _improvement_cells(aggregates))
    return text


def _aggregate_markdown(aggregates: Aggregates, out_dir: Path | None) -> list[str]:
    parts = ["## Aggregates across games", "", _aggregate_caption(aggregates) + ".", ""]
    parts += [f"Games: {', '.join(aggregates.games)}.", ""]
    parts += [_markdown_table(AGGREGATE_HEADERS, _aggregate_cells(aggregates)), ""]
    for path in aggregates.files:
        if path.suffix == ".png":
            link = path.name if out_dir is not None and path.parent == out_dir else str(path)
            parts += [f"![{path.stem}]({link})", ""]
    if aggregates.improvements:
        parts += ["### Probability of improvement", "", _improvement_caption(aggregates) + ".", ""]
        parts += [_markdown_table(IMPROVEMENT_HEADERS, _improvement_cells(aggregates)), ""]
    return parts


def _aligned(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    widths = [max(len(cell) for cell in column) for column in zip(headers, *rows, strict=True)]
    lines = [headers, ["-" * width for width in widths], *rows]
    return "\n".join(
        "  ".join(cell.ljust(width) for cell, width in zip(line, widths, strict=True)).rstrip()
        for line in lines
    )


ON_TRACK_HEADERS = (
    "Game", "Configuration", "Seed", "Trained", "Window", "Training games", "Mean score",
    "Reference", "Reference mean", "Reference range", "Verdict", "Latest evaluation",
)  # fmt: skip
ON_TRACK_TITLE = (
    f"Training games against Dopamine's curve of each run's agent; its {REFERENCE_PROTOCOL}"
)


def _on_track_cells(row: OnTrackRow, seed: int) -> list[str]:
    window = ""
    if row.window is not None:
        window = f"{row.window}–{row.window + 1}M frames"
        if not row.window_complete:
            window += f" (to {row.frames / WINDOW_FRAMES:.2f}M so far)"
    reference_range = (
        f"{_score_text(row.reference_low)} to {_score_text(row.reference_high)}"
        if row.reference_low is not None
        else ""
    )
    trained = f"{_count_text(row.steps)} steps, {_count_text(row.frames)} frames"
    return [
        row.game,
        row.configuration,
        str(seed),
        trained + ("" if row.finished else " (unfinished)"),
        window,
        str(row.games),
        _score_text(row.score),
        AGENTS[row.reference].name if row.reference is not None else "none",
        _score_text(row.reference_mean),
        reference_range,
        row.verdict or (row.why_none or ""),
        _score_text(row.last_eval_mean),
    ]


def _on_track_table(report: Report) -> tuple[Sequence[str], list[list[str]]]:
    seeds = {run.run_dir: run.config.seed for run in report.runs}
    return ON_TRACK_HEADERS, [_on_track_cells(row, seeds[row.run_dir]) for row in report.on_track]


def format_table(report: Report) -> str:
    """The results table (and the scores across games, and the on-track table) as aligned
    text for a terminal."""
    if report.rows:
        text = _aligned(TABLE_HEADERS, [_table_cells(row) for row in report.rows])
    else:
        text = "no run has a final evaluation: nothing to tabulate"
    if report.atari100k:
        text += "\n\nAtari 100k, against Data-Efficient Rainbow's published scores\n"
        text += _aligned(*atari100k_cells(report.atari100k))
    if report.summary:
        text += "\n\n" + _aligned(SUMMARY_HEADERS, _summary_cells(report.summary))
    if report.on_track:
        text += f"\n\nOn track? {ON_TRACK_TITLE}\n"
        text += _aligned(*_on_track_table(report))
    if report.aggregates is not None:
        text += "\n\n" + _aggregate_text(report.aggregates)
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
    parts += atari100k_markdown(report.atari100k)
    if report.summary:
        parts += ["## Across games", ""]
        parts += [_markdown_table(SUMMARY_HEADERS, _summary_cells(report.summary)), ""]
    if report.on_track:
        parts += ["## On track?", "", ON_TRACK_TEXT, ""]
        parts += [_markdown_table(*_on_track_table(report)), ""]
    if report.aggregates is not None:
        parts += _aggregate_markdown(report.aggregates, out_dir)
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
                kind = run.config.final_eval_network  # best, or last (Atari 100k)
                text = f"{score} over {final['episodes']} games, {kind} network of step {step}"
            cells.append([group.env, group.label, str(run.config.seed), str(run.run_dir), text])
    return cells
