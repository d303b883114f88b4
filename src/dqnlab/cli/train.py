"""`dqnlab train` and `dqnlab resume`: a run trained into its run directory, or carried on."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from dqnlab.cli.common import (
    ENV_HELP,
    Device,
    EnvKwargs,
    Progress,
    RunDir,
    Wrappers,
    resolve_device,
)
from dqnlab.config import preset_names


def train(
    env: Annotated[str, typer.Option(help=ENV_HELP)],
    preset: Annotated[
        str | None,
        typer.Option(
            help=f"A shipped preset ({', '.join(preset_names())}; by default nature for Atari, "
            "the tuned settings for an id dqnlab has them for (tuned/ID), classic otherwise) "
            "or a .toml path"
        ),
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="Override a setting: KEY=VALUE (repeatable)"),
    ] = None,
    env_kwarg: EnvKwargs = None,
    wrapper: Wrappers = None,
    steps: Annotated[
        int | None, typer.Option(help="Training budget in agent steps (total_steps)")
    ] = None,
    seed: Annotated[
        int | None, typer.Option(help="Run seed; every random stream derives from it")
    ] = None,
    run_dir: Annotated[
        Path | None, typer.Option(help="Where the run writes (default runs/ENV-PRESET-sSEED)")
    ] = None,
    device: Device = "auto",
    force: Annotated[
        bool, typer.Option(help="Start over in an existing run directory, deleting that run")
    ] = False,
    progress: Progress = True,
) -> None:
    """Train a DQN; writes config, CSV logs, TensorBoard events and checkpoints to the run dir."""
    from dqnlab.config import parse_overrides, parse_pairs, resolve_config, with_env_arguments
    from dqnlab.envs import check_env, default_preset
    from dqnlab.run.rundir import default_run_dir, prepare_run_dir

    preset = preset or default_preset(env)
    config = resolve_config(
        preset, parse_overrides(set_ or []), env=env, total_steps=steps, seed=seed
    )
    config = with_env_arguments(config, parse_pairs(env_kwarg or [], "--env-kwarg"), wrapper or [])
    check_env(config)
    torch_device = resolve_device(device)
    run_dir = run_dir or default_run_dir(env, preset, config.seed)
    resume = prepare_run_dir(run_dir, force, config)
    verb = "resuming" if resume else "training"
    typer.echo(f"dqnlab: {verb} {env} with preset {preset} on {torch_device} into {run_dir}")
    _run(config, run_dir, torch_device, progress, resume)


def resume(
    run_dir: RunDir,
    steps: Annotated[
        int | None, typer.Option(help="A new training budget in agent steps (total_steps)")
    ] = None,
    device: Device = "auto",
    progress: Progress = True,
) -> None:
    """Carry on a run from its newest complete checkpoint, exactly where it stopped."""
    import dataclasses

    from dqnlab.run.rundir import load_run_config, update_run_config

    config = load_run_config(run_dir)
    if steps is not None:
        config = dataclasses.replace(config, total_steps=steps)
        update_run_config(run_dir, config)
    torch_device = resolve_device(device)
    typer.echo(f"dqnlab: resuming {config.env} on {torch_device} from {run_dir}")
    _run(config, run_dir, torch_device, progress, resume=True)


def _run(config, run_dir: Path, device, progress: bool, resume: bool) -> None:  # noqa: ANN001
    from dqnlab.run.train import train as run_training

    result = run_training(config, run_dir, device, progress=progress, resume=resume)
    if result.interrupted:
        typer.echo(
            f"dqnlab: stopped by {result.interrupted} at step {result.steps} after saving a "
            f"checkpoint; resume with: dqnlab resume {run_dir}",
            err=True,
        )
        sys.exit(130 if result.interrupted == "SIGINT" else 143)
    typer.echo(
        f"dqnlab: {result.steps} steps, {result.frames} frames"
        + (
            f" ({result.session_frames} since the resume)"
            if resume and result.session_frames != result.frames
            else ""  # a fresh run's count starts after its first reset's no-op frames
        )
        + f" in {result.seconds:.0f} s "
        f"({result.frames_per_second:.0f} frames/s overall, {result.learning_frames_per_second:.0f} "
        f"once learning); "
        + (
            f"best evaluation mean {result.best_eval_mean:.2f}"
            if result.evaluations
            else "no periodic evaluation ran"
        )
    )
    if config.final_eval_after_training and result.steps >= config.total_steps:
        _final_evaluation(config, run_dir, device)


def _final_evaluation(config, run_dir: Path, device) -> None:  # noqa: ANN001
    """The run's final evaluation, saved as its final_evaluation.json, under the run's lease:
    the run is not done until it is saved, so `dqnlab status` and a sweep see it running,
    and no second process starts it meanwhile."""
    from dqnlab.config import DEFAULT_EVALUATION_SEED
    from dqnlab.run.evaluate import evaluate_and_save
    from dqnlab.run.lease import held

    network = config.final_eval_network
    typer.echo(
        f"dqnlab: final evaluation of the {network} network, {config.final_eval_episodes} games"
    )
    with held(run_dir):
        record = evaluate_and_save(run_dir, network, None, DEFAULT_EVALUATION_SEED, device)
    typer.echo(
        f"dqnlab: {config.env}: {record['mean']:.2f} ± {record['std']:.2f} over "
        f"{record['episodes']} games, saved in {run_dir}"
    )
