"""`dqnlab push` and `dqnlab pull` through a fake HfApi (no test reaches the network): one
commit up; down, the checks of a stranger's folder, each refusal one line with nothing
written; and the pulled agent scores what the run scored."""

from __future__ import annotations

import inspect
import json
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import httpx2
import pytest
import torch
from huggingface_hub import HfApi
from huggingface_hub.errors import HfHubHTTPError

from dqnlab.errors import ConfigError, DqnlabError
from dqnlab.hub import remote
from dqnlab.run import exported, rundir
from dqnlab.run.evaluate import final_evaluation
from tests.helpers import dqnlab_main
from tests.hub.conftest import EVALUATION_SEED
from tests.hub.fake_hub import COMMIT, FakeHubApi, http_error
from tests.hub.folders import change_settings

REPO = "someone/cartpole-dqn"
CPU = torch.device("cpu")


@pytest.fixture
def hub(tmp_path: Path) -> FakeHubApi:
    return FakeHubApi(tmp_path / "hub")


def published(hub: FakeHubApi, folder: Path, repo_id: str = REPO) -> Path:
    """`folder` as the main branch of `repo_id` on the fake Hub."""
    shutil.copytree(folder, hub.repo(repo_id))
    return hub.repo(repo_id)


def assert_nothing_written(target: Path) -> None:
    assert not target.exists()
    assert not [p for p in target.parent.glob(f".{target.name}.partial-*")]


def test_kwargs_dqnlab_passes_exist_in_huggingface_hubs_api(
    tiny_run: Path, hub: FakeHubApi, tmp_path: Path
) -> None:
    remote.push(tiny_run, REPO, api=hub, seed=EVALUATION_SEED, device=CPU, video=False, echo=print)
    remote.pull(REPO, tmp_path / "pulled", api=hub)
    for name, arguments in hub.calls:
        accepted = inspect.signature(getattr(HfApi, name)).parameters
        assert set(arguments) - {"files"} <= set(accepted), name


def test_push_creates_the_repository_and_uploads_the_folder_as_one_commit(
    tiny_run: Path, hub: FakeHubApi
) -> None:
    folder, commit = remote.push(
        tiny_run, REPO, private=True, api=hub, seed=EVALUATION_SEED, device=CPU, video=False,
        echo=print,
    )  # fmt: skip
    (created,) = hub.called("create_repo")
    assert created["exist_ok"] is True and created["private"] is True
    (upload,) = hub.called("upload_folder")
    assert upload["repo_id"] == REPO and upload["files"] == folder.files
    assert {"model.safetensors", "config.toml", "results.json", "README.md"} <= set(upload["files"])
    assert not any(name.endswith(".pt") for name in upload["files"])
    assert "+/-" in upload["commit_message"]
    card = (hub.repo(REPO) / "README.md").read_text()
    assert (
        "name: cartpole-dqn" in card and f"dqnlab pull {REPO} --run-dir runs/cartpole-dqn" in card
    )
    assert commit.commit_url.endswith(COMMIT)
    assert not Path(upload["folder_path"]).exists()  # the temporary export is gone
    # Pushed again: an earlier push's file this one lacks goes, the owner's own stay.
    (hub.repo(REPO) / "replay.gif").write_bytes(b"GIF89a")
    (hub.repo(REPO) / "notes.md").write_text("mine")
    remote.push(tiny_run, REPO, api=hub, seed=EVALUATION_SEED, device=CPU, video=False)
    assert {p.name for p in hub.repo(REPO).iterdir()} == {*folder.files, "notes.md"}


def test_push_pull_evaluate_reproduces_the_runs_score(
    tiny_run: Path, hub: FakeHubApi, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch
) -> None:
    remote.push(tiny_run, REPO, api=hub, seed=EVALUATION_SEED, device=CPU, video=False, echo=print)
    (hub.repo(REPO) / ".gitattributes").write_text("*.safetensors filter=lfs\n")  # as the Hub
    monkeypatch.setattr(remote, "default_api", lambda: hub)  # the command's own HfApi
    target = tmp_path / "runs" / "pulled"
    status, error = dqnlab_main(capsys, monkeypatch, "pull", REPO, "--run-dir", str(target))
    assert status == 0, error
    (download,) = hub.called("snapshot_download")
    assert download["revision"] == COMMIT  # the commit the file list was read at
    assert download["allow_patterns"] == list(exported.FOLDER_FILES)
    assert json.loads((target / "pulled.json").read_text())["commit"] == COMMIT
    assert not (target / ".gitattributes").exists()
    results = json.loads((target / "results.json").read_text())
    run_record = rundir.load_final_evaluation(tiny_run)
    assert run_record is not None and run_record["scores"] == results["scores"]
    status, error = dqnlab_main(
        capsys, monkeypatch, "evaluate", str(target), "--seed", str(results["seed"]),
        "--device", "cpu", "--json", str(tmp_path / "pulled.json"),
    )  # fmt: skip
    assert status == 0, error
    assert json.loads((tmp_path / "pulled.json").read_text())["scores"] == results["scores"]


@pytest.mark.parametrize("pickle_file", ["pytorch_model.bin", "model.pt", "agent.pkl"])
def test_pull_refuses_a_repository_holding_pickles_before_downloading(
    exported_folder: Path, hub: FakeHubApi, tmp_path: Path, pickle_file: str
) -> None:
    repo = published(hub, exported_folder)
    (repo / pickle_file).write_bytes(b"\x80\x04K\x01.")
    if pickle_file == "model.pt":
        (repo / "model.safetensors").unlink()
    target = tmp_path / "pulled"
    with pytest.raises(
        DqnlabError, match=f"holds {pickle_file}: files that may be pickles"
    ) as error:
        remote.pull(REPO, target, api=hub)
    assert len(str(error.value).splitlines()) == 1
    assert hub.called("snapshot_download") == []
    assert_nothing_written(target)


def test_a_pickle_in_a_local_folder_is_refused_too(exported_folder: Path, tmp_path: Path) -> None:
    from dqnlab.hub.checks import check_folder

    folder = tmp_path / "agent"
    shutil.copytree(exported_folder, folder)
    (folder / "extra").mkdir()
    (folder / "extra" / "network.pth").write_bytes(b"\x80\x04K\x01.")
    with pytest.raises(DqnlabError, match="holds extra/network.pth"):
        check_folder(folder)


@pytest.mark.parametrize("where", ["toml", "metadata"])
def test_pull_refuses_settings_from_a_newer_dqnlab(
    exported_folder: Path, hub: FakeHubApi, tmp_path: Path, where: str
) -> None:
    repo = published(hub, exported_folder)
    change_settings(repo, where, frame_warp=2)
    target = tmp_path / "pulled"
    with pytest.raises(ConfigError, match="does not know: frame_warp; it was written by dqnlab"):
        remote.pull(REPO, target, api=hub)
    assert_nothing_written(target)


def test_pull_refuses_settings_that_name_code_unless_allowed(
    exported_folder: Path, hub: FakeHubApi, tmp_path: Path
) -> None:
    repo = published(hub, exported_folder)
    wrapper = "tests.hub.user_wrapper:identity"
    change_settings(repo, env_wrappers=[wrapper])
    sys.modules.pop("tests.hub.user_wrapper", None)
    target = tmp_path / "pulled"
    with pytest.raises(DqnlabError, match="names code to import .*--allow-user-parts") as error:
        remote.pull(REPO, target, api=hub)
    assert wrapper in str(error.value) and len(str(error.value).splitlines()) == 1
    assert "tests.hub.user_wrapper" not in sys.modules  # nothing was imported
    assert_nothing_written(target)
    pulled = remote.pull(REPO, target, api=hub, allow_user_parts=True)
    assert pulled.checked.config.env_wrappers == (wrapper,)
    assert "tests.hub.user_wrapper" in sys.modules  # imported from the test suite, not the repo
    for setting, value in (("network", "os:system"), ("env", "os:getcwd"), ("policy", "a.b:C")):
        other = FakeHubApi(tmp_path / f"hub-{setting}")
        change_settings(published(other, exported_folder), **{setting: value})
        with pytest.raises(DqnlabError, match=f"{setting} = '{value}'"):
            remote.pull(REPO, tmp_path / f"pulled-{setting}", api=other)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"env": "Acrobot-v1"}, "does not match Acrobot-v1: the network takes float32 inputs of "
         "shape \\(1, 4\\) and has 2 actions; the environment gives float32 inputs of shape "
         "\\(1, 6\\) and has 3 actions"),
        ({"mlp_hidden_sizes": [32, 32]}, "does not fit its network"),
    ],
)  # fmt: skip
def test_pull_refuses_a_network_that_does_not_fit_its_environment(
    exported_folder: Path, hub: FakeHubApi, tmp_path: Path, changes: dict, message: str
) -> None:
    change_settings(published(hub, exported_folder), **changes)
    target = tmp_path / "pulled"
    with pytest.raises(DqnlabError, match=message):
        remote.pull(REPO, target, api=hub)
    assert_nothing_written(target)


def test_pull_refuses_a_config_toml_that_disagrees_with_the_network(
    exported_folder: Path, hub: FakeHubApi, tmp_path: Path
) -> None:
    change_settings(published(hub, exported_folder), "toml", discount=0.5)
    with pytest.raises(DqnlabError, match="disagree on discount"):
        remote.pull(REPO, tmp_path / "pulled", api=hub)


def _connection_refused() -> Exception:
    return httpx2.ConnectError("[Errno 111] Connection refused")


@pytest.mark.parametrize(
    ("method", "failure", "message"),
    [
        ("model_info", _connection_refused(), "the Hub could not be reached \\(ConnectError"),
        ("snapshot_download", http_error(HfHubHTTPError, 500, "500 Server Error:\nbusy"),
         "the Hub answered 500 Server Error: busy"),
        ("create_repo", http_error(HfHubHTTPError, 401, "401 Unauthorized: bad token"),
         "cannot create the repository someone/cartpole-dqn: the Hub answered 401"),
        ("upload_folder", http_error(HfHubHTTPError, 403, "403 Forbidden: no write access"),
         "cannot upload to someone/cartpole-dqn: the Hub answered 403 Forbidden"),
    ],
)  # fmt: skip
def test_a_hub_failure_is_one_line_and_leaves_nothing(
    tiny_run: Path, exported_folder: Path, hub: FakeHubApi, tmp_path: Path, method: str,
    failure: Exception, message: str,
) -> None:  # fmt: skip
    hub.failures[method] = failure
    target = tmp_path / "pulled"
    with pytest.raises(DqnlabError, match=message) as error:
        if method in ("create_repo", "upload_folder"):
            remote.push(tiny_run, REPO, api=hub, seed=EVALUATION_SEED, device=CPU, video=False)
        else:
            published(hub, exported_folder)
            remote.pull(REPO, target, api=hub)
    assert len(str(error.value).splitlines()) == 1
    assert_nothing_written(target)


def test_pulling_a_repository_that_does_not_exist(hub: FakeHubApi, tmp_path: Path) -> None:
    with pytest.raises(DqnlabError, match="no such repository, or it is private"):
        remote.pull("someone/nothing", tmp_path / "pulled", api=hub)
    with pytest.raises(DqnlabError, match="is not OWNER/NAME"):
        remote.pull("no-owner", tmp_path / "pulled", api=hub)


def test_a_real_client_that_cannot_reach_the_hub_is_one_line(tmp_path: Path) -> None:
    # A closed port on this machine: huggingface_hub's own transport fails at once.
    api = HfApi(endpoint="http://127.0.0.1:9", token=False)
    with pytest.raises(DqnlabError, match="the Hub could not be reached"):
        remote.pull(REPO, tmp_path / "pulled", api=api)
    assert_nothing_written(tmp_path / "pulled")


def test_push_without_a_token_stops_before_anything_else(
    tiny_run: Path, hub: FakeHubApi, monkeypatch
) -> None:
    hub.token = None
    monkeypatch.setattr(remote, "get_token", lambda: None)
    with pytest.raises(DqnlabError, match="no Hugging Face token: log in with `hf auth login`"):
        remote.push(tiny_run, REPO, api=hub, seed=0, device=CPU)
    assert hub.calls == []


def test_huggingface_hubs_own_token_lookup_reads_hf_token(monkeypatch) -> None:
    monkeypatch.setenv("HF_TOKEN", "hf_from_the_environment")
    assert remote.has_token(SimpleNamespace(token=None))
    for variable in ("HF_TOKEN", "HUGGING_FACE_HUB_TOKEN", "HF_OIDC_RESOURCE"):
        monkeypatch.delenv(variable, raising=False)
    monkeypatch.setattr("huggingface_hub.constants.HF_TOKEN_PATH", "/nonexistent/token")  # no login
    assert not remote.has_token(SimpleNamespace(token=None))


def test_an_evaluation_of_the_pulled_folder_needs_no_hub(
    exported_folder: Path, hub: FakeHubApi, tmp_path: Path, monkeypatch
) -> None:
    published(hub, exported_folder)
    target = remote.pull(REPO, tmp_path / "pulled", api=hub).folder
    monkeypatch.setitem(sys.modules, "huggingface_hub", None)  # gone: only safetensors is read
    results = json.loads((target / "results.json").read_text())
    played, _ = final_evaluation(target, "best", None, results["seed"], CPU)
    assert played.scores == results["scores"]


def test_the_commands_print_what_they_did_and_one_line_when_refused(
    tiny_run: Path, hub: FakeHubApi, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch
) -> None:
    monkeypatch.setattr(remote, "default_api", lambda: hub)
    out = tmp_path / "exported"
    status, _ = dqnlab_main(
        capsys, monkeypatch, "export", str(tiny_run), "--out", str(out), "--no-video",
        "--device", "cpu", "--seed", str(EVALUATION_SEED),
    )  # fmt: skip
    assert status == 0
    assert not (out / "replay.mp4").exists() and (out / "model.safetensors").is_file()
    push = ["push", str(tiny_run), "--repo-id", REPO, "--no-video", "--device", "cpu"]
    refusal = http_error(HfHubHTTPError, 403, "403 Forbidden: read-only token")
    hub.failures["upload_folder"] = refusal
    status, error = dqnlab_main(capsys, monkeypatch, *push, "--seed", str(EVALUATION_SEED))
    assert status == 2 and len(error.splitlines()) == 1
    assert error.startswith(f"dqnlab: error: cannot upload to {REPO}: the Hub answered 403")
    del hub.failures["upload_folder"]
    monkeypatch.setattr(sys, "argv", ["dqnlab", *push, "--seed", str(EVALUATION_SEED)])
    with pytest.raises(SystemExit) as exit_info:
        from dqnlab.cli import main

        main()
    assert exit_info.value.code in (0, None)
    printed = capsys.readouterr().out
    assert "pushed README.md, config.toml" in printed and printed.rstrip().endswith(COMMIT)
    assert "CartPole-v1: " in printed and "over 3 games (results.json)" in printed
