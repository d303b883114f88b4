"""Dopamine's published curves as a reference, the on-track verdicts, Nature Fig. 2's panels."""

from __future__ import annotations

import csv
import functools
import gzip
import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.collections import PolyCollection

from dqnlab.analysis.report import Report, RunResults, build_report, curve_figure, format_table
from dqnlab.analysis.report.legend import ON_TRACK_TEXT
from dqnlab.analysis.report.reference import (
    AGENTS,
    REFERENCE_PROTOCOL,
    WINDOW_FRAMES,
    load_reference_curves,
    load_references,
    on_track_rows,
    reference_agent,
)
from dqnlab.config import resolve_config
from dqnlab.run import rundir
from dqnlab.run.logs import EPISODE_FIELDS, EVALUATION_FIELDS, read_csv

DATA = Path(__file__).parents[3] / "src" / "dqnlab" / "data"


def published(game: str, iteration: int, agent: str = "dqn") -> list[float]:
    """The five runs' scores of one iteration, read from the shipped file directly: the
    DQN CSV, or the variants' gzip-compressed one."""
    return published_scores(agent).get((game, iteration), [])


@functools.cache
def published_scores(agent: str) -> dict[tuple[str, int], list[float]]:
    if agent == "dqn":
        text = (DATA / "dopamine_dqn_curves.csv").read_text()
    else:
        text = gzip.decompress((DATA / "dopamine_variant_curves.csv.gz").read_bytes()).decode()
    scores: dict[tuple[str, int], list[float]] = {}
    for row in csv.DictReader(io.StringIO(text)):
        if row.get("agent", "dqn") == agent:
            key = (row["game"], int(row["iteration"]))
            scores.setdefault(key, []).append(float(row["train_return"]))
    return scores


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


def fake_run(
    run_dir: Path,
    env: str,
    games: list[tuple[int, float]],
    preset: str = "nature",
    evaluations: tuple[int, ...] = (),
    **settings: Any,
) -> RunResults:
    """A run directory with only its config (`preset` and `settings`), episodes.csv, (frames
    at the game's end, score) per training game at 4 frames a step, and evaluations.csv, a
    periodic evaluation of mean 0 at each step of `evaluations`."""
    run_dir.mkdir(parents=True)
    config = resolve_config(preset, env=env, total_steps=10_000_000, **settings)
    rundir.write_run_config(run_dir, config)
    with rundir.episodes_path(run_dir).open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=EPISODE_FIELDS)
        writer.writeheader()
        for number, (frames, score) in enumerate(games, 1):
            writer.writerow(
                {"step": frames // 4, "frames": frames, "episode": number, "score": score,
                 "steps": 1000, "epsilon": 0.1, "wall_seconds": 1.0}
            )  # fmt: skip
    with rundir.evaluations_path(run_dir).open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=EVALUATION_FIELDS)
        writer.writeheader()
        for step in evaluations:
            writer.writerow(
                {"step": step, "frames": 4 * step, "mean": 0.0, "std": 0.0, "episodes": 1,
                 "steps": 1000, "best_mean": 0.0, "frames_per_second": 1.0, "wall_seconds": 1.0,
                 "heldout_max_q": "", "heldout_td_error": ""}
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
    rows = on_track_rows([(run, "all") for run in runs], load_references(r.config for r in runs))
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
    assert "## On track?" in results and ON_TRACK_TEXT in results
    assert all(row.reference == "dqn" for row in atari_report.on_track)
    assert "On track?" in format_table(atari_report)
    without = build_report(list(atari_runs.values()), reference="none")
    assert without.on_track == [] and all(curve.references == {} for curve in without.curves)
    live = fake_run(tmp_path / "live", "pong", [(2_100_000, -20.0)])
    report = build_report([live.run_dir])
    assert any("unfinished (newest checkpoint at step 0 of 10000000)" in n for n in report.notes)
    (row,) = report.on_track
    assert row.verdict is not None and "(unfinished)" in format_table(report)


# The DQN family: each run against its own agent's curve --------------------------------


@pytest.mark.parametrize(
    ("preset", "settings", "agent", "why"),
    [
        ("nature", {}, "dqn", None),
        ("machado", {}, "dqn", None),  # Nature-era settings (sticky actions) do not count
        ("nature", {"optimizer": "adam"}, "dqn", None),
        ("double", {}, None, "for DQN + double Q-learning"),
        ("dueling", {}, None, "dueling head"),
        ("prioritized", {}, None, "prioritized replay"),
        ("c51", {}, "c51", None),
        ("rainbow", {}, "rainbow", None),
        ("rainbow", {"target": "max", "dueling": False, "noisy": False}, "rainbow", None),
        ("c51", {"n_step": 3}, None, "for DQN + 3-step returns + C51"),  # no prioritized
        ("c51", {"target": "double"}, None, "double Q-learning + C51"),
        ("nature", {"loss": "x.y:Z"}, None, "for your own loss (x.y:Z)"),
        ("rainbow", {"loss": "x.y:Z"}, None, "for your own loss (x.y:Z)"),
    ],
)
def test_each_configuration_is_compared_with_the_agent_of_its_parts(
    preset: str, settings: dict[str, Any], agent: str | None, why: str | None
) -> None:
    match = reference_agent(resolve_config(preset, env="pong", **settings))
    assert match.agent == agent
    if why is None:
        assert match.why_none is None
    else:
        assert match.why_none is not None and match.why_none.startswith("Dopamine publishes no")
        assert why in match.why_none
    full_rainbow = preset == "rainbow" and not settings
    assert (match.caveat is not None) == full_rainbow  # what the compact Rainbow lacks
    if full_rainbow:
        assert "without the run's double Q-learning, dueling head and noisy nets" in str(
            match.caveat
        )


@pytest.mark.parametrize("agent", ["c51", "rainbow"])
def test_the_variants_bands_are_the_packaged_files(agent: str) -> None:
    curves = load_reference_curves(["pong", "breakout", "surround", "CartPole-v1"], agent)
    assert set(curves) == {"pong", "breakout"}
    for game, curve in curves.items():
        assert curve.agent == agent and curve.windows == 199 and curve.runs == 5
        for iteration in (0, 9, 49, 198):
            scores = published(game, iteration, agent)
            assert len(scores) == 5
            assert curve.mean[iteration] == pytest.approx(np.mean(scores))
            assert curve.low[iteration] == min(scores)
            assert curve.high[iteration] == max(scores)
    # The means at iterations 9, 49 and 198 that the data's description gives.
    described = {"c51": (-6.1, 17.6, 19.3), "rainbow": (15.2, 19.3, 20.2)}[agent]
    assert tuple(round(float(curves["pong"].mean[i]), 1) for i in (9, 49, 198)) == described


def test_a_report_draws_each_agent_once_and_sets_each_run_beside_its_own(tmp_path: Path) -> None:
    games = [(500_000, -20.0), (1_500_000, 10.0)]  # the latest window: 1M to 2M frames
    steps = (250_000, 500_000)  # 2M frames: two windows of the references drawn
    runs = [
        fake_run(tmp_path / "nature", "pong", games, "nature", steps),
        fake_run(tmp_path / "rainbow", "pong", games, "rainbow", steps),
        fake_run(
            tmp_path / "compact",
            "pong",
            games,
            "rainbow",
            steps,
            target="max",
            dueling=False,
            noisy=False,
        ),  # Dopamine's Rainbow: no caveat
        fake_run(tmp_path / "double", "pong", games, "double", steps),
    ]
    report = build_report([run.run_dir for run in runs])
    (pong,) = report.curves
    assert len(pong.series) == 4 and set(pong.references) == {"dqn", "rainbow"}
    axes = curve_figure(pong).axes[0]
    drawn = {line.get_label(): line for line in axes.get_lines()}
    legends = {
        agent: f"{AGENTS[agent].name}: mean of 5 runs, band min–max\n{REFERENCE_PROTOCOL}"
        for agent in ("dqn", "rainbow")
    }
    assert [label for label in drawn if label.startswith("Dopamine")] == [
        legends[agent] for agent in pong.references
    ]  # each agent once, the two rainbow configurations sharing Dopamine's Rainbow
    assert "Dopamine Rainbow (compact: C51, 3-step, prioritized)" in legends["rainbow"]
    for agent, line in ((agent, drawn[legends[agent]]) for agent in legends):
        assert line.get_color() == AGENTS[agent].color
        assert list(line.get_ydata()) == pytest.approx(
            [np.mean(published("pong", i, agent)) for i in (0, 1, 1)]  # a step per window
        )
    bands = [c for c in axes.collections if isinstance(c, PolyCollection)]
    assert len(bands) == 2  # one seed per configuration: the references' bands only
    rows = {row.run_dir.name: row for row in report.on_track}
    for name, agent in (("nature", "dqn"), ("rainbow", "rainbow"), ("compact", "rainbow")):
        scores = published("pong", 1, agent)
        assert rows[name].reference == agent and rows[name].window == 1
        assert rows[name].reference_mean == pytest.approx(np.mean(scores))
        assert (rows[name].reference_low, rows[name].reference_high) == (min(scores), max(scores))
        assert rows[name].verdict is not None
    double = rows["double"]
    assert double.reference is None and double.verdict is None and double.reference_mean is None
    assert double.why_none == "Dopamine publishes no curve for DQN + double Q-learning"
    assert any(
        note.startswith("pong, ") and double.why_none in note and "no reference curve" in note
        for note in report.notes
    )
    assert sum("compared with Dopamine's compact Rainbow" in note for note in report.notes) == 1
    table = format_table(report)
    assert double.why_none in table and AGENTS["rainbow"].name in table
