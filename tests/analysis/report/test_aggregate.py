"""Aggregates across games: the numbers against hand computations and against rliable
called directly, the notes on input they cannot use, the figures, and a written report.

Runs are made up (a config.toml and a final evaluation, nothing trained), and every
bootstrap is small: rliable's percentile intervals are reproduced exactly with the same
seed and repetitions, whatever their number.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rliable import library, metrics

from dqnlab.analysis.report import (
    DEFAULT_BOOTSTRAP_REPETITIONS,
    DEFAULT_BOOTSTRAP_SEED,
    AggregateSettings,
    RunResults,
    aggregate_statistics,
    format_markdown,
    format_table,
    group_runs,
    load_reference_scores,
    probability_of_improvement,
    score_matrices,
    write_report,
)
from dqnlab.analysis.report.aggregate import profile_thresholds
from dqnlab.config import resolve_config
from dqnlab.errors import DqnlabError
from dqnlab.run.logs import read_csv
from dqnlab.run.rundir import save_final_evaluation, write_run_config
from tests.analysis.report.common import BREAKOUT, PONG, hns

REPETITIONS = 200
SEED = 7
SMALL = AggregateSettings(bootstrap_repetitions=REPETITIONS, bootstrap_seed=SEED)
# Runs x games, percent. Sorted, the eight scores are 10 20 50 60 90 150 300 500; the
# games' means 30 75 85 400.
SCORES = np.array([[10.0, 90.0, 20.0, 300.0], [50.0, 60.0, 150.0, 500.0]])
GAMES = ("a", "b", "c", "d")
# Five runs of six games: enough distinct resamples that the seed moves the bounds.
WIDE = np.random.default_rng(1).lognormal(4.0, 1.0, size=(5, 6)).round(1)
WIDE_GAMES = tuple("abcdef")


def _bounds(points_and_intervals: tuple[dict[str, Any], dict[str, Any]]) -> tuple[float, float]:
    low, high = np.ravel(points_and_intervals[1]["x"])
    return float(low), float(high)


# The statistics --------------------------------------------------------------------------


def test_point_estimates_worked_out_by_hand() -> None:
    (item,) = aggregate_statistics({"x": SCORES}, GAMES, SMALL).configurations
    assert item.iqm.estimate == pytest.approx((50 + 60 + 90 + 150) / 4)  # the middle four
    assert item.median.estimate == pytest.approx((75 + 85) / 2)
    assert item.mean.estimate == pytest.approx((30 + 75 + 85 + 400) / 4)
    # Clipped at human (100): 10 90 20 100 50 60 100 100, mean 66.25.
    assert item.optimality_gap.estimate == pytest.approx(100 - 66.25)
    assert item.seeds_per_game == 2 and item.resampled == "runs"
    for name in ("iqm", "median", "mean", "optimality_gap"):
        interval = item.statistic(name)
        assert interval.low <= interval.estimate <= interval.high
        assert interval.low < interval.high


def test_intervals_are_rliables_with_the_same_seed_and_repetitions() -> None:
    state = np.random.get_state()
    (item,) = aggregate_statistics({"x": WIDE}, WIDE_GAMES, SMALL).configurations
    assert np.array_equal(np.random.get_state()[1], state[1])  # numpy's global state kept

    def iqm(scores: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(scores)])

    np.random.seed(SEED)
    expected = _bounds(library.get_interval_estimates({"x": WIDE}, iqm, reps=REPETITIONS))
    assert (item.iqm.low, item.iqm.high) == pytest.approx(expected)
    # rliable's fractions (1 = human, its default threshold 1) give the same gap / 100.
    np.random.seed(SEED)
    gap = _bounds(
        library.get_interval_estimates(
            {"x": WIDE / 100},
            lambda scores: np.array([metrics.aggregate_optimality_gap(scores)]),
            reps=REPETITIONS,
        )
    )
    assert (item.optimality_gap.low, item.optimality_gap.high) == pytest.approx(
        (100 * gap[0], 100 * gap[1])
    )
    # The seed is used: another one moves the bounds.
    other = AggregateSettings(bootstrap_repetitions=REPETITIONS, bootstrap_seed=SEED + 1)
    (moved,) = aggregate_statistics({"x": WIDE}, WIDE_GAMES, other).configurations
    assert (moved.iqm.low, moved.iqm.high) != (item.iqm.low, item.iqm.high)


def test_probability_of_improvement_worked_out_by_hand() -> None:
    x = np.array([[1.0, 5.0], [3.0, 7.0]])
    y = np.array([[2.0, 5.0], [0.0, 9.0]])
    # First game: 1 beats 0 only, 3 beats both: 3/4. Second: 5 ties 5 (half), 7 beats 5:
    # 1.5/4. Their mean: 0.5625.
    assert probability_of_improvement(x, y)[0] == pytest.approx(0.5625)
    assert metrics.probability_of_improvement(x, y) == pytest.approx(0.5625)
    aggregates = aggregate_statistics({"x": x, "y": y}, ("a", "b"), SMALL)
    forward, backward = aggregates.improvements
    assert (forward.configuration, forward.other) == ("x", "y")
    assert forward.probability.estimate == pytest.approx(0.5625)
    assert backward.probability.estimate == pytest.approx(1 - 0.5625)
    assert backward.probability.low == pytest.approx(1 - forward.probability.high)
    assert backward.probability.high == pytest.approx(1 - forward.probability.low)
    # The interval is rliable's, with rliable's own (slow) statistic.
    x, y = WIDE[:, :3], WIDE[::-1, 3:]
    (forward, _) = aggregate_statistics({"x": x, "y": y}, ("a", "b", "c"), SMALL).improvements
    np.random.seed(SEED)
    expected = _bounds(
        library.get_interval_estimates(
            {"x": [x, y]}, metrics.probability_of_improvement, reps=REPETITIONS
        )
    )
    assert (forward.probability.low, forward.probability.high) == pytest.approx(expected)
    assert forward.probability.low < forward.probability.high


def test_probability_of_improvement_equals_rliables_with_ties_and_unequal_runs() -> None:
    generator = np.random.default_rng(0)
    for runs, other_runs in ((3, 3), (2, 5), (4, 1)):
        x = generator.integers(0, 4, size=(runs, 6)).astype(float)  # few values: ties
        y = generator.integers(0, 4, size=(other_runs, 6)).astype(float)
        expected = metrics.probability_of_improvement(x, y)
        assert probability_of_improvement(x, y)[0] == pytest.approx(expected)
    same = generator.normal(size=(3, 4))
    assert probability_of_improvement(same, same)[0] == 0.5


def test_performance_profile_is_rliables_score_distribution() -> None:
    (profile,) = aggregate_statistics({"x": SCORES}, GAMES, SMALL).profiles
    thresholds = np.linspace(0, 500, 161)  # to the highest score (below 800), 3.125 apart
    # Scores 50, 150, 300 and 500 lie on thresholds: "above" is strict.
    expected = library.score_distributions(SCORES, thresholds)
    assert np.array_equal(profile.fraction, expected)
    assert profile.fraction[16] == 5 / 8 and profile.fraction[32] == 3 / 8  # 50 and 100
    assert profile.fraction[0] == 1.0 and profile.fraction[-1] == 0.0
    # The bands are rliable's default profile's, with the same seed.
    aggregates = aggregate_statistics({"x": WIDE}, WIDE_GAMES, SMALL)
    thresholds = np.array(aggregates.thresholds)
    assert (thresholds[0], thresholds[-1]) == (0, WIDE.max())
    np.random.seed(SEED)
    fractions, intervals = library.create_performance_profile(
        {"x": WIDE}, thresholds, reps=REPETITIONS
    )
    (profile,) = aggregates.profiles
    assert profile.fraction == pytest.approx(fractions["x"])
    assert profile.low == pytest.approx(intervals["x"][0])
    assert profile.high == pytest.approx(intervals["x"][1])
    # From the lowest score where it is below 0, to at least human and at most 8 x human.
    assert profile_thresholds([np.array([[-20.0, 2000.0]])])[[0, -1]].tolist() == [-20, 800]
    assert profile_thresholds([np.array([[10.0, 50.0]])])[[0, -1]].tolist() == [0, 100]


def test_settings_are_checked_and_the_command_line_shares_their_defaults() -> None:
    with pytest.raises(DqnlabError, match="human_nature"):
        AggregateSettings(baseline="nature")
    with pytest.raises(DqnlabError, match="positive"):
        AggregateSettings(bootstrap_repetitions=0)
    with pytest.raises(DqnlabError, match="seed"):
        AggregateSettings(bootstrap_seed=-1)
    from dqnlab.cli.results import report

    defaults = inspect.signature(report).parameters
    assert defaults["bootstrap_reps"].default == DEFAULT_BOOTSTRAP_REPETITIONS
    assert defaults["bootstrap_seed"].default == DEFAULT_BOOTSTRAP_SEED
    assert defaults["baseline"].default == AggregateSettings().baseline


# Which scores: notes on what cannot be used ----------------------------------------------


def _run(env: str, seed: int, mean: float, **settings: Any) -> RunResults:
    preset = "nature" if env in ("pong", "breakout", "seaquest", "surround") else "classic"
    config = resolve_config(preset, env=env, seed=seed, **settings)
    final = {"mean": mean, "std": 0.0, "episodes": 1}
    return RunResults(Path(f"runs/{env}-{settings}-s{seed}"), config, [], final)


def _matrices(runs: list[RunResults], baseline: str = "human") -> Any:
    return score_matrices(group_runs(runs), load_reference_scores(), baseline)


def test_a_single_game_has_no_aggregates_and_says_why() -> None:
    games, matrices, notes = _matrices([_run("pong", 0, -10.0), _run("pong", 1, 0.0)])
    assert games == () and matrices == {}
    assert notes == [
        "no aggregates across games: they need human-normalised scores of two games or more, "
        "and only pong has them"
    ]


def test_non_atari_runs_are_left_out_with_a_note() -> None:
    runs = [_run("CartPole-v1", 0, 200.0), _run("pong", 0, -10.0), _run("breakout", 0, 20.0)]
    games, matrices, notes = _matrices(runs)
    assert games == ("pong", "breakout")
    assert any(note.startswith("aggregates across games: CartPole-v1 left out") for note in notes)
    games, matrices, notes = _matrices(runs[:1])
    assert matrices == {} and any("no run has one" in note for note in notes)


def test_nature_baseline_uses_the_nature_human_and_leaves_out_games_without_it() -> None:
    runs = [_run("pong", 0, -10.0), _run("breakout", 0, 20.0), _run("surround", 0, 0.0)]
    games, matrices, notes = _matrices(runs, "human_nature")
    assert games == ("pong", "breakout")
    (matrix,) = matrices.values()
    expected = [hns(-10.0, PONG, "human_nature"), hns(20.0, BREAKOUT, "human_nature")]
    assert matrix.tolist() == [pytest.approx(expected)]
    assert any("surround left out: no Nature human score" in note for note in notes)
    games, _, _ = _matrices(runs, "human")
    assert games == ("pong", "breakout", "surround")  # dqn_zoo's covers all 57


def test_one_seed_per_game_resamples_the_games() -> None:
    runs = [_run("pong", 0, -10.0), _run("breakout", 0, 20.0), _run("seaquest", 0, 3000.0)]
    games, matrices, notes = _matrices(runs)
    assert any("one seed per game" in note and "resample the games" in note for note in notes)
    (item,) = aggregate_statistics(matrices, games, SMALL).configurations
    assert item.resampled == "games" and item.mean.low < item.mean.high
    np.random.seed(SEED)
    expected = library.get_interval_estimates(
        {"x": matrices["all settings equal"]},
        lambda scores: np.array([metrics.aggregate_mean(scores)]),
        task_bootstrap=True,
        reps=REPETITIONS,
    )
    assert (item.mean.low, item.mean.high) == pytest.approx(_bounds(expected))


def test_unequal_seeds_keep_the_lowest_common_number_per_game() -> None:
    runs = [_run("pong", seed, -10.0 + seed) for seed in (2, 0, 1)]
    runs += [_run("breakout", seed, 20.0 + seed) for seed in (0, 1)]
    games, matrices, notes = _matrices(runs)
    (matrix,) = matrices.values()
    assert matrix.shape == (2, 2)  # runs x games
    assert matrix[:, 0] == pytest.approx([hns(-10.0, PONG, "human"), hns(-9.0, PONG, "human")])
    (note,) = [note for note in notes if "left out" in note]
    assert "keeps its 2 run(s) of lowest seed" in note and note.endswith("s2")


def test_configurations_are_compared_over_the_games_they_share() -> None:
    runs = [
        _run(game, 0, score, learning_rate=rate)
        for game, score in (("pong", 0.0), ("breakout", 10.0), ("seaquest", 500.0))
        for rate in (0.00025, 0.0001)
        if not (game == "seaquest" and rate == 0.0001)
    ]
    games, matrices, notes = _matrices(runs)
    assert games == ("pong", "breakout") and len(matrices) == 2
    assert all(matrix.shape == (1, 2) for matrix in matrices.values())
    assert any("seaquest (only learning_rate=0.00025) left out" in note for note in notes)
    shared = [run for run in runs if run.config.env != "breakout"]
    _, matrices, notes = _matrices(shared + [_run("breakout", 0, 10.0, learning_rate=0.00025)])
    assert matrices == {} and any("fewer than two games in common" in note for note in notes)


# A written report -------------------------------------------------------------------------

# Final-evaluation means: game -> learning rate -> seeds 0 and 1.
MEANS = {
    "pong": {0.00025: [-5.0, 3.0], 0.0001: [-15.0, -12.0]},
    "breakout": {0.00025: [40.0, 25.0], 0.0001: [12.0, 20.0]},
}


def _fake_runs(root: Path) -> Path:
    """Two games x two learning rates x two seeds: a config.toml and a final evaluation."""
    for game, by_rate in MEANS.items():
        for rate, means in by_rate.items():
            for seed, mean in enumerate(means):
                run_dir = root / f"{game}-lr{rate}-s{seed}"
                run_dir.mkdir(parents=True)
                config = resolve_config("nature", env=game, seed=seed, learning_rate=rate)
                write_run_config(run_dir, config)
                record = {"mean": mean, "std": 1.0, "episodes": 2, "checkpoint_step": 100}
                save_final_evaluation(run_dir, record)
    return root


def test_a_report_writes_the_aggregate_section_csv_files_and_figures(tmp_path: Path) -> None:
    sweep = _fake_runs(tmp_path / "sweep")
    out = tmp_path / "out"
    report = write_report([sweep], out, aggregate=SMALL)
    aggregates = report.aggregates
    assert aggregates is not None and aggregates.games == ("breakout", "pong")
    names = ["learning_rate=0.0001", "learning_rate=0.00025"]
    assert [item.configuration for item in aggregates.configurations] == names
    slow = aggregates.scores["learning_rate=0.0001"]
    assert slow[:, 1].tolist() == pytest.approx([hns(m, PONG, "human") for m in (-15.0, -12.0)])
    # Median and mean of the game means: the summary across games, over the same runs.
    for row in report.summary:
        (item,) = [i for i in aggregates.configurations if i.configuration == row.configuration]
        if row.baseline == "human":
            assert item.statistic(row.statistic).estimate == pytest.approx(row.hns)
    # Every run of the faster rate beats every run of the slower on both games.
    better = {(i.configuration, i.other): i.probability for i in aggregates.improvements}
    assert better["learning_rate=0.00025", "learning_rate=0.0001"].estimate == 1.0
    assert better["learning_rate=0.0001", "learning_rate=0.00025"].estimate == 0.0

    written = sorted(path.name for path in aggregates.files)
    assert written == [
        "aggregates.csv", "aggregates.png", "aggregates.svg", "performance-profiles.png",
        "performance-profiles.svg", "probability-of-improvement.csv",
    ]  # fmt: skip
    assert all(path in report.files for path in aggregates.files)
    records = read_csv(out / "aggregates.csv")
    assert len(records) == 4 * 2
    (iqm,) = [r for r in records if r["statistic"] == "iqm" and r["configuration"] == names[0]]
    assert float(iqm["estimate_percent"]) == pytest.approx(
        aggregates.configurations[0].iqm.estimate
    )
    assert float(iqm["low_percent"]) == pytest.approx(aggregates.configurations[0].iqm.low)
    assert (iqm["baseline"], iqm["games"], iqm["seeds_per_game"]) == ("human", "2", "2")
    assert (iqm["bootstrap_repetitions"], iqm["bootstrap_seed"]) == (str(REPETITIONS), str(SEED))
    improvements = read_csv(out / "probability-of-improvement.csv")
    assert [(r["configuration"], r["other"], float(r["probability"])) for r in improvements] == [
        (names[0], names[1], 0.0),
        (names[1], names[0], 1.0),
    ]

    markdown = (out / "results.md").read_text()
    assert markdown == format_markdown(report, out)
    section = markdown[markdown.index("## Aggregates across games") :]
    assert "HNS % (dqn_zoo human)" in section.splitlines()[2]
    assert f"{REPETITIONS} repetitions, seed {SEED}" in section
    interval = aggregates.configurations[1].iqm
    assert f"| {interval.estimate:.1f} [{interval.low:.1f}, {interval.high:.1f}] |" in section
    assert "![aggregates](aggregates.png)" in section
    assert "![performance-profiles](performance-profiles.png)" in section
    assert f"| {names[1]} | {names[0]} | 1.00 [1.00, 1.00] | runs within games |" in section
    assert "Edge of the Statistical Precipice" in markdown  # the legend's source
    console = format_table(report)
    assert "Aggregates across 2 games, HNS % (dqn_zoo human)" in console
    assert "Probability of improvement of X over Y" in console

    # The figures, read back from their SVG: names, the baseline, labels, one bar per
    # configuration and statistic, one profile line per configuration.
    intervals = (out / "aggregates.svg").read_text()
    for text in (*names, "IQM", "Median", "Mean", "Optimality gap (lower is better)"):
        assert f"<!-- {text} -->" in intervals
    assert "<!-- HNS % (dqn_zoo human) -->" in intervals
    assert f"{REPETITIONS} repetitions, seed {SEED}" in intervals
    for statistic in ("iqm", "median", "mean", "optimality_gap"):
        assert intervals.count(f'id="interval-{statistic}-') == 2
    profiles = (out / "performance-profiles.svg").read_text()
    assert profiles.count('id="profile-') == 2
    for text in (f"{names[0]} (4 runs)", f"{names[1]} (4 runs)", "dqn_zoo human"):
        assert f"<!-- {text} -->" in profiles
    assert "<!-- fraction of runs with score &gt; τ -->" in profiles
    assert "<!-- human-normalised score τ, % of dqn_zoo human -->" in profiles
    assert all((out / name).read_bytes().startswith(b"\x89PNG") for name in written[1:4:2])

    # Nature's human baseline, asked for: named in the figures and files; then a report
    # of one game removes the aggregates' files the earlier reports wrote.
    nature = AggregateSettings("human_nature", REPETITIONS, SEED)
    write_report([sweep], out, aggregate=nature)
    assert "<!-- HNS % (Nature human) -->" in (out / "aggregates.svg").read_text()
    assert "Nature human" in (out / "performance-profiles.svg").read_text()
    assert {r["baseline"] for r in read_csv(out / "aggregates.csv")} == {"human_nature"}
    single = write_report(sorted(sweep.glob("pong-*")), out, aggregate=SMALL)
    assert single.aggregates is None
    assert not any((out / name).exists() for name in written)
    assert "## Aggregates across games" not in (out / "results.md").read_text()
    assert any("only pong has them" in note for note in single.notes)
