"""The Atari 100k report (`--reference der-paper`): the per-game table, the aggregates with
DER's published scores beside dqnlab's, and the note on a run off the protocol, from a
made-up sweep (a config.toml and a final evaluation per run, nothing trained) against
numbers worked out here by hand."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dqnlab.analysis.report import ALL_EQUAL, AggregateSettings, format_table, write_report
from dqnlab.analysis.report.atari100k import DER_PAPER
from dqnlab.config import resolve_config
from dqnlab.run.logs import read_csv
from dqnlab.run.rundir import (
    network_path,
    save_final_evaluation,
    save_network,
    write_run_config,
)

SMALL = AggregateSettings(bootstrap_repetitions=200, bootstrap_seed=3)
# Rows of data/atari100k_scores.csv: random, human, DER's published mean.
ROWS = {
    "road_runner": (11.5, 7845.0, 9600.0),
    "krull": (1598.0, 2665.5, 2851.5),
    "pong": (-20.7, 14.6, -19.3),
}
# Final-evaluation means by game and seed.
MEANS = {"road_runner": [5000.0, 7000.0], "krull": [3000.0], "pong": [-15.0]}


def _hns(score: float, game: str) -> float:
    random, human, _ = ROWS[game]
    return (score - random) / (human - random)


def _fake_sweep(root: Path, **settings: object) -> Path:
    """Each run trained to its budget (a last.pt of step 100,000: nothing else in it) and
    given its final evaluation."""
    for game, means in MEANS.items():
        for seed, mean in enumerate(means):
            run_dir = root / f"{game}-s{seed}"
            run_dir.mkdir(parents=True)
            write_run_config(run_dir, resolve_config("der", settings, env=game, seed=seed))
            save_network(network_path(run_dir, "last"), {"step": 100_000})
            record = {"mean": mean, "std": 1.0, "episodes": 100, "checkpoint_step": 100_000}
            save_final_evaluation(run_dir, record)
    return root


def test_the_table_and_aggregates_against_numbers_worked_out_by_hand(tmp_path: Path) -> None:
    sweep = _fake_sweep(tmp_path / "sweep")
    out = tmp_path / "out"
    report = write_report([sweep], out, reference="der-paper", aggregate=SMALL)

    rows = {row.game: row for row in report.atari100k}
    assert sorted(rows) == sorted(MEANS)
    assert rows["road_runner"].run_scores == (5000.0, 7000.0)
    assert rows["road_runner"].score == 6000.0
    for game, means in MEANS.items():
        random, human, der = ROWS[game]
        row = rows[game]
        assert (row.random, row.human, row.der) == (random, human, der)
        assert row.hns == pytest.approx(100 * _hns(float(np.mean(means)), game))
        assert row.der_hns == pytest.approx(100 * _hns(der, game))
    # road_runner: (6000 - 11.5) / 7833.5 = 0.76447...; krull 1402 / 1067.5 = 1.31335...;
    # pong 5.7 / 35.3 = 0.16147...: mean 0.74643..., median 0.76447...
    markdown = (out / "results.md").read_text()
    assert "| all settings equal | 3 | 0.746 | 0.764 |" in markdown  # DER's mean and median follow
    road = "| RoadRunner | all settings equal | 2 | 6000.0 (5000.0, 7000.0) | 11.5 | 7845 | 9600 |"
    assert road in markdown
    assert "not the IQM over per-run scores" in markdown
    assert "3000 ± 1.0 over 100 games, last network of step 100000" in markdown
    console = format_table(report)
    assert "Atari 100k, against Data-Efficient Rainbow's published scores" in console
    (krull,) = [line for line in console.splitlines() if line.startswith("Krull ")]
    assert krull.split()[-4:] == ["3000.0", "2851.5", "1.313", "1.174"]

    # The aggregates: dqnlab's runs and DER's published scores over the same three games.
    aggregates = report.aggregates
    assert aggregates is not None
    assert {item.configuration for item in aggregates.configurations} == {ALL_EQUAL, DER_PAPER}
    published = aggregates.scores[DER_PAPER]
    games = aggregates.games
    assert published.shape == (1, 3)
    assert published[0].tolist() == pytest.approx([100 * _hns(ROWS[g][2], g) for g in games])
    (der,) = [item for item in aggregates.configurations if item.configuration == DER_PAPER]
    assert der.mean.estimate == pytest.approx(100 * np.mean([_hns(ROWS[g][2], g) for g in games]))
    assert der.median.estimate == pytest.approx(
        100 * np.median([_hns(ROWS[g][2], g) for g in games])
    )
    assert (out / "performance-profiles.png").is_file()

    records = read_csv(out / "atari100k.csv")
    (road,) = [r for r in records if r["game"] == "road_runner"]
    assert (road["runs"], road["run_scores"], float(road["score_mean"])) == ("2", "5000 7000", 6000)
    assert float(road["der_paper"]) == 9600.0
    assert not [note for note in report.notes if "not the Atari 100k protocol" in note]


def test_a_run_off_the_protocol_is_named_in_the_report(tmp_path: Path) -> None:
    sweep = _fake_sweep(tmp_path / "sweep", sticky_action_probability=0.25)
    report = write_report([sweep], tmp_path / "out", reference="der-paper", aggregate=SMALL)
    off = [note for note in report.notes if "not the Atari 100k protocol" in note]
    assert len(off) == 4
    assert all("sticky_action_probability = 0.25 (the protocol: 0.0)" in note for note in off)
    assert "not the Atari 100k protocol" in (tmp_path / "out" / "results.md").read_text()


def test_without_der_paper_the_benchmark_table_is_left_out(tmp_path: Path) -> None:
    sweep = _fake_sweep(tmp_path / "sweep")
    report = write_report([sweep], tmp_path / "out", reference="none", aggregate=SMALL)
    assert report.atari100k == []
    assert report.aggregates is not None
    assert DER_PAPER not in {item.configuration for item in report.aggregates.configurations}
    assert not (tmp_path / "out" / "atari100k.csv").exists()


def test_a_run_still_training_is_neither_evaluated_nor_shown(tmp_path: Path) -> None:
    """A sweep in progress: the last network halfway through is not what the benchmark
    scores, so the report plays no final evaluation of it and leaves it out of the tables."""
    sweep = _fake_sweep(tmp_path / "sweep")
    training = sweep / "krull-s1"
    training.mkdir()
    write_run_config(training, resolve_config("der", env="krull", seed=1))
    save_network(network_path(training, "last"), {"step": 40_000})

    def must_not_evaluate(run_dir: Path) -> dict[str, object]:
        raise AssertionError(f"{run_dir} evaluated")

    report = write_report(
        [sweep], tmp_path / "out", reference="der-paper", aggregate=SMALL,
        evaluate_missing=must_not_evaluate,
    )  # fmt: skip
    (krull,) = [row for row in report.atari100k if row.game == "krull"]
    assert krull.run_scores == (3000.0,)
    (note,) = [note for note in report.notes if str(training) in note]
    assert "training (newest checkpoint at step 40000 of 100000)" in note
