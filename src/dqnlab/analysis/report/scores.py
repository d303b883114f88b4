"""Scores: the reference scores, human-normalised scores, the results table's rows and
the scores across games.

The human-normalised score is 100 × (score − random) / (human − random), given with two
human baselines (`data/README.md`): dqn_zoo's, the set DeepMind's later code uses, and
the Nature paper's own (Extended Data Table 2). They differ for 34 of the 49 games, so
only scores normalised by the same baseline can be compared.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from dqnlab.analysis.report.runs import Group

# Roderick, MacGlashan and Tellex 2017, "Implementing the Deep Q-Network", Table 1: their
# own implementation's mean score (± s.d.) over 30 games of the best network, Nature's
# final protocol. The only games they report.
SEED_PAPER_SCORES: dict[str, tuple[float, float]] = {
    "pong": (19.7, 1.1),
    "breakout": (339.3, 86.1),
    "seaquest": (6309.0, 1027.0),
}

# The two human baselines: dqn_zoo's and the Nature paper's (ED Table 2), and their
# names in tables and figures.
BASELINES = ("human", "human_nature")
BASELINE_NAMES = {"human": "dqn_zoo human", "human_nature": "Nature human"}


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


@dataclass(frozen=True)
class Atari100kScores:
    """One row of `data/atari100k_scores.csv`: a game of the Atari 100k benchmark, its random
    and human scores as Dopamine's `normalization_utils.py` gives them, and Data-Efficient
    Rainbow's published mean after 100k steps (van Hasselt et al. 2019)."""

    game: str  # as papers write it (RoadRunner)
    ale_name: str  # as ale-py and --env (road_runner)
    random: float
    human: float
    der: float


def load_atari100k_scores() -> dict[str, Atari100kScores]:
    """The 26 games of Atari 100k by ale-py name, in the file's (alphabetical) order."""
    text = (resources.files("dqnlab") / "data" / "atari100k_scores.csv").read_text()
    return {
        row["ale_name"]: Atari100kScores(
            row["game"], row["ale_name"], float(row["random"]), float(row["human"]),
            float(row["der"]),
        )
        for row in csv.DictReader(io.StringIO(text))
    }  # fmt: skip


def human_normalised(score: float, random: float, human: float | None) -> float | None:
    """100 × (score − random) / (human − random): 0 is random play, 100 the human's score."""
    if human is None:
        return None
    return 100.0 * (score - random) / (human - random)


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
