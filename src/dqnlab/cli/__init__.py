"""The `dqnlab` command: train, evaluate, benchmark, ablate, sweep, status, report, inspect,
share agents (export, push, pull), list games and presets."""

from __future__ import annotations

import typer

from dqnlab.cli import bench, hub, listings, results, sweeps, train
from dqnlab.cli.allocator import keep_freed_memory
from dqnlab.cli.common import run_command

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="markdown",
    help="The Nature DQN exactly as DeepMind ran it, on Atari or any discrete-action Gymnasium env.",
)
# In the order `dqnlab --help` lists them; each command's name is its function's.
for command in (
    train.train,
    train.resume,
    results.evaluate,
    bench.bench,
    sweeps.ablate,
    sweeps.sweep,
    sweeps.status,
    results.report,
    results.inspect,
    hub.export,
    hub.push,
    hub.pull,
    listings.games,
    listings.presets,
):
    app.command()(command)


def main() -> None:
    """Entry point: a DqnlabError ends the command with one line and exit status 2 (75
    for a run directory another process trains: `lease.LeaseHeld`). glibc is first told to
    keep freed memory for reuse (`allocator.py`)."""
    keep_freed_memory()
    run_command(app)
