"""An exported (or pulled) folder in `dqnlab inspect` and `dqnlab report`: its one network's
Q-values, and whether the run it came from had finished training."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from dqnlab.analysis.inspection.qvalues import compare_networks
from dqnlab.analysis.report.runs import load_run
from dqnlab.run import exported, rundir
from tests.helpers import dqnlab_main
from tests.hub.folders import copy_folder


def test_inspect_shows_the_exported_network_as_the_run_shows_its_best(
    exported_folder: Path, tiny_run: Path, tmp_path: Path
) -> None:
    folder = copy_folder(exported_folder, tmp_path / "agent")
    cpu = torch.device("cpu")
    mine = compare_networks(folder, frames=4, checkpoints=["best"], device=cpu)
    theirs = compare_networks(tiny_run, frames=4, checkpoints=["best"], device=cpu)
    assert [n.path for n in mine.networks] == [folder / exported.MODEL_FILE]
    assert mine.networks[0].step == theirs.networks[0].step
    # The same network on the same game's frames: the same Q-values.
    assert mine.q_values.shape == theirs.q_values.shape
    assert np.array_equal(mine.q_values, theirs.q_values)


def test_dqnlab_inspect_takes_an_exported_folder_and_refuses_a_second_network(
    exported_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch
) -> None:
    folder = copy_folder(exported_folder, tmp_path / "agent")
    out = tmp_path / "inspection"
    status, error = dqnlab_main(
        capsys, monkeypatch, "inspect", str(folder), "--frames", "3", "--out", str(out),
        "--device", "cpu",
    )  # fmt: skip
    assert status == 0, error
    with (out / "q_values.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 3 * 2  # 3 frames x CartPole's 2 actions, one network
    status, error = dqnlab_main(
        capsys, monkeypatch, "inspect", str(folder), "--checkpoints", "best,worst"
    )
    assert status == 2 and len(error.splitlines()) == 1
    assert "exported folder: its one network is model.safetensors" in error


def test_report_reads_how_far_the_exported_run_trained(
    exported_folder: Path, tiny_run: Path, tmp_path: Path
) -> None:
    results = json.loads((exported_folder / exported.RESULTS_FILE).read_text())
    assert results["trained_steps"] == rundir.network_step(tiny_run, "last") == 600
    run = load_run(exported_folder)
    assert run.steps == 600 and run.finished  # not "unfinished", as it was before
    # An export without the field (an older dqnlab's): the network's own step, the least
    # the run trained, so it reads unfinished rather than finished.
    older = copy_folder(exported_folder, tmp_path / "older")
    del results["trained_steps"]
    (older / exported.RESULTS_FILE).write_text(json.dumps(results))
    best_step = exported.read_description(older / exported.MODEL_FILE)["step"]
    assert load_run(older).steps == best_step
