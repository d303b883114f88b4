"""The `dqnlab` command as a whole: the typer app the docs are generated from, its commands
in their order, and every command's help."""

from __future__ import annotations

from pathlib import Path

import pytest
import typer

from dqnlab.cli import app, main
from tests.helpers import dqnlab

COMMANDS = ["train", "resume", "evaluate", "bench", "ablate", "sweep", "tune", "status", "report",
            "inspect", "export", "push", "pull", "games", "presets"]  # fmt: skip


def test_the_app_and_entry_point_the_docs_and_pyproject_name() -> None:
    """`dqnlab.cli.app` (the docs' command reference is built from it) lists every command
    in this order, and `dqnlab.cli:main` is the console script's entry point."""
    command = typer.main.get_command(app)
    context = command.make_context("dqnlab", [], resilient_parsing=True)
    assert command.list_commands(context) == COMMANDS  # type: ignore[attr-defined]
    pyproject = (Path(__file__).parents[2] / "pyproject.toml").read_text()
    assert 'dqnlab = "dqnlab.cli:main"' in pyproject and callable(main)


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
        "export",
        "push",
        "pull",
        "games",
    ],
)
def test_every_command_has_help(command: str) -> None:
    result = dqnlab(command, "--help")
    assert result.returncode == 0 and "Usage:" in result.stdout
