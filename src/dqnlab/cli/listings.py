"""`dqnlab games` and `dqnlab presets`: what --env and --preset accept."""

from __future__ import annotations

from typing import Annotated

import typer


def games() -> None:
    """List the Atari games ale-py ships (names accepted by --env)."""
    from dqnlab.envs.atari import game_names

    typer.echo(" ".join(game_names()))


def presets(
    name: Annotated[str | None, typer.Argument(help="Print this preset's TOML")] = None,
) -> None:
    """List the shipped presets (tuned/ENV-ID: the tuned settings for one environment id), or
    print one (copy it, edit it, pass its path to --preset)."""
    from dqnlab.config import load_preset, preset_names, preset_text

    if name is None:
        typer.echo(" ".join(preset_names()))
        return
    load_preset(name)  # validates the name
    typer.echo(preset_text(name), nl=False)
