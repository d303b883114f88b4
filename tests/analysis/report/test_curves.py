"""Learning curves: the mean over seeds at each step, bands, the frames axis."""

from __future__ import annotations

from pathlib import Path

import pytest
from matplotlib.collections import PolyCollection

from dqnlab.analysis.report import (
    ALL_EQUAL,
    Report,
    RunResults,
    curve_figure,
    write_report,
)
from dqnlab.analysis.report.reference import AGENTS, REFERENCE_PROTOCOL
from dqnlab.config import resolve_config
from dqnlab.run.logs import read_csv
from tests.analysis.report.common import (
    CARTPOLE_TINY,
    CountingEvaluator,
    train_run,
)


def test_curve_is_the_mean_over_the_seeds_present_at_each_step(
    atari_report: Report, atari_runs: dict[str, Path]
) -> None:
    curves = {curve.game: curve for curve in atari_report.curves}
    assert set(curves) == {"pong", "breakout"}
    (pong,) = curves["pong"].series
    seed0, seed1 = (
        {int(r["step"]): float(r["mean"]) for r in read_csv(atari_runs[name] / "evaluations.csv")}
        for name in ("pong-s0", "pong-s1")
    )
    assert sorted(seed0) == [200, 300] and sorted(seed1) == [200]  # the shorter run
    assert pong.steps == (200, 300)
    assert pong.seeds_at_step == (2, 1)
    assert pong.mean == pytest.approx(((seed0[200] + seed1[200]) / 2, seed0[300]))
    assert pong.low == (min(seed0[200], seed1[200]), seed0[300])
    assert pong.high == (max(seed0[200], seed1[200]), seed0[300])
    (breakout,) = curves["breakout"].series
    assert breakout.low is None and breakout.high is None  # one seed: no band
    # Atari frames per step: 4 repeated frames plus the no-op starts.
    frames = [int(r["frames"]) for r in read_csv(atari_runs["pong-s0"] / "evaluations.csv")]
    assert curves["pong"].frames_per_step is not None
    assert 4.0 <= curves["pong"].frames_per_step <= max(frames) / 200


def test_figure_has_a_line_per_configuration_and_a_band_per_seeded_one(
    atari_report: Report,
) -> None:
    for curve in atari_report.curves:
        axes = curve_figure(curve).axes[0]
        assert axes.get_title() == curve.game
        labels = [line.get_label() for line in axes.get_lines()]
        assert list(curve.references) == ["dqn"]  # Dopamine's DQN behind both games' lines
        name = AGENTS["dqn"].name
        reference = f"{name}: mean of 5 runs, band min–max\n{REFERENCE_PROTOCOL}"
        assert labels == [series.legend_label for series in curve.series] + [reference]
        legend = axes.get_legend()
        assert [text.get_text() for text in legend.get_texts()] == labels
        bands = [c for c in axes.collections if isinstance(c, PolyCollection)]
        assert len(bands) == (2 if curve.game == "pong" else 1)  # seeds' band, reference's
    pong = next(curve for curve in atari_report.curves if curve.game == "pong")
    assert pong.series[0].legend_label == f"{ALL_EQUAL} (2 seeds)"


def test_a_run_without_periodic_evaluations_has_no_curve(tmp_path: Path) -> None:
    settings = {**CARTPOLE_TINY, "total_steps": 100}  # no step past replay start
    run_dir = train_run(tmp_path / "fresh", "classic", **settings)
    assert read_csv(run_dir / "evaluations.csv") == []
    evaluator = CountingEvaluator()
    report = write_report([run_dir], tmp_path / "out", evaluate_missing=evaluator)
    assert report.curves == []
    assert not list((tmp_path / "out").glob("curves-*"))
    assert any("no periodic evaluation yet" in note for note in report.notes)
    assert any("no figure" in note for note in report.notes)
    assert "no periodic evaluation yet" in (tmp_path / "out" / "results.md").read_text()
    assert len(report.rows) == 1 and evaluator.calls == [run_dir]  # the final network


def test_no_frames_axis_when_configurations_repeat_actions_differently() -> None:
    from dqnlab.analysis.report import Group, PeriodicEvaluation, learning_curves

    def group(repeat: int, *runs_frames: int) -> Group:
        config = resolve_config("nature", env="pong", action_repeat_frames=repeat)
        runs = [
            RunResults(Path(f"r{repeat}-{n}"), config, [PeriodicEvaluation(100, f, 0.0, 1)], None)
            for n, f in enumerate(runs_frames)
        ]
        return Group("pong", f"action_repeat_frames={repeat}", {}, runs)

    (agreeing,) = learning_curves([group(4, 410, 420)])
    assert agreeing.frames_per_step == pytest.approx(4.15)
    (differing,) = learning_curves([group(2, 210), group(4, 410)])
    assert differing.frames_per_step is None
