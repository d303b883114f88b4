"""`dqnlab train` end to end, as a user runs it (real processes, real environments), the
runs evaluated after; runs it refuses to overwrite; bad input as one clear line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dqnlab.analysis.video import video_file_name
from tests.helpers import dqnlab


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


def test_a_run_that_ends_with_its_final_evaluation_of_the_last_network(tmp_path: Path) -> None:
    # Atari 100k's protocol on CartPole: no periodic evaluation, the last network's final
    # evaluation played when training reaches its budget, and `evaluate` defaults to it.
    run = tmp_path / "cartpole"
    trained = dqnlab(
        "train", "--env", "CartPole-v1", "--steps", "300", "--run-dir", str(run),
        "--set", "replay_start_steps=100", "--set", "eval_period_steps=0",
        "--set", "final_eval_network='last'", "--set", "final_eval_after_training=true",
        "--set", "final_eval_episodes=2", "--no-progress",
    )  # fmt: skip
    assert trained.returncode == 0, trained.stderr
    assert "final evaluation of the last network, 2 games" in trained.stdout
    assert (run / "evaluations.csv").read_text().count("\n") <= 1  # its header at most
    saved = json.loads((run / "final_evaluation.json").read_text())
    assert saved["checkpoint_step"] == 300 and saved["episodes"] == 2
    assert saved["checkpoint"].endswith("last.pt")
    # `dqnlab evaluate` plays the same network by default, and keeps the record of more games.
    again = dqnlab("evaluate", str(run), "--episodes", "1")
    assert again.returncode == 0, again.stderr
    assert "kept" in again.stdout
    assert json.loads((run / "final_evaluation.json").read_text()) == saved


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


def test_the_final_evaluation_after_training_holds_the_runs_lease(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A run is not done until its final evaluation is saved: while it plays, `dqnlab status`
    # and a sweep must see the run held (not "retrying"), and no second process may start it.
    import torch

    from dqnlab.cli.train import _final_evaluation
    from dqnlab.config import resolve_config
    from dqnlab.run import evaluate
    from dqnlab.run.lease import LeaseHeld, RunLease, lease_is_live

    run = tmp_path / "run"
    run.mkdir()
    seen: list[bool] = []

    def fake_evaluation(run_dir: Path, *args: object) -> dict[str, float]:
        seen.append(lease_is_live(run_dir))
        with pytest.raises(LeaseHeld):
            RunLease(run_dir).acquire()
        return {"mean": 1.0, "std": 0.0, "episodes": 2}

    monkeypatch.setattr(evaluate, "evaluate_and_save", fake_evaluation)
    config = resolve_config("classic", env="CartPole-v1")
    _final_evaluation(config, run, torch.device("cpu"))
    assert seen == [True]
    assert not lease_is_live(run)  # released at the end
