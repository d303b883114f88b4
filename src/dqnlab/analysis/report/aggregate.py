"""Aggregates across games: the interquartile mean, median, mean and optimality gap of
each configuration's human-normalised scores with stratified bootstrap confidence
intervals, performance profiles, and the probability that one configuration improves on
another. The statistics of Agarwal et al., NeurIPS 2021, "Deep Reinforcement Learning at
the Edge of the Statistical Precipice", computed with their library, rliable.

Scores are in percent, as in the results table (100 = the human baseline). rliable's
papers use fractions (1 = human), so its optimality-gap threshold of 1 is 100 here.

Computing only: `aggregate_figures.py` draws them, `write.py` writes the files. rliable is
imported inside the functions that call it: importing it (arch, statsmodels, scipy.stats)
takes seconds, which every `dqnlab` command would otherwise pay.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dqnlab.analysis.report.runs import Group
from dqnlab.analysis.report.scores import (
    BASELINE_NAMES,
    BASELINES,
    ReferenceScores,
    human_normalised,
)
from dqnlab.errors import DqnlabError

# 10,000 rather than the 50,000 rliable defaults to: docs/benchmark.md's figures table gives the
# time for 57 games x 5 seeds x 2 configurations and how little the bounds move.
DEFAULT_BOOTSTRAP_REPETITIONS = 10_000
DEFAULT_BOOTSTRAP_SEED = 0
CONFIDENCE = 0.95
HUMAN_PERCENT = 100.0  # the optimality gap's threshold: the human baseline
# The performance profile's thresholds run from 0 (or the lowest score) to the highest
# score, at most 8 x human: beyond it few runs remain and the informative part, around
# the human score, would be squeezed into the left of the figure.
PROFILE_MAX_PERCENT = 800.0
PROFILE_THRESHOLDS = 161
STATISTICS = ("iqm", "median", "mean", "optimality_gap")
STATISTIC_NAMES = {
    "iqm": "IQM",
    "median": "Median",
    "mean": "Mean",
    "optimality_gap": "Optimality gap",
}
# What a bootstrap resamples: the runs within each game (rliable's stratified bootstrap),
# or the games, where a configuration has one run per game.
RESAMPLED_RUNS, RESAMPLED_GAMES = "runs", "games"


@dataclass(frozen=True)
class AggregateSettings:
    """How the aggregates are computed: the human baseline (`BASELINES`), and the
    bootstrap's repetitions and seed, stated with every interval."""

    baseline: str = "human"
    bootstrap_repetitions: int = DEFAULT_BOOTSTRAP_REPETITIONS
    bootstrap_seed: int = DEFAULT_BOOTSTRAP_SEED

    def __post_init__(self) -> None:
        if self.baseline not in BASELINES:
            raise DqnlabError(
                f"baseline {self.baseline!r} is not one of {', '.join(BASELINES)} "
                "(human: dqn_zoo's; human_nature: the Nature paper's tester)"
            )
        if self.bootstrap_repetitions < 1:
            raise DqnlabError(
                f"bootstrap repetitions {self.bootstrap_repetitions} must be positive"
            )
        if not 0 <= self.bootstrap_seed < 2**32:  # numpy's legacy seeding takes 32 bits
            raise DqnlabError(f"bootstrap seed {self.bootstrap_seed} must be in [0, 2**32)")


# What is computed -----------------------------------------------------------------------


@dataclass(frozen=True)
class Interval:
    """A point estimate and its confidence interval."""

    estimate: float
    low: float
    high: float


@dataclass(frozen=True)
class ConfigurationAggregate:
    """One configuration's four aggregates over the games, in percent."""

    configuration: str
    seeds_per_game: int  # the rows of its runs x games matrix
    resampled: str  # RESAMPLED_RUNS or RESAMPLED_GAMES
    iqm: Interval  # interquartile mean: the mean of the middle half of all run scores
    median: Interval  # of the games' mean scores
    mean: Interval  # of the games' mean scores
    optimality_gap: Interval  # how far the scores fall short of human: lower is better

    def statistic(self, name: str) -> Interval:
        interval: Interval = getattr(self, name)
        return interval


@dataclass(frozen=True)
class Improvement:
    """The probability of improvement of `configuration` over `other`: the chance that a
    run of `configuration` on a game scores higher than a run of `other` on that game,
    ties counting half, averaged over the games."""

    configuration: str
    other: str
    resampled: str
    probability: Interval


@dataclass(frozen=True)
class Profile:
    """One configuration's performance profile: at each threshold, the fraction of its
    runs (over all games) with a score above it, and that fraction's interval."""

    configuration: str
    fraction: tuple[float, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]


@dataclass
class Aggregates:
    """The aggregates of every configuration over the same games."""

    baseline: str  # one of BASELINES
    games: tuple[str, ...]
    scores: dict[str, np.ndarray]  # per configuration: runs x games, percent
    bootstrap_repetitions: int
    bootstrap_seed: int
    configurations: list[ConfigurationAggregate]
    improvements: list[Improvement]  # every ordered pair, two configurations or more
    thresholds: tuple[float, ...]  # of the profiles, percent
    profiles: list[Profile]
    files: list[Path] = field(default_factory=list)

    @property
    def baseline_name(self) -> str:
        return BASELINE_NAMES[self.baseline]

    @property
    def bootstrap_text(self) -> str:
        """How every interval was computed, for the captions of tables and figures."""
        return (
            f"{CONFIDENCE:.0%} confidence intervals, stratified bootstrap (rliable), "
            f"{self.bootstrap_repetitions:,} repetitions, seed {self.bootstrap_seed}"
        )


# Selecting the scores -------------------------------------------------------------------


def score_matrices(
    groups: Sequence[Group], references: Mapping[str, ReferenceScores], baseline: str
) -> tuple[tuple[str, ...], dict[str, np.ndarray], list[str]]:
    """The games and, per configuration, its runs x games matrix of human-normalised
    final-evaluation means (percent), with notes on what was left out and why.

    rliable takes a matrix per configuration, and comparing configurations (the
    probability of improvement pairs them game by game) needs the same games for each:
    the matrices hold the games that every configuration has a score of, and each game
    the same number of runs, the smallest a game has, keeping the runs of lowest seed.
    No matrices (and a note) when fewer than two games remain."""
    notes: list[str] = []
    cells, unscored = _normalised_scores(groups, references, baseline)
    name = BASELINE_NAMES[baseline]
    if unscored:
        notes.append(
            f"aggregates across games: {', '.join(unscored)} left out: no {name} score "
            + (
                "(the Nature human scores cover the Nature paper's 49 games; non-Atari "
                "environments and Gymnasium ids have none)"
                if baseline == "human_nature"
                else "(non-Atari environments and Gymnasium ids have none)"
            )
        )
    scored = list(dict.fromkeys(game for by_game in cells.values() for game in by_game))
    if len(scored) < 2:
        notes.append(
            "no aggregates across games: they need human-normalised scores of two games or "
            + (f"more, and only {scored[0]} has them" if scored else "more, and no run has one")
        )
        return (), {}, notes
    games = tuple(game for game in scored if all(game in by_game for by_game in cells.values()))
    if len(games) < len(scored):
        missing = [
            f"{game} (only {', '.join(c for c in cells if game in cells[c])})"
            for game in scored
            if game not in games
        ]
        notes.append(
            "aggregates across games: configurations are compared over the same games, "
            f"those every one of them has: {', '.join(missing)} left out; report a "
            "configuration's runs alone to aggregate it over all of its games"
        )
    if len(games) < 2:
        notes.append(
            "no aggregates across games: the configurations have fewer than two games in common"
        )
        return (), {}, notes
    matrices = {}
    for configuration, by_game in cells.items():
        matrices[configuration] = _runs_by_games(configuration, by_game, games, notes)
    return games, matrices, notes


# Per game: (seed, run directory, score) of a configuration's runs with a final evaluation.
_ByGame = dict[str, list[tuple[int, Path, float]]]


def _normalised_scores(
    groups: Sequence[Group], references: Mapping[str, ReferenceScores], baseline: str
) -> tuple[dict[str, _ByGame], list[str]]:
    """Per configuration, the human-normalised final-evaluation mean of every run that has
    one; and the games of the runs that have no score under `baseline` (left out)."""
    unscored: list[str] = []
    cells: dict[str, _ByGame] = {}
    for group in groups:
        reference = references.get(group.env)
        human = getattr(reference, baseline) if reference is not None else None
        runs = [run for run in group.runs if run.final_evaluation is not None]
        if reference is None or human is None:
            if runs and group.env not in unscored:
                unscored.append(group.env)
            continue
        for run in runs:
            assert run.final_evaluation is not None
            score = human_normalised(float(run.final_evaluation["mean"]), reference.random, human)
            assert score is not None
            by_game = cells.setdefault(group.label, {})
            by_game.setdefault(group.env, []).append((run.config.seed, run.run_dir, score))
    return cells, unscored


def _runs_by_games(
    configuration: str, by_game: _ByGame, games: Sequence[str], notes: list[str]
) -> np.ndarray:
    """One configuration's runs x games matrix: each game's runs of lowest seed, as many as
    the game with fewest has; notes on the runs left out and on a single seed."""
    seeds = min(len(by_game[game]) for game in games)
    left_out = []
    columns = []
    for game in games:
        by_seed = sorted(by_game[game], key=lambda cell: cell[0])  # stable: ties keep order
        columns.append([score for _, _, score in by_seed[:seeds]])
        left_out += [str(run_dir) for _, run_dir, _ in by_seed[seeds:]]
    if left_out:
        notes.append(
            f"aggregates across games, {configuration}: its games have different numbers "
            f"of seeds and rliable's bootstrap takes a runs x games matrix, so each game "
            f"keeps its {seeds} run(s) of lowest seed: left out {', '.join(left_out)}"
        )
    if seeds == 1:
        notes.append(
            f"aggregates across games, {configuration}: one seed per game, so its "
            "intervals resample the games (how much the aggregate depends on which games "
            "were played), not the runs (how it would vary with new seeds)"
        )
    return np.array(columns).T


def aggregate_scores(
    groups: Sequence[Group], references: Mapping[str, ReferenceScores], settings: AggregateSettings
) -> tuple[Aggregates | None, list[str]]:
    """`score_matrices`, then `aggregate_statistics` where there are any; with notes."""
    games, matrices, notes = score_matrices(groups, references, settings.baseline)
    if not matrices:
        return None, notes
    return aggregate_statistics(matrices, games, settings), notes


# The statistics -------------------------------------------------------------------------


def aggregate_statistics(
    scores: Mapping[str, np.ndarray], games: Sequence[str], settings: AggregateSettings
) -> Aggregates:
    """The aggregates, profiles and probabilities of improvement of the runs x games
    matrices `scores` (percent).

    Every bootstrap starts from `settings.bootstrap_seed`, so a configuration's intervals
    do not depend on which other configurations are reported with it. A configuration
    with one run per game resamples its games instead (rliable's `task_bootstrap`)."""
    repetitions, seed = settings.bootstrap_repetitions, settings.bootstrap_seed
    configurations = []
    for configuration, matrix in scores.items():
        estimates, low, high = _interval_estimates(
            matrix, _four_aggregates, repetitions, seed, over_games=len(matrix) == 1
        )
        intervals = {
            name: Interval(float(estimates[i]), float(low[i]), float(high[i]))
            for i, name in enumerate(STATISTICS)
        }
        configurations.append(
            ConfigurationAggregate(
                configuration,
                seeds_per_game=len(matrix),
                resampled=RESAMPLED_GAMES if len(matrix) == 1 else RESAMPLED_RUNS,
                **intervals,
            )
        )
    thresholds = profile_thresholds(scores.values())
    profiles = [
        _profile(configuration, matrix, thresholds, repetitions, seed)
        for configuration, matrix in scores.items()
    ]
    return Aggregates(
        baseline=settings.baseline,
        games=tuple(games),
        scores=dict(scores),
        bootstrap_repetitions=repetitions,
        bootstrap_seed=seed,
        configurations=configurations,
        improvements=_improvements(scores, repetitions, seed),
        thresholds=tuple(float(tau) for tau in thresholds),
        profiles=profiles,
    )


def _four_aggregates(scores: np.ndarray) -> np.ndarray:
    from rliable import metrics

    return np.array(
        [
            metrics.aggregate_iqm(scores),
            metrics.aggregate_median(scores),
            metrics.aggregate_mean(scores),
            metrics.aggregate_optimality_gap(scores, gamma=HUMAN_PERCENT),
        ]
    )


def probability_of_improvement(scores: np.ndarray, other: np.ndarray) -> np.ndarray:
    """rliable's `metrics.probability_of_improvement` of two runs x games matrices, as a
    one-element array, counted over all pairs of runs at once.

    rliable's own calls scipy's Mann-Whitney test once per game, which also works out a
    p-value it discards, and the bootstrap calls it games x repetitions times: minutes
    per pair of configurations over 57 games (docs/benchmark.md's figures table). The statistic
    it keeps, U / (runs x other runs), is the fraction of pairs of runs in which the
    first scores higher, ties counting half: the same number, from one array operation."""
    difference = scores[:, np.newaxis, :] - other[np.newaxis, :, :]  # run, other run, game
    per_game = np.mean((difference > 0) + 0.5 * (difference == 0), axis=(0, 1))
    return np.array([per_game.mean()])


def _improvements(
    scores: Mapping[str, np.ndarray], repetitions: int, seed: int
) -> list[Improvement]:
    """Both directions of every pair from one bootstrap: in every resample the probability
    of Y over X is 1 minus that of X over Y, so its interval is the mirror image."""
    found: dict[tuple[str, str], Improvement] = {}
    names = list(scores)
    for i, first in enumerate(names):
        for second in names[i + 1 :]:
            x, y = scores[first], scores[second]
            if min(len(x), len(y)) == 1:  # one run per game: resample the games
                per_game = [
                    probability_of_improvement(x[:, [game]], y[:, [game]])[0]
                    for game in range(x.shape[1])
                ]
                resampled = RESAMPLED_GAMES
                estimate, low, high = _interval_estimates(
                    np.array([per_game]), _mean, repetitions, seed, over_games=True
                )
            else:
                resampled = RESAMPLED_RUNS
                estimate, low, high = _interval_estimates(
                    [x, y], probability_of_improvement, repetitions, seed, over_games=False
                )
            p = Interval(float(estimate[0]), float(low[0]), float(high[0]))
            found[first, second] = Improvement(first, second, resampled, p)
            mirror = Interval(1.0 - p.estimate, 1.0 - p.high, 1.0 - p.low)
            found[second, first] = Improvement(second, first, resampled, mirror)
    return [found[x, y] for x in names for y in names if x != y]


def _mean(scores: np.ndarray) -> np.ndarray:
    return np.array([scores.mean()])


def profile_thresholds(matrices: Iterable[np.ndarray]) -> np.ndarray:
    """From 0 (or the lowest score, if below) to the highest score, at least the human
    score and at most PROFILE_MAX_PERCENT."""
    values = np.concatenate([matrix.ravel() for matrix in matrices])
    highest = min(max(float(values.max()), HUMAN_PERCENT), PROFILE_MAX_PERCENT)
    return np.linspace(min(0.0, float(values.min())), highest, PROFILE_THRESHOLDS)


def fraction_above(scores: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """rliable's score distribution (its default profile, one threshold at a time in
    `library.run_score_deviation`) for all thresholds at once: the fraction of the
    scores of all runs and games above each threshold."""
    above: np.ndarray = np.mean(scores[..., np.newaxis] > thresholds, axis=(0, 1))
    return above


def _profile(
    configuration: str, scores: np.ndarray, thresholds: np.ndarray, repetitions: int, seed: int
) -> Profile:
    from rliable import library

    with _numpy_global_seed(seed):
        fractions, intervals = library.create_performance_profile(
            {configuration: scores},
            thresholds,
            custom_profile_func=fraction_above,
            task_bootstrap=len(scores) == 1,
            reps=repetitions,
            confidence_interval_size=CONFIDENCE,
        )
    low, high = intervals[configuration]
    return Profile(
        configuration,
        tuple(float(value) for value in fractions[configuration]),
        tuple(float(value) for value in low),
        tuple(float(value) for value in high),
    )


def _interval_estimates(
    scores: np.ndarray | list[np.ndarray],
    statistic: Callable[..., np.ndarray],
    repetitions: int,
    seed: int,
    *,
    over_games: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """rliable's `library.get_interval_estimates` of one matrix (a list of matrices: each
    resampled independently): the estimates and their lower and upper bounds."""
    from rliable import library

    with _numpy_global_seed(seed):
        estimates, intervals = library.get_interval_estimates(
            {"scores": scores},
            statistic,
            task_bootstrap=over_games,
            reps=repetitions,
            confidence_interval_size=CONFIDENCE,
        )
    low, high = intervals["scores"]
    return np.atleast_1d(estimates["scores"]), np.atleast_1d(low), np.atleast_1d(high)


@contextmanager
def _numpy_global_seed(seed: int) -> Iterator[None]:
    """rliable's bootstrap draws its indices from numpy's global generator
    (`np.random.choice` in `StratifiedBootstrap.update_indices`), not from the
    `random_state` it takes (which arch 7 deprecates and arch 8 refuses): seeded here and
    restored afterwards, so the report neither depends on nor disturbs other draws."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)
