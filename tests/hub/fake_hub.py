"""A stand-in for huggingface_hub's `HfApi`: the calls dqnlab makes, served from folders on
disk, each call recorded. No test reaches the network."""

from __future__ import annotations

import fnmatch
import shutil
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import httpx2
from huggingface_hub.errors import HfHubHTTPError, RepositoryNotFoundError

COMMIT = "0123456789abcdef0123456789abcdef01234567"


def http_error(kind: type[HfHubHTTPError], status: int, message: str) -> HfHubHTTPError:
    """An error as huggingface_hub raises it for an HTTP answer of `status`."""
    request = httpx2.Request("POST", "https://huggingface.co/api/repos/create")
    return kind(message, response=httpx2.Response(status, request=request))


class FakeHubApi:
    """`repos/OWNER--NAME/` is a repository's main branch; a download copies the files the
    caller allows into `cache/`, as huggingface_hub's cache would hold them."""

    def __init__(self, root: Path, token: str | None = "hf_test_token") -> None:
        self.root = root
        self.token = token
        self.calls: list[tuple[str, dict[str, Any]]] = []
        self.failures: dict[str, BaseException] = {}  # method name -> what it raises

    def repo(self, repo_id: str) -> Path:
        return self.root / "repos" / repo_id.replace("/", "--")

    def _call(self, name: str, **arguments: Any) -> None:
        self.calls.append((name, arguments))
        if name in self.failures:
            raise self.failures[name]

    def called(self, name: str) -> list[dict[str, Any]]:
        return [arguments for called, arguments in self.calls if called == name]

    def create_repo(self, repo_id: str, **options: Any) -> str:
        self._call("create_repo", repo_id=repo_id, **options)
        self.repo(repo_id).mkdir(parents=True, exist_ok=bool(options.get("exist_ok")))
        return f"https://huggingface.co/{repo_id}"

    def upload_folder(self, *, repo_id: str, folder_path: str, **options: Any) -> Any:
        files = sorted(p.name for p in Path(folder_path).iterdir())
        self._call(
            "upload_folder", repo_id=repo_id, folder_path=folder_path, files=files, **options
        )
        repo = self.repo(repo_id)
        for path in [p for p in repo.rglob("*") if p.is_file()]:
            name = path.relative_to(repo).as_posix()
            deleted = any(fnmatch.fnmatch(name, p) for p in options.get("delete_patterns") or [])
            if deleted and name not in files and name != ".gitattributes":
                path.unlink()
        shutil.copytree(folder_path, repo, dirs_exist_ok=True)
        return SimpleNamespace(commit_url=f"https://huggingface.co/{repo_id}/commit/{COMMIT}")

    def model_info(self, repo_id: str, **options: Any) -> Any:
        self._call("model_info", repo_id=repo_id, **options)
        repo = self.repo(repo_id)
        if not repo.is_dir():
            raise http_error(RepositoryNotFoundError, 404, "404 Client Error: Repository Not Found")
        files = sorted(p.relative_to(repo).as_posix() for p in repo.rglob("*") if p.is_file())
        return SimpleNamespace(sha=COMMIT, siblings=[SimpleNamespace(rfilename=f) for f in files])

    def snapshot_download(self, repo_id: str, **options: Any) -> str:
        self._call("snapshot_download", repo_id=repo_id, **options)
        repo = self.repo(repo_id)
        snapshot = self.root / "cache" / repo_id.replace("/", "--") / str(options.get("revision"))
        snapshot.mkdir(parents=True, exist_ok=True)
        patterns = options.get("allow_patterns") or ["*"]
        for path in repo.rglob("*"):
            name = path.relative_to(repo).as_posix()
            if path.is_file() and any(fnmatch.fnmatch(name, p) for p in patterns):
                (snapshot / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(path, snapshot / name)
        return str(snapshot)
