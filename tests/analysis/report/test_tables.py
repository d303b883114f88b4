"""The table as the terminal, results.csv and results.md show it."""

from __future__ import annotations

import csv

import pytest

from dqnlab.analysis.report import (
    Report,
    format_markdown,
    format_table,
)
from dqnlab.run.logs import read_csv
from tests.analysis.report.common import (
    PONG,
    hns,
)


def test_terminal_table(atari_report: Report) -> None:
    text = format_table(atari_report)
    lines = text.splitlines()
    assert lines[0].split("  ")[0] == "Game"
    assert "HNS % (dqn_zoo human)" in lines[0] and "HNS % (Nature human)" in lines[0]
    assert any(line.startswith("pong ") and "-15.5 ± 4.5" in line for line in lines)
    assert any(line.startswith("median ") for line in lines)


def test_csv_columns_are_numbers_where_numbers(atari_report: Report) -> None:
    out = atari_report.files[0].parent
    with (out / "results.csv").open(newline="") as handle:
        for row in csv.DictReader(handle):
            for name, value in row.items():
                if name not in ("game", "configuration", "score_std_over", "run_dirs") and value:
                    float(value)


def test_results_files_hold_the_table(atari_report: Report) -> None:
    out = atari_report.files[0].parent
    rows = {row["game"]: row for row in read_csv(out / "results.csv")}
    assert set(rows) == {"pong", "breakout"}
    assert float(rows["pong"]["score_mean"]) == pytest.approx(-15.5)
    assert float(rows["pong"]["hns_human_percent"]) == pytest.approx(hns(-15.5, PONG, "human"))
    assert float(rows["pong"]["hns_human_nature_percent"]) == pytest.approx(
        hns(-15.5, PONG, "human_nature")
    )
    assert rows["pong"]["seeds"] == "2" and rows["pong"]["score_std_over"] == "seeds"
    assert rows["breakout"]["seed_mean_min"] == ""  # one seed: no spread across seeds
    summary = read_csv(out / "summary.csv")
    assert len(summary) == 4 and {row["games"] for row in summary} == {"2"}
    markdown = (out / "results.md").read_text()
    assert "HNS % (dqn_zoo human)" in markdown and "HNS % (Nature human)" in markdown
    assert "## Legend" in markdown and "Extended Data Table 2" in markdown
    assert "![pong](curves-pong.png)" in markdown
    assert "| pong | all settings equal | 2 | 2 | 200–300 | -15.5 ± 4.5 | -20.0 to -11.0 |" in (
        markdown
    )
    assert format_markdown(atari_report, out) == markdown
