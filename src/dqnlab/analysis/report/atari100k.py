"""The Atari 100k benchmark in a report (`dqnlab report --reference der-paper`): each game's
final scores beside random, human and Data-Efficient Rainbow's published score, DER's
published scores as one more configuration of the aggregates across games, and the runs
that depart from the benchmark's protocol (`config.atari100k_departures`).

DER's published scores (van Hasselt, Hessel & Aslanides 2019, arXiv:1906.05243, as
`data/atari100k_scores.csv` gives them) are one number per game, the mean over the paper's
runs: as a configuration of the aggregates it has one "run" per game, so its intervals
resample the games, and its interquartile mean is the IQM of 26 per-game means, which is
not the IQM over per-run scores that rliable's papers report (those need every run's
score; the paper's per-run scores are not published).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from dqnlab.analysis.report.runs import Group, RunResults
from dqnlab.analysis.report.scores import Atari100kScores, human_normalised
from dqnlab.config import atari100k_departures

DER_PAPER = "DER (published)"
ATARI100K_COLUMNS = (
    "game", "configuration", "runs", "run_scores", "score_mean", "random", "human",
    "der_paper", "hns_percent", "der_paper_hns_percent",
)  # fmt: skip


@dataclass(frozen=True)
class Atari100kRow:
    """One game and configuration of the benchmark's table."""

    game: str  # ale-py's name
    title: str  # as papers write it
    configuration: str
    run_scores: tuple[float, ...]  # each run's final-evaluation mean, by seed
    score: float  # their mean
    random: float
    human: float
    der: float  # Data-Efficient Rainbow's published mean
    hns: float  # percent, of `score`
    der_hns: float  # percent, of `der`


def atari100k_rows(
    groups: Sequence[Group], scores: Mapping[str, Atari100kScores]
) -> list[Atari100kRow]:
    """One row per group of a benchmark game with a final evaluation, in the groups' order."""
    rows = []
    for group in groups:
        reference = scores.get(group.env)
        runs = sorted(
            (run for run in group.runs if run.final_evaluation is not None),
            key=lambda run: run.config.seed,
        )
        if reference is None or not runs:
            continue
        means = tuple(float(run.final_evaluation["mean"]) for run in runs)  # type: ignore[index]
        score = float(np.mean(means))
        rows.append(
            Atari100kRow(
                group.env, reference.game, group.label, means, score, reference.random,
                reference.human, reference.der, _hns(score, reference),
                _hns(reference.der, reference),
            )
        )  # fmt: skip
    return rows


def _hns(score: float, reference: Atari100kScores) -> float:
    value = human_normalised(score, reference.random, reference.human)
    assert value is not None  # every benchmark game has a human score
    return value


def published_matrix(games: Sequence[str], scores: Mapping[str, Atari100kScores]) -> np.ndarray:
    """DER's published scores of `games` as a 1 x games matrix of human-normalised percent,
    the shape of one configuration in the aggregates."""
    return np.array([[_hns(scores[game].der, scores[game]) for game in games]])


def protocol_notes(runs: Sequence[RunResults]) -> list[str]:
    """A note for each run that departs from the Atari 100k protocol, naming the settings."""
    notes = []
    for run in runs:
        departures = atari100k_departures(run.config)
        if departures:
            notes.append(
                f"{run.run_dir}: not the Atari 100k protocol ({'; '.join(departures)}): its "
                "scores are not comparable with the published Atari 100k scores"
            )
    return notes


def atari100k_record(row: Atari100kRow) -> dict[str, object]:
    """A row of atari100k.csv (`ATARI100K_COLUMNS`)."""
    return {
        "game": row.game,
        "configuration": row.configuration,
        "runs": len(row.run_scores),
        "run_scores": " ".join(f"{score:g}" for score in row.run_scores),
        "score_mean": row.score,
        "random": row.random,
        "human": row.human,
        "der_paper": row.der,
        "hns_percent": row.hns,
        "der_paper_hns_percent": row.der_hns,
    }


def atari100k_cells(rows: Sequence[Atari100kRow]) -> tuple[list[str], list[list[str]]]:
    """The per-game table for a terminal: headers and one row of cells per game."""
    headers = ["Game", "Configuration", "Runs", "Score", "DER (paper)", "HNS", "DER HNS"]
    cells = [
        [row.title, row.configuration, str(len(row.run_scores)), f"{row.score:.1f}",
         f"{row.der:g}", f"{row.hns / 100:.3f}", f"{row.der_hns / 100:.3f}"]
        for row in rows
    ]  # fmt: skip
    return headers, cells


def atari100k_markdown(rows: Sequence[Atari100kRow]) -> list[str]:
    """The benchmark's section of results.md: the per-game table, then the mean and median
    human-normalised score of each configuration and of DER's published scores over the
    same games."""
    if not rows:
        return []
    lines = [
        "## Atari 100k",
        "",
        "Each game's final score (the mean of each run's final evaluation; the runs' own "
        "means in brackets), beside random, human and Data-Efficient Rainbow's published "
        "mean after 100k steps (van Hasselt et al. 2019); human-normalised scores (HNS) "
        "as fractions, (score - random) / (human - random).",
        "",
        "| Game | Configuration | Runs | Score | Random | Human | DER (paper) | HNS | DER HNS |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in rows:
        runs = ", ".join(f"{score:.1f}" for score in row.run_scores)
        lines.append(
            f"| {row.title} | {row.configuration} | {len(row.run_scores)} | {row.score:.1f} "
            f"({runs}) | {row.random:g} | {row.human:g} | {row.der:g} | "
            f"{row.hns / 100:.3f} | {row.der_hns / 100:.3f} |"
        )
    lines += ["", "| Configuration | Games | Mean HNS | Median HNS | DER mean | DER median |"]
    lines += ["|---|---:|---:|---:|---:|---:|"]
    for configuration in dict.fromkeys(row.configuration for row in rows):
        mine = [row for row in rows if row.configuration == configuration]
        hns = np.array([row.hns for row in mine]) / 100
        der = np.array([row.der_hns for row in mine]) / 100
        lines.append(
            f"| {configuration} | {len(mine)} | {hns.mean():.3f} | {np.median(hns):.3f} | "
            f"{der.mean():.3f} | {np.median(der):.3f} |"
        )
    lines += [
        "",
        f"In the aggregates below, {DER_PAPER} is one score per game (the paper's mean over "
        "its runs): its intervals resample the games, and its IQM is the interquartile mean "
        "of per-game means, which is not the IQM over per-run scores of rliable's papers.",
        "",
    ]
    return lines
