"""The `dqnlab` command end to end, as a user runs it: real processes, real environments."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest

from dqnlab.analysis.video import video_file_name


def dqnlab(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "dqnlab", *args],
        capture_output=True, text=True, cwd=cwd, timeout=600,
    )  # fmt: skip


def test_train_and_evaluate_cartpole(tmp_path: Path) -> None:
    run = tmp_path / "cartpole"
    trained = dqnlab(
        "train", "--env", "CartPole-v1", "--steps", "2000", "--seed", "1", "--run-dir", str(run),
        "--set", "replay_start_steps=500", "--set", "eval_period_steps=1000",
        "--set", "eval_steps=500", "--no-progress",
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr
    assert "2000 steps" in trained.stdout
    out = tmp_path / "eval.json"
    evaluated = dqnlab("evaluate", str(run), "--episodes", "3", "--json", str(out))
    assert evaluated.returncode == 0, evaluated.stderr
    result = json.loads(out.read_text())
    # A checkpoint file evaluates with the configuration saved inside it.
    last = str(run / "checkpoints" / "last.pt")
    elsewhere = dqnlab("evaluate", str(tmp_path), "--checkpoint", last, "--episodes", "1")
    assert elsewhere.returncode == 0, elsewhere.stderr
    assert set(result) == {"env", "checkpoint", "checkpoint_step", "episodes", "scores", "mean",
                           "std", "frames", "frames_per_second", "seed", "epsilon",
                           "max_episode_frames"}  # fmt: skip
    assert result["epsilon"] == 0.0 and result["seed"] == 12345  # classic preset: greedy
    assert result["env"] == "CartPole-v1" and result["episodes"] == len(result["scores"]) == 3
    assert result["frames"] == sum(result["scores"])  # CartPole: +1 per step, frame = step
    assert f"{result['mean']:.2f} ± {result['std']:.2f}" in evaluated.stdout
    # The best network's evaluation is the run's final one, unless one of more games is kept.
    assert json.loads((run / "final_evaluation.json").read_text()) == result
    fewer = dqnlab("evaluate", str(run), "--episodes", "2")
    assert fewer.returncode == 0 and "kept" in fewer.stdout
    assert json.loads((run / "final_evaluation.json").read_text()) == result


def test_train_and_evaluate_an_atari_game(tmp_path: Path) -> None:
    run = tmp_path / "pong"
    trained = dqnlab(
        "train", "--env", "pong", "--steps", "600", "--run-dir", str(run),
        "--set", "replay_start_steps=200", "--set", "replay_capacity=2000",
        "--set", "eval_period_steps=300", "--set", "eval_steps=200", "--device", "cpu",
        "--no-progress",
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr
    assert "preset nature" in trained.stdout
    evaluations = (run / "evaluations.csv").read_text().splitlines()
    assert [line.split(",")[0] for line in evaluations[1:]] == ["300", "600"]
    out = tmp_path / "eval.json"
    evaluated = dqnlab("evaluate", str(run), "--checkpoint", "last", "--episodes", "1",
                       "--json", str(out))  # fmt: skip
    assert evaluated.returncode == 0, evaluated.stderr
    result = json.loads(out.read_text())
    # A full Pong game of a barely trained agent: 21 points to the opponent, many frames.
    assert result["scores"][0] < 0 and result["frames"] > 3000
    # Filmed, the same game: the same score, in the file's name.
    videos = tmp_path / "videos"
    filmed = dqnlab("evaluate", str(run), "--checkpoint", "last", "--episodes", "1",
                    "--video", str(videos), "--json", str(out))  # fmt: skip
    assert filmed.returncode == 0, filmed.stderr
    assert json.loads(out.read_text())["scores"] == result["scores"]
    name = video_file_name("pong", 1, 1, result["scores"][0], "mp4")
    assert [path.name for path in videos.iterdir()] == [name]
    assert (videos / name).stat().st_size > 10_000


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


@pytest.mark.parametrize(
    "command",
    [
        "train",
        "resume",
        "evaluate",
        "bench",
        "ablate",
        "sweep",
        "status",
        "report",
        "inspect",
        "games",
    ],
)
def test_every_command_has_help(command: str) -> None:
    result = dqnlab(command, "--help")
    assert result.returncode == 0 and "Usage:" in result.stdout


def test_refuses_to_overwrite_a_run(tmp_path: Path) -> None:
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.toml").write_text("")
    refused = dqnlab("train", "--env", "CartPole-v1", "--run-dir", str(tmp_path / "run"))
    assert refused.returncode == 2 and "--force" in refused.stderr


def test_force_never_deletes_a_directory_that_is_not_a_run(tmp_path: Path) -> None:
    precious = tmp_path / "project"
    precious.mkdir()
    (precious / "thesis.tex").write_text("years of work")
    refused = dqnlab("train", "--env", "CartPole-v1", "--run-dir", str(precious), "--force")
    assert refused.returncode == 2 and "not a dqnlab run directory" in refused.stderr
    assert (precious / "thesis.tex").read_text() == "years of work"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--env", "pongg"], "close matches: pong"),
        (["--env", "CartPole-v9"], "close matches"),
        (["--env", "Pendulum-v1"], "Discrete action space"),
        (["--env", "pong", "--set", "discount=2"], "discount = 2.0 must be between 0 and 1"),
        (["--env", "pong", "--preset", "natur"], "unknown preset 'natur'"),
        (["--env", "pong", "--set", "networkk=mlp"], "did you mean network"),
        (["--env", "pong", "--device", "tpu"], "--device 'tpu' is not one of"),
    ],
)
def test_bad_input_gives_one_clear_line(tmp_path: Path, args: list[str], message: str) -> None:
    result = dqnlab("train", *args, "--run-dir", str(tmp_path / "run"), "--no-progress")
    assert result.returncode == 2
    assert message in result.stderr
    assert "Traceback" not in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists()


def test_evaluate_a_directory_that_is_not_a_run(tmp_path: Path) -> None:
    result = dqnlab("evaluate", str(tmp_path))
    assert result.returncode == 2 and "not a dqnlab run directory" in result.stderr


def test_lists(tmp_path: Path) -> None:
    games = dqnlab("games")
    assert games.returncode == 0 and "space_invaders" in games.stdout.split()
    presets = dqnlab("presets")
    assert presets.stdout.split() == ["classic", "machado", "nature", "seed-paper"]
    nature = dqnlab("presets", "nature")
    assert "learning_rate = 0.00025" in nature.stdout
