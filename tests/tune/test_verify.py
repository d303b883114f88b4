"""`dqnlab tune --verify N`: the best settings and the starting preset trained on new
seeds, each run's best and last networks played; carried on after a stop, never played
twice; a check left by another best trial refused in one line."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

pytest.importorskip("optuna", reason="dqnlab tune needs the extra: pip install -e '.[tune]'")

from dqnlab.cli import main  # noqa: E402
from dqnlab.errors import DqnlabError  # noqa: E402
from dqnlab.run.rundir import load_run_config  # noqa: E402
from dqnlab.tune import verify as verify_module  # noqa: E402
from dqnlab.tune.driver import tune  # noqa: E402
from dqnlab.tune.verify import VerifyStopped, summary, verification_seeds, verify  # noqa: E402
from tests.helpers import dqnlab_main  # noqa: E402
from tests.tune.test_tune import TINY  # noqa: E402

CPU = torch.device("cpu")
# Three games per network, one thread (many times faster beside other work): a check of 2
# seeds × 2 settings takes a few seconds.
PLAN = dataclasses.replace(TINY, fixed={**TINY.fixed, "final_eval_episodes": 3, "threads": 1})


@pytest.fixture(scope="module")
def study_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny study of two trials, its best.toml written."""
    path = tmp_path_factory.mktemp("verify") / "study"
    tune(path, PLAN, 2, CPU, "dqnlab tune --env CartPole-v1 --trials 2")
    return path


def test_new_seeds_follow_the_study_s_own() -> None:
    assert verification_seeds(PLAN, 0, 5) == [10, 11, 12, 13, 14]
    assert verification_seeds(PLAN, 3, 2) == [13, 14]
    assert verification_seeds(dataclasses.replace(PLAN, seeds=12), 0, 2) == [12, 13]


def test_the_check_trains_the_best_settings_and_the_start_on_new_seeds(study_dir: Path) -> None:
    best = json.loads((study_dir / "best.toml").read_text().split("# Searched: ")[1].split("\n")[0])
    checked = verify(study_dir, PLAN, 2, CPU)
    assert [(row.settings, row.seed, row.network) for row in checked] == [
        (settings, seed, network)
        for settings in ("tuned", "start")
        for seed in (10, 11)
        for network in ("best", "last")
    ]
    for seed in (10, 11):
        tuned = load_run_config(study_dir / "verify" / f"tuned-s{seed}")
        start = load_run_config(study_dir / "verify" / f"start-s{seed}")
        assert (tuned.seed, start.seed) == (seed, seed)
        assert (tuned.total_steps, start.total_steps) == (300, 300)
        assert tuned.learning_rate == best["learning_rate"]
        assert tuned.batch_size == best["batch_size"]
        assert start.learning_rate == 0.0023  # classic's own
        assert tuned.eval_steps == start.eval_steps == 50  # the study's fixed settings
    with (study_dir / "verify.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 8
    for row, one in zip(rows, checked, strict=True):
        record = json.loads(
            (study_dir / "verify" / f"{row['settings']}-s{row['seed']}" / f"{row['network']}.json")
            .read_text()
        )  # fmt: skip
        assert len(record["scores"]) == int(row["episodes"]) == 3
        assert float(row["mean"]) == pytest.approx(record["mean"], rel=1e-5)
        assert one.scores == tuple(record["scores"])
    lines = summary(checked, "classic")
    assert lines[0].startswith("tuned (best.toml): best network ")
    assert lines[1].startswith("start (classic): best network ")


def test_a_check_carried_on_trains_and_plays_only_what_is_missing(
    study_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    first = verify(study_dir, PLAN, 2, CPU)
    played: list[tuple[str, str]] = []
    real_evaluation = verify_module.final_evaluation

    def evaluation(run_dir, network, *args):  # noqa: ANN001, ANN202
        played.append((run_dir.name, network))
        return real_evaluation(run_dir, network, *args)

    def no_training(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("a run the check holds whole was trained again")

    monkeypatch.setattr(verify_module, "final_evaluation", evaluation)
    monkeypatch.setattr(verify_module, "train", no_training)
    assert verify(study_dir, PLAN, 2, CPU) == first
    assert played == []
    (study_dir / "verify" / "start-s11" / "last.json").unlink()
    monkeypatch.setattr(verify_module, "train", real_train_once := _counting(verify_module))
    assert verify(study_dir, PLAN, 2, CPU) == first  # the same network, the same games
    assert played == [("start-s11", "last")] and real_train_once.calls == 1


def _counting(module):  # noqa: ANN001, ANN202
    from dqnlab.run.train import train as real_train

    def train(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        train.calls += 1  # type: ignore[attr-defined]
        return real_train(*args, **kwargs)

    train.calls = 0  # type: ignore[attr-defined]
    return train


def test_a_signal_stops_the_check_in_one_line_and_the_same_call_carries_it_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    study_dir = tmp_path / "study"
    tune(study_dir, PLAN, 1, CPU, "dqnlab tune --env CartPole-v1 --trials 1")
    from dqnlab.run.train import train as real_train

    def stopped(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        result = real_train(*args, **kwargs)
        return dataclasses.replace(result, interrupted="SIGINT")

    monkeypatch.setattr(verify_module, "train", stopped)
    with pytest.raises(VerifyStopped) as stop:
        verify(study_dir, PLAN, 1, CPU)
    assert stop.value.exit_status == 130
    assert str(stop.value) == (
        f"stopped by SIGINT in {study_dir / 'verify' / 'tuned-s10'} after saving a "
        "checkpoint; the same command carries the check on"
    )
    assert not (study_dir / "verify" / "tuned-s10" / "best.json").exists()
    monkeypatch.setattr(verify_module, "train", real_train)
    assert len(verify(study_dir, PLAN, 1, CPU)) == 4


def test_a_check_of_another_best_trial_is_refused_in_one_line(tmp_path: Path) -> None:
    study_dir = tmp_path / "study"
    tune(study_dir, PLAN, 1, CPU, "dqnlab tune --env CartPole-v1 --trials 1")
    verify(study_dir, PLAN, 1, CPU)
    best = study_dir / "best.toml"
    text = best.read_text()
    best.write_text(text.replace("\nbatch_size = ", "\nbatch_size = 7  # was ", 1))
    with pytest.raises(DqnlabError, match=r"^--verify: .*delete .*verify to check these$"):
        verify(study_dir, PLAN, 1, CPU)


def test_a_study_without_a_complete_trial_has_nothing_to_check(tmp_path: Path) -> None:
    with pytest.raises(DqnlabError, match="best.toml does not exist"):
        verify(tmp_path, PLAN, 1, CPU)


def test_the_command_checks_after_the_study_and_says_the_means(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    study_dir = tmp_path / "s"
    monkeypatch.setattr(sys, "argv", [
        "dqnlab", "tune", "--env", "CartPole-v1", "--trials", "1", "--steps", "300",
        "--evaluations", "2", "--set", "eval_steps=50", "--set", "heldout_transitions=50",
        "--set", "final_eval_episodes=3", "--set", "threads=1", "--verify", "1",
        "--study-dir", str(study_dir),
    ])  # fmt: skip
    with pytest.raises(SystemExit) as exit_info:
        main()
    out = capsys.readouterr().out
    assert not exit_info.value.code
    with (study_dir / "verify.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    means = {(row["settings"], row["network"]): float(row["mean"]) for row in rows}
    assert len(rows) == 4
    assert "checking the best settings and classic on 1 new seeds" in out
    assert f"tuned (best.toml): best network {means['tuned', 'best']:.2f}" in out
    assert f"start (classic): best network {means['start', 'best']:.2f}" in out
    assert f"last network {means['start', 'last']:.2f}" in out


def test_the_command_refuses_a_negative_check_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    status, err = dqnlab_main(
        capsys, monkeypatch, "tune", "--env", "CartPole-v1", "--trials", "1", "--steps", "300",
        "--verify", "-1", "--study-dir", str(tmp_path / "s"),
    )  # fmt: skip
    assert status == 2 and err.strip() == "dqnlab: error: --verify -1: must be 0 (no check) or more"
    assert not (tmp_path / "s").exists()


def test_two_jobs_check_each_run_as_one_process_does(tmp_path: Path) -> None:
    """The runs dealt out to two worker processes (one PyTorch thread each, the study's
    threads left free) give the same games as the check in one process at one thread."""
    plan = dataclasses.replace(PLAN, fixed={**TINY.fixed, "final_eval_episodes": 3})
    tune(tmp_path / "jobs", plan, 1, CPU, "dqnlab tune --env CartPole-v1 --trials 1")
    shutil.copytree(tmp_path / "jobs", tmp_path / "one")
    in_jobs = verify(tmp_path / "jobs", plan, 2, CPU, jobs=2)
    assert in_jobs == verify(tmp_path / "one", plan, 2, CPU, threads=1)
    assert len(in_jobs) == 8
    for run_dir in (tmp_path / "jobs" / "verify").iterdir():
        assert load_run_config(run_dir).threads == 1
    assert (tmp_path / "jobs" / "verify.csv").read_text() == (
        tmp_path / "one" / "verify.csv"
    ).read_text()


def test_ctrl_c_stops_both_jobs_of_the_check_in_one_line_and_the_same_command_ends_it(
    tmp_path: Path,
) -> None:
    """SIGINT to the process group, as Ctrl-C sends it, while two jobs train a run each.
    A checkpoint every 50 steps: the signal goes once both runs have one, long before
    either can end its 2,500 (every 250 let the faster run finish first once, on CI)."""
    study_dir = tmp_path / "study"
    args = [sys.executable, "-m", "dqnlab", "tune", "--env", "CartPole-v1", "--trials", "1",
            "--steps", "2500", "--evaluations", "2", "--pruner", "none", "--jobs", "2",
            "--verify", "1", "--set", "mlp_hidden_sizes=[8]", "--set", "threads=1",
            "--set", "checkpoint_period_steps=50", "--set", "eval_steps=50",
            "--set", "heldout_transitions=50", "--set", "final_eval_episodes=3",
            "--study-dir", str(study_dir)]  # fmt: skip
    process = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               start_new_session=True)  # fmt: skip
    runs = [study_dir / "verify" / name for name in ("tuned-s10", "start-s10")]
    deadline = time.monotonic() + 120
    while not all((run / "checkpoints").is_dir() and any((run / "checkpoints").iterdir())
                  for run in runs):  # fmt: skip
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    assert re.fullmatch(
        r"dqnlab: error: stopped by SIGINT in \S+/verify/(tuned|start)-s10 and "
        r"\S+/verify/(tuned|start)-s10 each after saving a checkpoint; the same command "
        r"carries the check on\n",
        err,
    ), err
    assert not (study_dir / "verify.csv").exists()
    finished = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert finished.returncode == 0, finished.stderr
    with (study_dir / "verify.csv").open() as handle:
        assert len(list(csv.DictReader(handle))) == 4
