"""What the commands share: option types, the torch device of a --device option, the --json
files, and how the `dqnlab` command reports an error or a warning: in one line."""

from __future__ import annotations

import ctypes
import json
import sys
import warnings
from pathlib import Path
from typing import Annotated, Any

import typer

from dqnlab.errors import DqnlabError

Device = Annotated[str, typer.Option(help="auto, cpu or cuda")]
RunDir = Annotated[Path, typer.Argument(help="A run directory written by `dqnlab train`")]
Progress = Annotated[bool, typer.Option(help="Show the live progress bar")]
# How a Gymnasium environment is made: the settings env_kwargs and env_wrappers, added to.
EnvKwargs = Annotated[
    list[str] | None,
    typer.Option(
        "--env-kwarg",
        help="An argument of the environment's constructor: KEY=VALUE, VALUE a TOML literal "
        '(false, 3, [4, 4], "text") or else a plain string (map_name=8x8); repeatable, added '
        "to env_kwargs (a KEY given here replaces the same KEY from the preset or --set)",
    ),
]
Wrappers = Annotated[
    list[str] | None,
    typer.Option(
        "--wrapper",
        help="A wrapper around the environment: module:callable, called as callable(env) and "
        "returning a gymnasium.Env; repeatable, applied in order, after env_wrappers' own",
    ),
]
ENV_HELP = (
    "Atari game (pong), Gymnasium id (CartPole-v1, or one an installed package provides), "
    "module:Env-id or module:EnvClass"
)


def resolve_device(name: str):  # noqa: ANN201 - torch is imported only when needed
    """The torch device of a --device option, or a one-line error."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name not in ("cpu", "cuda") and not name.startswith("cuda:"):
        raise DqnlabError(f"--device {name!r} is not one of: auto, cpu, cuda")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise DqnlabError(f"--device {name} was asked for but no CUDA device is available")
    return torch.device(name)


def write_json(path: Path, record: Any) -> None:
    """A --json option's file: `record` indented, its directory made if missing."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=2) + "\n")


def run_command(app: typer.Typer) -> None:
    """Run `app` as the `dqnlab` command: a DqnlabError ends it with one line and exit
    status 2 (75 for a run directory another process trains: `lease.LeaseHeld`)."""
    warnings.formatwarning = format_warning
    keep_freed_memory()
    try:
        app()
    except DqnlabError as error:
        print(f"dqnlab: error: {error}", file=sys.stderr)
        sys.exit(getattr(error, "exit_status", 2))  # 2, or a status a caller acts on


def format_warning(message, category, filename, lineno, line=None) -> str:  # noqa: ANN001
    """dqnlab's own warnings as one line; others as Python shows them."""
    if "dqnlab" in Path(filename).parts:
        return f"dqnlab: warning: {message}\n"
    return _python_format_warning(message, category, filename, lineno, line)


_python_format_warning = warnings.formatwarning


def keep_freed_memory() -> None:
    """Ask glibc to keep freed memory instead of returning it to the system: PyTorch's
    per-update temporaries were otherwise faulted in again every update, thousands of
    page faults a noticeable part of the update on CPU. Best effort: glibc only."""
    if sys.platform != "linux":
        return
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 64 << 20)  # M_MMAP_THRESHOLD: serve blocks up to 64 MiB from the heap
        libc.mallopt(-1, 256 << 20)  # M_TRIM_THRESHOLD: keep up to 256 MiB of free heap
    except (OSError, AttributeError):
        pass
