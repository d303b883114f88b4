"""`dqnlab report`, `dqnlab inspect` and `dqnlab evaluate` on runs trained by the command."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from tests.helpers import dqnlab


def test_report_and_inspect_two_runs_that_differ_in_one_setting(tmp_path: Path) -> None:
    runs = []
    for gamma in ("0.9", "0.99"):
        run = tmp_path / "runs" / f"cartpole-{gamma}"
        trained = dqnlab(
            "train", "--env", "CartPole-v1", "--steps", "900", "--run-dir", str(run),
            "--set", f"discount={gamma}", "--set", "replay_start_steps=300",
            "--set", "eval_period_steps=300", "--set", "eval_steps=300", "--no-progress",
        )  # fmt: skip
        assert trained.returncode == 0, trained.stderr
        runs.append(run)
    out = tmp_path / "report"
    reported = dqnlab("report", *map(str, runs), "--out", str(out), "--episodes", "2",
                      "--frames", "3")  # fmt: skip
    assert reported.returncode == 0, reported.stderr
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert sorted(row["configuration"] for row in rows) == ["discount=0.9", "discount=0.99"]
    for run, row in zip(runs, sorted(rows, key=lambda row: row["configuration"]), strict=True):
        final = json.loads((run / "final_evaluation.json").read_text())  # played by report
        assert final["episodes"] == 2 and float(row["score_mean"]) == pytest.approx(final["mean"])
        assert f"{final['mean']:.1f} ± {final['std']:.1f}" in reported.stdout
        q_values = list(csv.DictReader((out / "q-values" / run.name / "q_values.csv").open()))
        assert {r["network"] for r in q_values} == {"best", "worst"}
        assert len(q_values) == 2 * 3 * 2  # networks x frames x CartPole's actions
    assert (out / "curves-CartPole-v1.png").stat().st_size > 0
    assert "![CartPole-v1](curves-CartPole-v1.png)" in (out / "results.md").read_text()

    inspected = dqnlab("inspect", str(runs[0]), "--frames", "2", "--checkpoints", "best")
    assert inspected.returncode == 0, inspected.stderr
    assert len(list((runs[0] / "inspect").glob("frame-*.png"))) == 2
    # By default (eval_networks_kept = "best_and_worst") no network is kept by step.
    missing = dqnlab("inspect", str(runs[0]), "--checkpoints", "123")
    assert missing.returncode == 2 and "keeps no network per evaluation" in missing.stderr


def test_evaluate_a_directory_that_is_not_a_run(tmp_path: Path) -> None:
    result = dqnlab("evaluate", str(tmp_path))
    assert result.returncode == 2 and "not a dqnlab run directory" in result.stderr
