"""Writing a report: the files, final evaluations played once where missing, Q-values."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from matplotlib.collections import PolyCollection

from dqnlab.analysis.report import (
    Report,
    build_report,
    curve_figure,
    final_network_evaluator,
    find_runs,
    write_report,
)
from dqnlab.run import rundir
from dqnlab.run.logs import read_csv
from dqnlab.run.rundir import load_final_evaluation
from tests.analysis.report.common import (
    FEW_REPS,
    CountingEvaluator,
    must_not_evaluate,
    row_of,
    write_final_evaluation,
)


def test_a_run_another_process_holds_is_not_evaluated_by_the_report(
    cartpole_copy: Path, tmp_path: Path
) -> None:
    # A sweep's run playing its final evaluation holds its lease: the report must neither
    # play that evaluation a second time nor write beside it.
    from dqnlab.run.lease import held

    held_run, *others = sorted(find_runs([cartpole_copy]))
    evaluator = CountingEvaluator()
    with held(held_run):
        report = write_report([cartpole_copy], tmp_path / "out", evaluate_missing=evaluator)
    assert sorted(evaluator.calls) == others
    assert load_final_evaluation(held_run) is None
    assert any(f"{held_run}: another process holds it now" in note for note in report.notes)


def test_figures_are_written_as_png_and_svg(atari_report: Report) -> None:
    names = sorted(path.name for curve in atari_report.curves for path in curve.files)
    assert names == [
        "curves-breakout.png",
        "curves-breakout.svg",
        "curves-pong.png",
        "curves-pong.svg",
    ]
    for curve in atari_report.curves:
        png, svg = curve.files
        assert png.read_bytes().startswith(b"\x89PNG") and png.stat().st_size > 1000
        assert "<svg" in svg.read_text()
        assert png in atari_report.files and svg in atari_report.files


def test_groups_come_from_differing_settings_and_missing_evaluations_are_played_once(
    cartpole_copy: Path, tmp_path: Path
) -> None:
    evaluator = CountingEvaluator()
    report = write_report([cartpole_copy], tmp_path / "out", evaluate_missing=evaluator)
    seeds = {group.label: [run.config.seed for run in group.runs] for group in report.groups}
    assert seeds == {"life_loss_terminal=true": [0, 1], "life_loss_terminal=false": [0]}
    assert sorted(evaluator.calls) == sorted(find_runs([cartpole_copy]))
    assert sorted(report.evaluated) == sorted(evaluator.calls)
    for run_dir in evaluator.calls:
        saved = load_final_evaluation(run_dir)
        assert saved is not None and saved["episodes"] == 2
    # Non-Atari: raw scores, no reference, no normalised score, no summary across games.
    row = row_of(report, "CartPole-v1", "life_loss_terminal=true")
    assert row.seeds == 2 and row.games_per_seed == (2, 2)
    (group,) = [group for group in report.groups if group.label == row.configuration]
    finals = [load_final_evaluation(run.run_dir) for run in group.runs]
    assert row.score == pytest.approx(np.mean([final["mean"] for final in finals]))
    assert row.hns_human is None and row.hns_human_nature is None and row.nature_dqn is None
    assert report.summary == []
    (record,) = [
        r
        for r in read_csv(tmp_path / "out" / "results.csv")
        if r["configuration"] == row.configuration
    ]
    assert record["hns_human_percent"] == "" and record["random"] == ""
    assert float(record["score_mean"]) == pytest.approx(row.score)
    # Two groups: two lines, a band for the one with two seeds.
    (curve,) = report.curves
    assert curve.frames_per_step is None  # a CartPole frame is a step: no top axis
    axes = curve_figure(curve).axes[0]
    assert [line.get_label() for line in axes.get_lines()] == [  # the sweep's order
        "life_loss_terminal=false (1 seed)",
        "life_loss_terminal=true (2 seeds)",
    ]
    assert len([c for c in axes.collections if isinstance(c, PolyCollection)]) == 1
    # A second report reads the saved evaluations: nothing is played again.
    write_report([cartpole_copy], tmp_path / "again", evaluate_missing=evaluator)
    assert len(evaluator.calls) == 3


def test_final_evaluation_of_an_older_best_network_is_played_again(
    cartpole_copy: Path, tmp_path: Path
) -> None:
    runs = find_runs([cartpole_copy])
    for run_dir in runs:
        write_final_evaluation(run_dir, [1.0, 3.0])
    stale = runs[0] / "final_evaluation.json"
    record = json.loads(stale.read_text())
    record["checkpoint_step"] = -1  # as if the run had trained on since it was evaluated
    stale.write_text(json.dumps(record))
    evaluator = CountingEvaluator()
    report = build_report(runs, evaluate_missing=evaluator, echo=lambda _: None)
    assert evaluator.calls == [runs[0]]
    assert json.loads(stale.read_text())["checkpoint_step"] != -1
    # Without an evaluator the older one is shown, with a note.
    record["checkpoint_step"] = -1
    stale.write_text(json.dumps(record))
    report = build_report(runs, evaluate_missing=None)
    assert any("step -1" in note and "older one" in note for note in report.notes)


def test_without_an_evaluator_runs_lacking_a_final_evaluation_are_left_out(
    cartpole_copy: Path,
) -> None:
    runs = find_runs([cartpole_copy])
    write_final_evaluation(runs[0], [5.0, 7.0])
    report = build_report([cartpole_copy], evaluate_missing=None)
    assert [(row.configuration, row.seeds, row.score) for row in report.rows] == [
        ("life_loss_terminal=false", 1, 6.0)
    ]
    assert (
        sum("no final evaluation" in note and "not in the table" in note for note in report.notes)
        == 2
    )
    assert len(report.curves) == 1  # the curves need no final evaluation


def test_unsafe_game_names_make_safe_file_names() -> None:
    from dqnlab.analysis.report.write import _file_stem

    taken: set[str] = set()
    assert _file_stem("ALE/Pong-v5", taken) == "curves-ALE_Pong-v5"
    assert _file_stem("my_envs:Grid", taken) == "curves-my_envs_Grid"
    assert _file_stem("my_envs/Grid", taken) == "curves-my_envs_Grid-2"


def test_report_inspects_each_runs_best_against_worst(cartpole_copy: Path, tmp_path: Path) -> None:
    runs = find_runs([cartpole_copy])
    (runs[0] / "checkpoints" / "worst.pt").unlink()  # as before the first quarter ends
    out = tmp_path / "out"
    report = write_report(
        [cartpole_copy], out, evaluate_missing=CountingEvaluator(), inspect_frames=2
    )
    inspected = {item.run_dir: item.inspection for item in report.inspections}
    assert set(inspected) == set(runs)
    assert [n.name for n in inspected[runs[0]].networks] == ["best"]
    assert any(f"{runs[0]}: no worst network" in note for note in report.notes)
    for run in runs[1:]:
        networks = inspected[run].networks
        assert [n.name for n in networks] == ["best", "worst"]
        assert networks[1].path == run / "checkpoints" / "worst.pt"
        rows = read_csv(out / "q-values" / run.name / "q_values.csv")
        assert len(rows) == 2 * 2 * 2  # networks x frames x actions
    markdown = (out / "results.md").read_text()
    assert markdown.count("](q-values/") == len(runs)
    assert all((out / "q-values" / run.name / "overview.png").stat().st_size > 0 for run in runs)


def test_runs_of_the_same_name_get_their_own_q_value_folders(tmp_path: Path) -> None:
    from dqnlab.analysis.report.write import _unique_name

    taken: set[str] = set()
    names = [_unique_name(tmp_path / parent / "s0", taken) for parent in ("a", "b", "b")]
    assert names == ["s0", "b-s0", "b-s0-2"]


def test_the_final_evaluation_names_the_network_it_played(
    cartpole_copy: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run still training may save a new best.pt while its old best network plays."""
    import dqnlab.run.evaluate

    run = find_runs([cartpole_copy])[0]
    best, worst = run / "checkpoints" / "best.pt", run / "checkpoints" / "worst.pt"
    played_step, newer_step = rundir.load_network(best)["step"], rundir.load_network(worst)["step"]
    assert played_step != newer_step
    play_games = dqnlab.run.evaluate.play_games

    def play_then_replace_best(*args: Any, **kwargs: Any) -> Any:
        result = play_games(*args, **kwargs)
        shutil.copy(worst, best)  # training wrote a new best network meanwhile
        return result

    monkeypatch.setattr(dqnlab.run.evaluate, "play_games", play_then_replace_best)
    record = final_network_evaluator(torch.device("cpu"), episodes=1)(run)
    assert record["checkpoint_step"] == played_step
    assert load_final_evaluation(run)["checkpoint_step"] == played_step


def test_a_report_written_again_leaves_only_its_own_files(
    atari_runs: dict[str, Path], tmp_path: Path
) -> None:
    out = tmp_path / "out"
    first = write_report(
        list(atari_runs.values()),
        out,
        evaluate_missing=must_not_evaluate,
        inspect_frames=1,
        aggregate=FEW_REPS,
    )
    assert (out / "summary.csv").is_file() and (out / "curves-pong.png").is_file()
    assert (out / "aggregates.csv").is_file() and (out / "performance-profiles.svg").is_file()
    assert len(first.inspections) == 3
    (out / "notes.txt").write_text("mine")  # not a report's file: kept
    write_report([atari_runs["breakout-s0"]], out, evaluate_missing=must_not_evaluate)
    assert sorted(p.name for p in out.iterdir()) == [
        "curves-breakout.png", "curves-breakout.svg", "notes.txt", "q-values", "results.csv",
        "results.md",
    ]  # fmt: skip
    assert list((out / "q-values").iterdir()) == []
