"""`dqnlab export`, `dqnlab push` and `dqnlab pull`: a trained agent shared as a folder, on
the Hugging Face Hub, and evaluated by `dqnlab evaluate` once pulled."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from dqnlab.cli.common import Device, RunDir, resolve_device
from dqnlab.config import DEFAULT_EVALUATION_SEED

Checkpoint = Annotated[
    str, typer.Option(help="best, last, or the path of a network file of the run")
]
Episodes = Annotated[
    int | None,
    typer.Option(
        help="Games of the final evaluation when the run has none of this network (default: final_eval_episodes)"
    ),
]
Seed = Annotated[int, typer.Option(help="Seed of that evaluation's games and of the video's")]
Video = Annotated[bool, typer.Option(help="Film one evaluation game when the environment renders")]


def export(
    run_dir: RunDir,
    out: Annotated[Path, typer.Option(help="The folder to write (new, or an empty directory)")],
    checkpoint: Checkpoint = "best",
    episodes: Episodes = None,
    seed: Seed = DEFAULT_EVALUATION_SEED,
    video: Video = True,
    device: Device = "auto",
) -> None:
    """A run's network as a self-describing folder: model.safetensors (no pickle),
    config.toml, results.json (the final evaluation), a video, the learning curve and a
    model card (README.md) in the Hugging Face Hub's format.

    `dqnlab evaluate OUT` plays the folder like a run directory. The final evaluation is
    the run's final_evaluation.json when it is of this network, else it is played first."""
    from dqnlab.hub import require_hub_extra

    require_hub_extra()
    from dqnlab.hub.export import export_run

    written = export_run(
        run_dir, out, checkpoint=checkpoint, episodes=episodes, seed=seed,
        device=resolve_device(device), video=video, echo=typer.echo,
    )  # fmt: skip
    _report_export(written.results, written.notes)
    typer.echo(f"dqnlab: exported {', '.join(written.files)} to {out}")


def push(
    run_dir: RunDir,
    repo_id: Annotated[str, typer.Option(help="The Hub model repository: OWNER/NAME")],
    private: Annotated[bool, typer.Option(help="Create the repository private")] = False,
    checkpoint: Checkpoint = "best",
    episodes: Episodes = None,
    seed: Seed = DEFAULT_EVALUATION_SEED,
    video: Video = True,
    device: Device = "auto",
) -> None:
    """Export a run (as `dqnlab export`) and upload it to a Hugging Face Hub model
    repository as one commit, creating the repository if needed.

    The token is huggingface_hub's: `hf auth login`, or HF_TOKEN."""
    from dqnlab.hub import require_hub_extra

    require_hub_extra()
    from dqnlab.hub.remote import push as push_run

    written, commit = push_run(
        run_dir, repo_id, private=private, checkpoint=checkpoint, episodes=episodes,
        seed=seed, device=resolve_device(device), video=video, echo=typer.echo,
    )  # fmt: skip
    _report_export(written.results, written.notes)
    url = getattr(commit, "commit_url", None) or f"https://huggingface.co/{repo_id}"
    typer.echo(f"dqnlab: pushed {', '.join(written.files)} to {url}")


def pull(
    repo_id: Annotated[str, typer.Argument(help="The Hub model repository: OWNER/NAME")],
    run_dir: Annotated[Path, typer.Option(help="The folder to write (new, or an empty directory)")],
    revision: Annotated[
        str | None, typer.Option(help="A branch, tag or commit of the repository (default: main)")
    ] = None,
    allow_user_parts: Annotated[
        bool,
        typer.Option(
            help="Accept settings that name code to import (module:Name, env_wrappers), imported from your Python environment"
        ),
    ] = False,
) -> None:
    """Download an agent exported by dqnlab from the Hugging Face Hub, check it, and keep
    it in RUN_DIR; `dqnlab evaluate RUN_DIR` then plays it under the final protocol.

    Refused, with nothing written: a repository holding pickles (.pt, .bin, .pkl ...),
    settings unknown to this dqnlab, settings that name code (unless
    --allow-user-parts), a network whose shapes do not fit its environment."""
    from dqnlab.hub import require_hub_extra

    require_hub_extra()
    from dqnlab.hub.remote import pull as pull_agent

    pulled = pull_agent(repo_id, run_dir, revision=revision, allow_user_parts=allow_user_parts)
    config = pulled.checked.config
    typer.echo(
        f"dqnlab: pulled {repo_id} ({pulled.commit or 'unknown commit'}): {config.env}, "
        f"network of step {pulled.checked.step}, written by dqnlab {pulled.checked.dqnlab_version}"
    )
    typer.echo(f"dqnlab: evaluate it with: dqnlab evaluate {run_dir}")


def _report_export(results: dict, notes: list[str]) -> None:
    typer.echo(
        f"{results['env']}: {results['mean']:.2f} ± {results['std']:.2f} over "
        f"{results['episodes']} games (results.json)"
    )
    for note in notes:
        typer.echo(f"note: {note}")
