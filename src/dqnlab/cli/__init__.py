"""The `dqnlab` command: train, evaluate, benchmark, ablate, sweep, tune, status, report, inspect,
share agents (export, push, pull), list games and presets."""

from __future__ import annotations

from typing import Any

import typer
from typer.core import TyperGroup

from dqnlab.cli import bench, hub, listings, results, sweeps, train, tune
from dqnlab.cli.allocator import keep_freed_memory
from dqnlab.cli.common import run_command

# In the order `dqnlab --help` lists them; each command's name is its function's, and
# `bench` is a group of subcommands (`dqnlab bench throughput`...).
COMMANDS = (
    train.train,
    train.resume,
    results.evaluate,
    bench.app,
    sweeps.ablate,
    sweeps.sweep,
    tune.tune,
    sweeps.status,
    results.report,
    results.inspect,
    hub.export,
    hub.push,
    hub.pull,
    listings.games,
    listings.presets,
)


def _name(command: Any) -> str:
    return str(command.info.name if isinstance(command, typer.Typer) else command.__name__)


class _InOrder(TyperGroup):
    """The commands in COMMANDS' order: typer would list a group after every command."""

    def list_commands(self, ctx: Any) -> list[str]:
        return [_name(command) for command in COMMANDS]


app = typer.Typer(
    cls=_InOrder,
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="markdown",
    help="The Nature DQN exactly as DeepMind ran it, on Atari or any discrete-action Gymnasium env.",
)
for command in COMMANDS:
    if isinstance(command, typer.Typer):
        app.add_typer(command)
    else:
        app.command()(command)


def main() -> None:
    """Entry point: a DqnlabError ends the command with one line and exit status 2 (75
    for a run directory another process trains: `lease.LeaseHeld`). glibc is first told to
    keep freed memory for reuse (`allocator.py`)."""
    keep_freed_memory()
    run_command(app)
