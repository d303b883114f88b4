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
    """List the shipped presets, or print one (copy it, edit it, pass its path to --preset)."""
    from importlib import resources

    from dqnlab.config import load_preset, preset_names

    if name is None:
        typer.echo(" ".join(preset_names()))
        return
    load_preset(name)  # validates the name
    typer.echo((resources.files("dqnlab") / "presets" / f"{name}.toml").read_text(), nl=False)
