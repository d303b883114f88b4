"""Finding runs and grouping them by the settings that differ."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from dqnlab.analysis.report import (
    ALL_EQUAL,
    RunResults,
    find_runs,
    group_runs,
    load_run,
    write_report,
)
from dqnlab.config import resolve_config
from dqnlab.errors import DqnlabError
from tests.analysis.report.common import (
    must_not_evaluate,
)


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


def test_variants_that_differ_in_many_settings_are_named_by_their_presets() -> None:
    def run(name: str, preset: str, **settings: Any) -> RunResults:
        return RunResults(Path(name), resolve_config(preset, env="pong", **settings), [], None)

    runs = [run("a", "nature"), run("b", "rainbow", seed=1, total_steps=500_000),
            run("c", "c51")]  # fmt: skip
    labels = [(g.label, [r.run_dir.name for r in g.runs]) for g in group_runs(runs)]
    assert labels == [("preset=nature", ["a"]), ("preset=rainbow", ["b"]), ("preset=c51", ["c"])]
    # One run that is no preset: every configuration keeps the settings that differ.
    runs.append(run("d", "rainbow", n_step=5))
    assert all("n_step=" in g.label for g in group_runs(runs))
    # Few settings differ (nature against double): they name the configurations.
    pair = [run("a", "nature"), run("b", "double")]
    assert [g.label for g in group_runs(pair)] == ["target=max", "target=double"]


def test_a_sweep_directory_stands_for_its_runs(cartpole_sweep: Path, tmp_path: Path) -> None:
    for seed in (10, 2):
        (tmp_path / f"run-s{seed}").mkdir()
        (tmp_path / f"run-s{seed}" / "config.toml").write_text("")
    assert [path.name for path in find_runs([tmp_path])] == ["run-s2", "run-s10"]
    runs = find_runs([cartpole_sweep])
    assert len(runs) == 3 and all(path.parent == cartpole_sweep for path in runs)
    assert find_runs([cartpole_sweep, runs[1]]) == runs  # a run named twice counts once


def test_a_run_kept_without_its_checkpoints_is_as_far_as_its_final_evaluation(
    cartpole_sweep: Path, tmp_path: Path
) -> None:
    """docs/atari100k-results/runs/ keeps each run's config, episodes and final evaluation
    alone: the run counts as trained to the step of the network its evaluation played."""
    import json
    import shutil

    trained = find_runs([cartpole_sweep])[0]
    kept = tmp_path / trained.name
    shutil.copytree(trained, kept, ignore=shutil.ignore_patterns("checkpoints"))
    total = load_run(trained).config.total_steps
    assert load_run(trained).finished and load_run(kept).steps == 0
    (kept / "final_evaluation.json").write_text(json.dumps({"checkpoint_step": total}))
    assert load_run(kept).steps == total and load_run(kept).finished


@pytest.mark.parametrize("make", [lambda root: root, lambda root: root / "missing"])
def test_a_directory_that_is_neither_run_nor_sweep_is_refused(
    tmp_path: Path, make: Callable[[Path], Path]
) -> None:
    (tmp_path / "notes").mkdir()
    with pytest.raises(DqnlabError):
        write_report([make(tmp_path)], tmp_path / "out", evaluate_missing=must_not_evaluate)
    assert not (tmp_path / "out").exists()


def test_a_runs_environment_arguments_do_not_hide_its_preset() -> None:
    from dqnlab.analysis.report.runs import matching_preset

    config = resolve_config(
        "double", env="FrozenLake-v1", env_kwargs={"is_slippery": False},
        env_wrappers=("gymnasium.wrappers:RecordEpisodeStatistics",),
    )  # fmt: skip
    assert matching_preset(config) == "double"
    assert matching_preset(resolve_config("double", env="pong", n_step=3)) is None
