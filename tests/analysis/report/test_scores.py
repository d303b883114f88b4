"""The table's scores against values worked out by hand: seeds, budgets, human-normalised scores."""

from __future__ import annotations

import math

import pytest

from dqnlab.analysis.report import (
    ALL_EQUAL,
    Report,
    load_reference_scores,
)
from tests.analysis.report.common import (
    BREAKOUT,
    PONG,
    hns,
    row_of,
)


def test_reference_scores_ship_with_the_package() -> None:
    references = load_reference_scores()
    assert len(references) == 57
    pong = references["pong"]
    assert (pong.random, pong.human, pong.human_nature) == (-20.7, 14.6, 9.3)
    assert (pong.nature_dqn, pong.nature_dqn_std) == (18.9, 1.3)
    phoenix = references["phoenix"]  # outside the Nature 49: dqn_zoo's baselines only
    assert phoenix.human_nature is None and phoenix.nature_dqn is None
    assert phoenix.random == 761.4


def test_one_seed_is_its_mean_and_std_over_games_normalised_by_both_baselines(
    atari_report: Report,
) -> None:
    row = row_of(atari_report, "breakout")
    assert row.seeds == 1 and row.games_per_seed == (3, 3)
    assert row.score == pytest.approx(20.0)
    assert row.score_std == pytest.approx(math.sqrt(200 / 3))  # ddof 0 over 10, 20, 30
    assert row.score_std_over == "games"
    assert row.seed_score_min is None and row.seed_score_max is None
    # (20 - 1.7) / (30.5 - 1.7) and (20 - 1.7) / (31.8 - 1.7)
    assert row.hns_human == pytest.approx(100 * 18.3 / 28.8)
    assert row.hns_human_nature == pytest.approx(100 * 18.3 / 30.1)
    assert (row.nature_dqn, row.nature_dqn_std) == (401.2, 26.9)
    assert (row.seed_paper, row.seed_paper_std) == (339.3, 86.1)


def test_several_seeds_are_the_mean_of_seed_means_with_their_spread(
    atari_report: Report,
) -> None:
    row = row_of(atari_report, "pong")
    assert row.seeds == 2 and row.games_per_seed == (2, 2)
    # Seed means -20 and -11.
    assert row.score == pytest.approx(-15.5)
    assert row.score_std == pytest.approx(4.5)
    assert row.score_std_over == "seeds"
    assert (row.seed_score_min, row.seed_score_max) == (-20.0, -11.0)
    assert row.hns_human == pytest.approx(100 * 5.2 / 35.3)  # (-15.5 + 20.7) / (14.6 + 20.7)
    assert row.hns_human_nature == pytest.approx(100 * 5.2 / 30.0)  # ... / (9.3 + 20.7)
    assert row.hns_human == pytest.approx(hns(-15.5, PONG, "human"))
    assert row.nature_dqn_hns_human == pytest.approx(hns(18.9, PONG, "human"))
    assert (row.seed_paper, row.seed_paper_std) == (19.7, 1.1)
    assert row.total_steps == (200, 300)


def test_budgets_are_ignored_for_grouping_and_said_so(atari_report: Report) -> None:
    (pong,) = [group for group in atari_report.groups if group.env == "pong"]
    assert pong.label == ALL_EQUAL and len(pong.runs) == 2
    assert any("pong" in note and "training budgets differ" in note for note in atari_report.notes)


def test_median_and_mean_across_two_games_per_baseline(atari_report: Report) -> None:
    summary = {(row.statistic, row.baseline): row for row in atari_report.summary}
    assert set(summary) == {(s, b) for s in ("median", "mean") for b in ("human", "human_nature")}
    for baseline in ("human", "human_nature"):
        pong, breakout = hns(-15.5, PONG, baseline), hns(20.0, BREAKOUT, baseline)
        nature = (hns(18.9, PONG, baseline) + hns(401.2, BREAKOUT, baseline)) / 2
        for statistic in ("median", "mean"):  # of two values both are their mean
            row = summary[statistic, baseline]
            assert set(row.games) == {"pong", "breakout"}
            assert row.configuration == ALL_EQUAL
            assert row.hns == pytest.approx((pong + breakout) / 2)
            assert row.nature_dqn_hns == pytest.approx(nature)
