"""A resumed run compares its weights with the digests the killed run wrote past the
checkpoint (run/digests.py): it says so when it retraces it, and names the first step
where it does not."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import pytest
import torch

from dqnlab.config import resolve_config
from dqnlab.run.digests import WeightDigests, weights_digest
from dqnlab.run.logs import read_csv
from dqnlab.run.rundir import prepare_run_dir
from dqnlab.run.state import TrainingState
from dqnlab.run.train import train

KILLED_AT = 340  # the killed run's last step: it recorded digests at 225, 250, ..., 325


class Killed(Exception):
    """Stands in for a SIGKILL: the run ends where it is, with no checkpoint."""


def config():
    # Checkpoints at 200 and 400 only (no periodic evaluation, which would checkpoint too).
    return resolve_config(
        "classic", env="CartPole-v1", total_steps=400, replay_start_steps=50,
        eval_period_steps=0, checkpoint_period_steps=200, replay_capacity=1000,
        digest_period_steps=25,
    )  # fmt: skip


def train_killed(run: Path, monkeypatch) -> None:
    prepare_run_dir(run, force=False)
    original = TrainingState.advance

    def advance(self):
        if self.steps == KILLED_AT:
            raise Killed
        return original(self)

    with monkeypatch.context() as patch:
        patch.setattr(TrainingState, "advance", advance)
        with pytest.raises(Killed):
            train(config(), run, torch.device("cpu"), progress=False, tensorboard=False)


def resume(run: Path) -> None:
    train(config(), run, torch.device("cpu"), progress=False, tensorboard=False, resume=True)


def digest_rows(run: Path) -> list[tuple[int, str]]:
    return [(int(row["step"]), row["weights"]) for row in read_csv(run / "digests.csv")]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("digests") / "uninterrupted"
    prepare_run_dir(run, force=False)
    train(config(), run, torch.device("cpu"), progress=False, tensorboard=False)
    return run


def test_a_resume_that_retraces_the_killed_run_says_so(
    tmp_path: Path, monkeypatch, capsys, uninterrupted: Path
) -> None:
    run = tmp_path / "run"
    train_killed(run, monkeypatch)
    assert [step for step, _ in digest_rows(run)] == list(range(25, KILLED_AT, 25))
    capsys.readouterr()
    resume(run)
    said = capsys.readouterr().err
    assert "retraces the killed run: the same weights at all 5 steps" in said
    assert "not retracing" not in said
    # The killed run's rows past the checkpoint were replaced, not kept beside the new ones.
    assert digest_rows(run) == digest_rows(uninterrupted)
    assert [step for step, _ in digest_rows(run)] == list(range(25, 401, 25))


def test_a_resume_that_computes_otherwise_names_the_first_step_that_differs(
    tmp_path: Path, monkeypatch, capsys
) -> None:
    run = tmp_path / "run"
    train_killed(run, monkeypatch)
    original = TrainingState.load_state_dict

    def load_state_dict(self, state):
        original(self, state)
        with torch.no_grad():  # one weight one float step away: what other arithmetic does
            weight = next(self.agent.online.parameters())
            weight[0, 0] = torch.nextafter(weight[0, 0], torch.tensor(1.0))

    monkeypatch.setattr(TrainingState, "load_state_dict", load_state_dict)
    capsys.readouterr()
    resume(run)
    said = capsys.readouterr().err
    assert "not retracing the run that was killed: its online network at step 225 differs" in said
    assert said.count("not retracing") == 1 and "retraces" not in said
    assert [step for step, _ in digest_rows(run)] == list(range(25, 401, 25))


def test_a_torn_last_row_and_a_stop_at_a_checkpoint_compare_nothing(
    tmp_path: Path, monkeypatch, capsys, uninterrupted: Path
) -> None:
    run = tmp_path / "run"
    shutil.copytree(uninterrupted, run)
    with (run / "digests.csv").open("a") as handle:
        handle.write("425,0123")  # half-written by a kill: no end of line
    capsys.readouterr()
    longer = dataclasses.replace(config(), total_steps=450)
    train(longer, run, torch.device("cpu"), progress=False, tensorboard=False, resume=True)
    said = capsys.readouterr().err
    assert "retrac" not in said
    assert [step for step, _ in digest_rows(run)] == list(range(25, 451, 25))


def test_the_digest_tells_one_float_step_apart() -> None:
    network = torch.nn.Sequential(torch.nn.Linear(4, 3), torch.nn.BatchNorm1d(3))
    before = weights_digest(network)
    assert weights_digest(network) == before
    with torch.no_grad():
        network[0].bias[2] = torch.nextafter(network[0].bias[2], torch.tensor(9.0))
    assert weights_digest(network) != before


def test_each_row_reaches_the_file_at_once(tmp_path: Path) -> None:
    # A SIGKILL loses what Python still buffers: the row must be in the file before the
    # next step, with the file still open.
    digests = WeightDigests(tmp_path / "digests.csv", resume_step=None)
    network = torch.nn.Linear(2, 2)
    digests.record(25, network)
    assert (tmp_path / "digests.csv").read_text().splitlines() == [
        "step,weights",
        f"25,{weights_digest(network)}",
    ]
    digests.close()
