"""Reports from real (tiny) runs: the table against scores worked out by hand, grouping
by differing settings, seed aggregation, learning curves and their figures, and the final
evaluation played once for runs that lack one."""

from __future__ import annotations

import csv
import json
import math
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from matplotlib.collections import PolyCollection

from dqnlab.config import resolve_config
from dqnlab.errors import DqnlabError
from dqnlab.run import rundir
from dqnlab.run.logs import read_csv
from dqnlab.run.rundir import load_final_evaluation, prepare_run_dir, save_final_evaluation
from dqnlab.run.train import train
from dqnlab.tools.report import (
    ALL_EQUAL,
    Report,
    RunResults,
    best_network_evaluator,
    build_report,
    curve_figure,
    find_runs,
    format_markdown,
    format_table,
    group_runs,
    load_reference_scores,
    write_report,
)

# Rows of data/atari_scores.csv: random, dqn_zoo human, Nature human, Nature DQN (± s.d.).
PONG = {"random": -20.7, "human": 14.6, "human_nature": 9.3, "dqn": 18.9, "dqn_std": 1.3}
BREAKOUT = {"random": 1.7, "human": 30.5, "human_nature": 31.8, "dqn": 401.2, "dqn_std": 26.9}

ATARI_TINY = {
    "replay_start_steps": 100,
    "replay_capacity": 1000,
    "batch_size": 8,
    "eval_period_steps": 100,
    "eval_steps": 100,
    "final_eval_episodes": 1,
    "final_eval_max_episode_frames": 400,
    "eval_networks_kept": "best_and_worst",
    "checkpoints_kept": 1,
}
CARTPOLE_TINY = {
    "env": "CartPole-v1",
    "total_steps": 600,
    "replay_start_steps": 100,
    "replay_capacity": 1000,
    "eval_period_steps": 200,
    "eval_steps": 200,
    "final_eval_max_episode_frames": 50,
    "eval_networks_kept": "best_and_worst",
    "checkpoints_kept": 1,
}
# Hand-written final evaluations: pong seeds 0 and 1, breakout seed 0.
PONG_SCORES = {0: [-21.0, -19.0], 1: [-10.0, -12.0]}
BREAKOUT_SCORES = [10.0, 20.0, 30.0]


def train_run(run_dir: Path, preset: str, **settings: Any) -> Path:
    config = resolve_config(preset, **settings)
    prepare_run_dir(run_dir, force=False)
    train(config, run_dir, torch.device("cpu"), progress=False, tensorboard=False)
    return run_dir


def write_final_evaluation(run_dir: Path, scores: list[float]) -> None:
    """A final evaluation with known scores, of the run's real best network."""
    best = run_dir / "checkpoints" / "best.pt"
    save_final_evaluation(
        run_dir,
        {
            "env": run_dir.name,
            "checkpoint": str(best),
            "checkpoint_step": rundir.load_network(best)["step"],
            "seed": 12345,
            "episodes": len(scores),
            "epsilon": 0.05,
            "max_episode_frames": 18000,
            "scores": scores,
            "mean": float(np.mean(scores)),
            "std": float(np.std(scores)),
            "frames": 0,
            "frames_per_second": 0.0,
        },
    )


def must_not_evaluate(run_dir: Path) -> dict[str, Any]:
    pytest.fail(f"{run_dir} has a final evaluation; none should be played")


class CountingEvaluator:
    """The report's default evaluator (2 games), counting its calls per run."""

    def __init__(self) -> None:
        self.calls: list[Path] = []
        self.evaluate = best_network_evaluator(torch.device("cpu"), episodes=2)

    def __call__(self, run_dir: Path) -> dict[str, Any]:
        self.calls.append(run_dir)
        return self.evaluate(run_dir)


def hns(score: float, game: dict[str, float], baseline: str) -> float:
    return 100 * (score - game["random"]) / (game[baseline] - game["random"])


@pytest.fixture(scope="module")
def atari_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Pong seeds 0 (300 steps) and 1 (200 steps: a shorter budget, fewer evaluations),
    breakout seed 0; final evaluations written by hand."""
    root = tmp_path_factory.mktemp("atari")
    runs = {
        "pong-s0": train_run(
            root / "pong-s0", "nature", env="pong", seed=0, total_steps=300, **ATARI_TINY
        ),
        "pong-s1": train_run(
            root / "pong-s1", "nature", env="pong", seed=1, total_steps=200, **ATARI_TINY
        ),
        "breakout-s0": train_run(
            root / "breakout-s0", "nature", env="breakout", seed=0, total_steps=300, **ATARI_TINY
        ),
    }
    write_final_evaluation(runs["pong-s0"], PONG_SCORES[0])
    write_final_evaluation(runs["pong-s1"], PONG_SCORES[1])
    write_final_evaluation(runs["breakout-s0"], BREAKOUT_SCORES)
    return runs


@pytest.fixture(scope="module")
def atari_report(atari_runs: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Report:
    out = tmp_path_factory.mktemp("atari-report")
    return write_report(list(atari_runs.values()), out, evaluate_missing=must_not_evaluate)


@pytest.fixture(scope="module")
def cartpole_sweep(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A sweep directory: life_loss_terminal true with seeds 0 and 1, false with seed 0
    (CartPole ignores the setting, but it is a setting: it labels a configuration)."""
    sweep = tmp_path_factory.mktemp("cartpole-sweep")
    for terminal, seed in ((True, 0), (True, 1), (False, 0)):
        name = f"life_loss_terminal={str(terminal).lower()}-s{seed}"
        train_run(sweep / name, "classic", seed=seed, life_loss_terminal=terminal, **CARTPOLE_TINY)
    (sweep / "logs").mkdir()  # a sweep holds other folders too: not runs, skipped
    return sweep


@pytest.fixture
def cartpole_copy(cartpole_sweep: Path, tmp_path: Path) -> Path:
    """The sweep as it was trained, for a test that adds final evaluations to it."""
    return Path(shutil.copytree(cartpole_sweep, tmp_path / "sweep"))


def row_of(report: Report, game: str, configuration: str = ALL_EQUAL) -> Any:
    (row,) = [r for r in report.rows if r.game == game and r.configuration == configuration]
    return row


# Reference scores --------------------------------------------------------------------


def test_reference_scores_ship_with_the_package() -> None:
    references = load_reference_scores()
    assert len(references) == 57
    pong = references["pong"]
    assert (pong.random, pong.human, pong.human_nature) == (-20.7, 14.6, 9.3)
    assert (pong.nature_dqn, pong.nature_dqn_std) == (18.9, 1.3)
    phoenix = references["phoenix"]  # outside the Nature 49: dqn_zoo's baselines only
    assert phoenix.human_nature is None and phoenix.nature_dqn is None
    assert phoenix.random == 761.4


def test_labels_name_the_settings_that_differ_and_ignore_operational_ones() -> None:
    def run(name: str, env: str = "breakout", **settings: Any) -> RunResults:
        config = resolve_config("nature", env=env, **settings)
        return RunResults(Path(name), config, [], None)

    seed_paper = {"optimizer": "rmsprop", "learning_rate": 0.00005}
    runs = [
        run("a", seed=0),
        run("b", seed=1, total_steps=1000, final_eval_episodes=5, checkpoints_kept=1,
            compile_update=True, eval_networks_kept="best_and_worst"),
        run("c", seed=0, **seed_paper),
        run("d", env="pong", seed=0),  # pong alone: labelled like breakout's runs
    ]  # fmt: skip
    groups = [(g.env, g.label, [r.run_dir.name for r in g.runs]) for g in group_runs(runs)]
    assert groups == [
        ("breakout", "optimizer=deepmind_rmsprop, learning_rate=0.00025", ["a", "b"]),
        ("breakout", "optimizer=rmsprop, learning_rate=5e-05", ["c"]),
        ("pong", "optimizer=deepmind_rmsprop, learning_rate=0.00025", ["d"]),
    ]
    (label,) = {g.label for g in group_runs([runs[0], runs[1], runs[3]])}
    assert label == ALL_EQUAL


# The results table -------------------------------------------------------------------


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


def test_terminal_table(atari_report: Report) -> None:
    text = format_table(atari_report)
    lines = text.splitlines()
    assert lines[0].split("  ")[0] == "Game"
    assert "HNS % (dqn_zoo human)" in lines[0] and "HNS % (Nature human)" in lines[0]
    assert any(line.startswith("pong ") and "-15.5 ± 4.5" in line for line in lines)
    assert any(line.startswith("median ") for line in lines)


# Learning curves ---------------------------------------------------------------------


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
        assert labels == [series.legend_label for series in curve.series]
        legend = axes.get_legend()
        assert [text.get_text() for text in legend.get_texts()] == labels
        bands = [c for c in axes.collections if isinstance(c, PolyCollection)]
        assert len(bands) == (1 if curve.game == "pong" else 0)
    pong = next(curve for curve in atari_report.curves if curve.game == "pong")
    assert pong.series[0].legend_label == f"{ALL_EQUAL} (2 seeds)"


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


# Grouping, non-Atari runs and the final evaluation -----------------------------------


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


# Run and sweep directories -----------------------------------------------------------


def test_a_sweep_directory_stands_for_its_runs(cartpole_sweep: Path, tmp_path: Path) -> None:
    for seed in (10, 2):
        (tmp_path / f"run-s{seed}").mkdir()
        (tmp_path / f"run-s{seed}" / "config.toml").write_text("")
    assert [path.name for path in find_runs([tmp_path])] == ["run-s2", "run-s10"]
    runs = find_runs([cartpole_sweep])
    assert len(runs) == 3 and all(path.parent == cartpole_sweep for path in runs)
    assert find_runs([cartpole_sweep, runs[1]]) == runs  # a run named twice counts once


@pytest.mark.parametrize("make", [lambda root: root, lambda root: root / "missing"])
def test_a_directory_that_is_neither_run_nor_sweep_is_refused(
    tmp_path: Path, make: Callable[[Path], Path]
) -> None:
    (tmp_path / "notes").mkdir()
    with pytest.raises(DqnlabError):
        write_report([make(tmp_path)], tmp_path / "out", evaluate_missing=must_not_evaluate)
    assert not (tmp_path / "out").exists()


def test_unsafe_game_names_make_safe_file_names() -> None:
    from dqnlab.tools.report.write import _file_stem

    taken: set[str] = set()
    assert _file_stem("ALE/Pong-v5", taken) == "curves-ALE_Pong-v5"
    assert _file_stem("my_envs:Grid", taken) == "curves-my_envs_Grid"
    assert _file_stem("my_envs/Grid", taken) == "curves-my_envs_Grid-2"


def test_csv_columns_are_numbers_where_numbers(atari_report: Report) -> None:
    out = atari_report.files[0].parent
    with (out / "results.csv").open(newline="") as handle:
        for row in csv.DictReader(handle):
            for name, value in row.items():
                if name not in ("game", "configuration", "score_std_over", "run_dirs") and value:
                    float(value)


# Q-values with the report ------------------------------------------------------------


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
    from dqnlab.tools.report.write import _unique_name

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
    record = best_network_evaluator(torch.device("cpu"), episodes=1)(run)
    assert record["checkpoint_step"] == played_step
    assert load_final_evaluation(run)["checkpoint_step"] == played_step


def test_no_frames_axis_when_configurations_repeat_actions_differently() -> None:
    from dqnlab.tools.report import Group, PeriodicEvaluation, learning_curves

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


def test_a_report_written_again_leaves_only_its_own_files(
    atari_runs: dict[str, Path], tmp_path: Path
) -> None:
    out = tmp_path / "out"
    first = write_report(
        list(atari_runs.values()), out, evaluate_missing=must_not_evaluate, inspect_frames=1
    )
    assert (out / "summary.csv").is_file() and (out / "curves-pong.png").is_file()
    assert len(first.inspections) == 3
    (out / "notes.txt").write_text("mine")  # not a report's file: kept
    write_report([atari_runs["breakout-s0"]], out, evaluate_missing=must_not_evaluate)
    assert sorted(p.name for p in out.iterdir()) == [
        "curves-breakout.png", "curves-breakout.svg", "notes.txt", "q-values", "results.csv",
        "results.md",
    ]  # fmt: skip
    assert list((out / "q-values").iterdir()) == []
