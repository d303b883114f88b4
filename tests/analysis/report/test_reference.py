"""Dopamine's published curves as a reference, the on-track verdicts, Nature Fig. 2's panels."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import pytest

from dqnlab.analysis.report import Report, RunResults, build_report, curve_figure, format_table
from dqnlab.analysis.report.reference import (
    REFERENCE_LABEL,
    REFERENCE_PROTOCOL,
    WINDOW_FRAMES,
    load_reference_curves,
    on_track_rows,
)
from dqnlab.config import resolve_config
from dqnlab.run import rundir
from dqnlab.run.logs import EPISODE_FIELDS, read_csv

SHARED_CSV = Path(__file__).parents[3] / "src" / "dqnlab" / "data" / "dopamine_dqn_curves.csv"


def published(game: str, iteration: int) -> list[float]:
    """The five runs' scores of one iteration, read from the shipped CSV directly."""
    with SHARED_CSV.open(newline="") as handle:
        return [
            float(row["train_return"])
            for row in csv.DictReader(handle)
            if row["game"] == game and int(row["iteration"]) == iteration
        ]


def test_the_band_at_chosen_frames_is_the_csvs(tmp_path: Path) -> None:
    curves = load_reference_curves(["space_invaders", "pong", "surround", "CartPole-v1"])
    assert set(curves) == {"space_invaders", "pong"}  # surround: not in Dopamine's 60
    invaders = curves["space_invaders"]  # Dopamine spells it spaceinvaders
    # The md beside the CSV says 200 iterations; the CSV holds 0 to 198 for every game.
    assert invaders.windows == 199 and invaders.runs == 5
    for iteration in (0, 57, 198):
        scores = published("spaceinvaders", iteration)
        assert len(scores) == 5
        assert invaders.mean[iteration] == pytest.approx(np.mean(scores))
        assert invaders.low[iteration] == min(scores)
        assert invaders.high[iteration] == max(scores)


def fake_run(run_dir: Path, env: str, games: list[tuple[int, float]]) -> RunResults:
    """A run directory with only its config and episodes.csv: (frames at the game's end,
    score) per training game, at 4 frames a step."""
    run_dir.mkdir(parents=True)
    config = resolve_config("nature", env=env, total_steps=10_000_000)
    rundir.write_run_config(run_dir, config)
    with rundir.episodes_path(run_dir).open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=EPISODE_FIELDS)
        writer.writeheader()
        for number, (frames, score) in enumerate(games, 1):
            writer.writerow(
                {"step": frames // 4, "frames": frames, "episode": number, "score": score,
                 "steps": 1000, "epsilon": 0.1, "wall_seconds": 1.0}
            )  # fmt: skip
    return RunResults(run_dir, config, [], None)


def test_verdicts_below_within_and_above_the_range(tmp_path: Path) -> None:
    scores = published("pong", 2)  # the window from 2M to 3M frames
    low, high = min(scores), max(scores)
    earlier = [(500_000, 100.0), (1_500_000, 100.0)]  # earlier windows do not count
    runs = [
        fake_run(tmp_path / "below", "pong", [*earlier, (2_100_000, low - 1.0)]),
        fake_run(tmp_path / "within", "pong", [*earlier, (2_100_000, low), (2_600_000, high)]),
        fake_run(tmp_path / "above", "pong", [*earlier, (2_100_000, high + 1.0), (3_000_000, 50)]),
        fake_run(tmp_path / "uncovered", "surround", [(2_100_000, 1.0)]),
        fake_run(tmp_path / "no-game", "pong", []),
        fake_run(tmp_path / "vector", "CartPole-v1", [(2_100_000, 1.0)]),
    ]
    rows = on_track_rows([(run, "all") for run in runs], load_reference_curves(["pong"]))
    by_name = {row.run_dir.name: row for row in rows}
    assert "vector" not in by_name  # a non-Atari run has no row
    below, within, above = by_name["below"], by_name["within"], by_name["above"]
    assert below.verdict == "below the range" and below.score == low - 1.0
    assert within.verdict == "within the range" and within.games == 2
    assert within.score == pytest.approx((low + high) / 2)
    assert above.verdict == "above the range"  # 3,000,000 ends window 2, not 3
    assert (
        above.window == 2
        and above.games == 2
        and above.score == pytest.approx((high + 1.0 + 50) / 2)
    )
    assert above.window_complete and not within.window_complete
    for row in (below, within, above):
        assert row.reference_mean == pytest.approx(np.mean(scores))
        assert (row.reference_low, row.reference_high) == (low, high)
        assert not row.finished and row.steps == row.frames // 4
    assert by_name["uncovered"].verdict is None
    assert "no curve for surround" in (by_name["uncovered"].why_none or "")
    assert by_name["no-game"].window is None and by_name["no-game"].verdict is None


def test_figure_draws_the_reference_and_the_heldout_panels(
    atari_report: Report, atari_runs: dict[str, Path]
) -> None:
    pong = next(curve for curve in atari_report.curves if curve.game == "pong")
    (series,) = pong.series
    logged = [
        float(row["heldout_max_q"])
        for name in ("pong-s0", "pong-s1")
        for row in read_csv(atari_runs[name] / "evaluations.csv")
        if int(row["step"]) == 200
    ]
    assert series.heldout_max_q is not None and series.heldout_td_error is not None
    assert len(logged) == 2 and series.heldout_max_q[0] == pytest.approx(np.mean(logged))
    figure = curve_figure(pong)
    score_axes, q_axes, td_axes = figure.axes[:3]
    assert q_axes.get_ylabel() == "held-out mean max Q"
    assert td_axes.get_ylabel() == "held-out mean |TD error|"
    # The reference is a step over the first 1M-frame window (the runs are far shorter).
    (reference,) = [line for line in score_axes.get_lines() if "Dopamine" in line.get_label()]
    assert reference.get_ydata()[0] == pytest.approx(np.mean(published("pong", 0)))
    assert reference.get_xdata()[1] == pytest.approx(WINDOW_FRAMES / pong.measured_frames_per_step)
    svg = io.StringIO()
    figure.savefig(svg, format="svg")
    text = svg.getvalue()
    for label in ("held-out mean max Q", "held-out mean |TD error|", REFERENCE_PROTOCOL[:20]):
        assert label in text  # matplotlib keeps each text as a comment beside its glyphs


def test_the_report_has_an_on_track_section_and_notes_unfinished_runs(
    atari_report: Report, atari_runs: dict[str, Path], tmp_path: Path
) -> None:
    assert len(atari_report.on_track) == 3  # every Atari run, finished or not
    assert all(row.finished for row in atari_report.on_track)
    results = (atari_report.files[-1].parent / "results.md").read_text()
    assert "## On track?" in results and REFERENCE_LABEL in results
    assert "On track?" in format_table(atari_report)
    without = build_report(list(atari_runs.values()), reference="none")
    assert without.on_track == [] and all(curve.reference is None for curve in without.curves)
    live = fake_run(tmp_path / "live", "pong", [(2_100_000, -20.0)])
    report = build_report([live.run_dir])
    assert any("unfinished (newest checkpoint at step 0 of 10000000)" in n for n in report.notes)
    (row,) = report.on_track
    assert row.verdict is not None and "(unfinished)" in format_table(report)
