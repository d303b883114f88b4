"""`dqnlab export`: a run's network as safetensors and what describes it, a folder that
`dqnlab evaluate` plays like the run, written whole or not at all."""

from __future__ import annotations

import json
import struct
import sys
from pathlib import Path

import pytest
import torch

from dqnlab.errors import DqnlabError
from dqnlab.run import exported, rundir
from dqnlab.run.evaluate import final_evaluation
from tests.helpers import dqnlab_main
from tests.hub.conftest import EVALUATION_SEED
from tests.hub.folders import copy_folder


def test_the_folder_holds_the_network_as_safetensors_and_what_describes_it(
    exported_folder: Path, tiny_run: Path
) -> None:
    names = {path.name for path in exported_folder.iterdir()}
    videos = names & {"replay.mp4", "replay.gif"}  # GIF where no MP4 encoder
    assert len(videos) == 1 and (exported_folder / videos.pop()).stat().st_size > 0
    assert names - {"replay.mp4", "replay.gif"} == {
        "README.md", "config.toml", "model.safetensors", "results.json", "learning-curve.png",
        "episodes.csv", "evaluations.csv",
    }  # fmt: skip
    # safetensors: an 8-byte header length, a JSON header, raw tensor bytes; no pickle.
    data = (exported_folder / "model.safetensors").read_bytes()
    (length,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + length])
    assert header["__metadata__"]["format"] == exported.SAFETENSORS_FORMAT
    ends = [entry["data_offsets"][1] for key, entry in header.items() if key != "__metadata__"]
    assert len(data) == 8 + length + max(ends)
    best = torch.load(rundir.network_path(tiny_run, "best"), weights_only=True)
    payload = exported.load_network(exported_folder / "model.safetensors")
    assert payload["network"].keys() == best["network"].keys()
    for name, tensor in best["network"].items():
        assert torch.equal(payload["network"][name], tensor), name
    for key in ("config", "action_names", "step", "observation_dtype", "eval_mean"):
        assert payload[key] == best[key], key
    assert tuple(payload["input_shape"]) == tuple(best["input_shape"]) == (1, 4)
    assert (exported_folder / "config.toml").read_text() == (tiny_run / "config.toml").read_text()
    # results.json: the final evaluation the export played (and saved in the run).
    results = json.loads((exported_folder / "results.json").read_text())
    saved = rundir.load_final_evaluation(tiny_run)
    assert saved is not None
    for key in ("mean", "std", "scores", "episodes", "seed", "checkpoint_step", "epsilon"):
        assert results[key] == saved[key], key
    assert (results["episodes"], results["seed"], results["checkpoint"]) == (
        3,
        EVALUATION_SEED,
        "best",
    )
    assert results["checkpoint_step"] == best["step"]
    assert "protocol" in results and results["network"] == "model.safetensors"


def test_dqnlab_evaluate_plays_an_exported_folder_as_the_run(
    exported_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch
) -> None:
    folder = copy_folder(exported_folder, tmp_path / "agent")
    results = json.loads((folder / "results.json").read_text())
    played, network = final_evaluation(folder, "best", None, EVALUATION_SEED, torch.device("cpu"))
    assert played.scores == results["scores"]
    assert network.path == folder / "model.safetensors"
    assert network.step == results["checkpoint_step"]
    json_path = tmp_path / "evaluation.json"
    status, _ = dqnlab_main(
        capsys, monkeypatch, "evaluate", str(folder), "--seed", str(EVALUATION_SEED),
        "--device", "cpu", "--json", str(json_path),
    )  # fmt: skip
    assert status == 0
    assert json.loads(json_path.read_text())["scores"] == results["scores"]
    assert (folder / "final_evaluation.json").is_file()  # as in a run directory
    status, error = dqnlab_main(
        capsys, monkeypatch, "evaluate", str(folder), "--checkpoint", "last"
    )
    assert status == 2 and "exported folder" in error and len(error.splitlines()) == 1


def test_a_safetensors_file_that_dqnlab_did_not_write_is_refused(tmp_path: Path) -> None:
    import safetensors.torch

    path = tmp_path / "model.safetensors"
    safetensors.torch.save_file({"weight": torch.zeros(2, 2)}, str(path))
    with pytest.raises(DqnlabError, match="is not a dqnlab network"):
        exported.load_network(path)
    path.write_bytes(b"\x80\x04K\x01.")  # a pickle, named .safetensors
    with pytest.raises(DqnlabError, match="not a readable safetensors file"):
        exported.load_network(path)


def test_the_export_is_written_whole_or_not_at_all(
    tiny_run: Path, tmp_path: Path, monkeypatch
) -> None:
    from dqnlab.hub import export

    def broken_card(facts: object) -> str:
        raise RuntimeError("the card failed")

    monkeypatch.setattr(export, "model_card", broken_card)
    out = tmp_path / "exports" / "agent"
    with pytest.raises(RuntimeError, match="the card failed"):
        export.export_run(tiny_run, out, seed=0, device=torch.device("cpu"), video=False)
    assert list((tmp_path / "exports").iterdir()) == []  # no folder, no staging left
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(DqnlabError, match="is not an empty directory"):
        export.export_run(tiny_run, out, seed=0, device=torch.device("cpu"), video=False)
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_without_the_hub_extra_the_commands_say_how_to_install_it(
    tiny_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch
) -> None:
    monkeypatch.setitem(sys.modules, "safetensors", None)  # import fails, as when missing
    for args in (
        ["export", str(tiny_run), "--out", str(tmp_path / "out")],
        ["push", str(tiny_run), "--repo-id", "someone/agent"],
        ["pull", "someone/agent", "--run-dir", str(tmp_path / "pulled")],
    ):
        status, error = dqnlab_main(capsys, monkeypatch, *args)
        assert status == 2 and "pip install 'dqnlab[hub]'" in error, args
        assert len(error.splitlines()) == 1
    assert not (tmp_path / "out").exists() and not (tmp_path / "pulled").exists()
