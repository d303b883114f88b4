"""`dqnlab push` and `dqnlab pull`: an exported folder to and from a Hugging Face Hub model
repository, through an `HfApi` (`api`, injected: tests give a fake one).

Push exports into a temporary directory, then creates the repository if needed
(`create_repo(exist_ok=True)`) and uploads the folder as one commit (`upload_folder`, which
also deletes an earlier push's files that this one lacks); the
token is huggingface_hub's own (`hf auth login`, or HF_TOKEN). Pull reads the file list
first and refuses a repository holding pickles before downloading anything, downloads
only an exported folder's files through huggingface_hub's cache (`snapshot_download`),
copies them into a staging directory next to the target, checks them (`checks.py`) and
renames the staging directory onto the target: a refusal or failure leaves nothing there.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from huggingface_hub import errors as hub_errors
from huggingface_hub import get_token

from dqnlab import __version__
from dqnlab.errors import DqnlabError
from dqnlab.hub.checks import CheckedFolder, check_folder, refuse_pickles
from dqnlab.hub.export import Exported, export_run
from dqnlab.run import exported

_REPO_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*/[A-Za-z0-9][A-Za-z0-9._-]*")
MAX_MESSAGE = 300  # characters of a server's message kept in the one line


def default_api() -> Any:
    """huggingface_hub's client, with the token it finds itself."""
    from huggingface_hub import HfApi

    return HfApi()


def check_repo_id(repo_id: str) -> None:
    if not _REPO_ID.fullmatch(repo_id) or ".." in repo_id or repo_id.endswith(".git"):
        raise DqnlabError(f"repository id {repo_id!r} is not OWNER/NAME (letters, digits, . _ -)")


def _one_line(error: BaseException) -> str:
    text = " ".join(str(error).split())
    return text if len(text) <= MAX_MESSAGE else text[: MAX_MESSAGE - 3] + "..."


@contextlib.contextmanager
def hub_call(action: str) -> Iterator[None]:
    """huggingface_hub's errors as one line saying what could not be done."""
    transport_error = getattr(hub_errors, "HTTPError", OSError)  # httpx2's, in 2.x
    try:
        yield
    except hub_errors.GatedRepoError:
        raise DqnlabError(
            f"cannot {action}: the repository is gated (accept its terms on the Hub)"
        ) from None
    except hub_errors.RepositoryNotFoundError:
        raise DqnlabError(
            f"cannot {action}: no such repository, or it is private and your token cannot see it"
        ) from None
    except hub_errors.RevisionNotFoundError:
        raise DqnlabError(f"cannot {action}: no such revision") from None
    except hub_errors.HfHubHTTPError as error:
        raise DqnlabError(f"cannot {action}: the Hub answered {_one_line(error)}") from None
    except hub_errors.OfflineModeIsEnabled:
        raise DqnlabError(f"cannot {action}: HF_HUB_OFFLINE is set") from None
    except (transport_error, OSError) as error:
        raise DqnlabError(
            f"cannot {action}: the Hub could not be reached ({type(error).__name__}: "
            f"{_one_line(error)})"
        ) from None


def has_token(api: Any) -> bool:
    """Whether a token is given to `api` or huggingface_hub finds one (HF_TOKEN, login)."""
    return bool(getattr(api, "token", None) or get_token())


def push(
    run_dir: Path,
    repo_id: str,
    *,
    private: bool = False,
    api: Any = None,
    checkpoint: str = "best",
    episodes: int | None = None,
    seed: int,
    device: torch.device,
    video: bool = True,
    echo: Callable[[str], object] = print,
) -> tuple[Exported, Any]:
    """Export the run and upload it to `repo_id` as one commit; the export and the
    upload's CommitInfo. The token is checked before anything is evaluated."""
    check_repo_id(repo_id)
    api = api if api is not None else default_api()
    if not has_token(api):
        raise DqnlabError(
            "no Hugging Face token: log in with `hf auth login` or set HF_TOKEN (a token "
            "with write access)"
        )
    with tempfile.TemporaryDirectory(prefix="dqnlab-push-") as temporary:
        folder = export_run(
            run_dir,
            Path(temporary) / "export",
            checkpoint=checkpoint,
            episodes=episodes,
            seed=seed,
            device=device,
            video=video,
            repo_id=repo_id,
            echo=echo,
        )
        results = folder.results
        message = (
            f"dqnlab {__version__}: {results['env']}, {results['mean']:.2f} +/- "
            f"{results['std']:.2f} over {results['episodes']} games"
        )
        with hub_call(f"create the repository {repo_id}"):
            api.create_repo(
                repo_id, repo_type="model", private=True if private else None, exist_ok=True
            )
        with hub_call(f"upload to {repo_id}"):
            commit = api.upload_folder(
                repo_id=repo_id,
                repo_type="model",
                folder_path=str(folder.folder),
                commit_message=message,
                # An earlier push's files that this one lacks (a GIF where there is now an
                # MP4, a video left out) go; the owner's other files stay.
                delete_patterns=list(exported.FOLDER_FILES),
            )
    return folder, commit


@dataclass(frozen=True)
class Pulled:
    folder: Path
    commit: str | None  # the repository's commit the files are from
    checked: CheckedFolder


def pull(
    repo_id: str,
    run_dir: Path,
    *,
    revision: str | None = None,
    api: Any = None,
    allow_user_parts: bool = False,
    cache_dir: Path | None = None,
) -> Pulled:
    """Download the exported agent `repo_id` (at `revision`) into the new folder
    `run_dir`, checked (`checks.check_folder`); `dqnlab evaluate run_dir` then plays it."""
    check_repo_id(repo_id)
    if run_dir.exists() and (not run_dir.is_dir() or any(run_dir.iterdir())):
        raise DqnlabError(f"--run-dir {run_dir} exists and is not an empty directory")
    api = api if api is not None else default_api()
    where = f"{repo_id}" + (f" at {revision}" if revision else "")
    with hub_call(f"read {where}"):
        info = api.model_info(repo_id, revision=revision)
    names = [sibling.rfilename for sibling in info.siblings or []]
    refuse_pickles(names, where)
    missing = [name for name in (exported.MODEL_FILE, exported.CONFIG_FILE) if name not in names]
    if missing:
        raise DqnlabError(f"{where} is not an exported dqnlab agent: no {' and no '.join(missing)}")
    commit = getattr(info, "sha", None)
    with hub_call(f"download {where}"):
        snapshot = Path(
            api.snapshot_download(
                repo_id,
                revision=commit or revision,
                allow_patterns=list(exported.FOLDER_FILES),
                cache_dir=cache_dir,
            )
        )
    staging = run_dir.parent / f".{run_dir.name}.partial-{os.getpid()}"
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    try:
        for name in exported.FOLDER_FILES:
            if (snapshot / name).is_file():
                shutil.copyfile(snapshot / name, staging / name)  # the blob, not the link
        checked = check_folder(staging, allow_user_parts)
        record = {"repo_id": repo_id, "revision": revision, "commit": commit}
        exported.save_json(
            staging / exported.PULLED_FILE, {**record, "dqnlab_version": __version__}
        )
        os.replace(staging, run_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return Pulled(run_dir, commit, checked)
