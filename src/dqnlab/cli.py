"""The `dqnlab` command: train, evaluate, and list games and presets."""

from __future__ import annotations

import ctypes
import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from dqnlab.errors import DqnlabError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="The Nature DQN exactly as DeepMind ran it, on Atari or any discrete-action Gymnasium env.",
)


@app.command()
def train(
    env: Annotated[
        str, typer.Option(help="Atari game (pong), Gymnasium id (CartPole-v1) or module:EnvClass")
    ],
    preset: Annotated[
        str | None,
        typer.Option(
            help="nature (Atari default), seed-paper, machado, classic (default otherwise), or a .toml path"
        ),
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="Override a setting: KEY=VALUE (repeatable)"),
    ] = None,
    steps: Annotated[
        int | None, typer.Option(help="Training budget in agent steps (total_steps)")
    ] = None,
    seed: Annotated[
        int | None, typer.Option(help="Run seed; every random stream derives from it")
    ] = None,
    run_dir: Annotated[
        Path | None, typer.Option(help="Where the run writes (default runs/ENV-PRESET-sSEED)")
    ] = None,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda")] = "auto",
    force: Annotated[
        bool, typer.Option(help="Start over in an existing run directory, deleting that run")
    ] = False,
    progress: Annotated[bool, typer.Option(help="Show the live progress bar")] = True,
) -> None:
    """Train a DQN; writes config, CSV logs, TensorBoard events and checkpoints to the run dir."""
    from dqnlab.agent import resolve_device
    from dqnlab.config import parse_overrides, resolve_config
    from dqnlab.envs import check_env_name, is_atari
    from dqnlab.train import prepare_run_dir

    check_env_name(env)
    preset = preset or ("nature" if is_atari(env) else "classic")
    config = resolve_config(
        preset, parse_overrides(set_ or []), env=env, total_steps=steps, seed=seed
    )
    torch_device = resolve_device(device)
    run_dir = (
        run_dir
        or Path("runs")
        / f"{env.replace(':', '_').replace('/', '_')}-{Path(preset).stem}-s{config.seed}"
    )
    resume = prepare_run_dir(run_dir, force, config)
    verb = "resuming" if resume else "training"
    typer.echo(f"dqnlab: {verb} {env} with preset {preset} on {torch_device} into {run_dir}")
    _run(config, run_dir, torch_device, progress, resume)


@app.command()
def resume(
    run_dir: Annotated[Path, typer.Argument(help="A run directory written by `dqnlab train`")],
    steps: Annotated[
        int | None, typer.Option(help="A new training budget in agent steps (total_steps)")
    ] = None,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda")] = "auto",
    progress: Annotated[bool, typer.Option(help="Show the live progress bar")] = True,
) -> None:
    """Carry on a run from its newest complete checkpoint, exactly where it stopped."""
    import dataclasses

    from dqnlab.agent import resolve_device
    from dqnlab.config import config_to_toml
    from dqnlab.evaluate import CONFIG_FILE, load_run_config

    config = load_run_config(run_dir)
    if steps is not None and steps != config.total_steps:
        config = dataclasses.replace(config, total_steps=steps)
        (run_dir / CONFIG_FILE).write_text(config_to_toml(config))
    torch_device = resolve_device(device)
    typer.echo(f"dqnlab: resuming {config.env} on {torch_device} from {run_dir}")
    _run(config, run_dir, torch_device, progress, resume=True)


def _run(config, run_dir: Path, device, progress: bool, resume: bool) -> None:  # noqa: ANN001
    from dqnlab.train import train as run_training

    result = run_training(config, run_dir, device, progress=progress, resume=resume)
    if result.interrupted:
        typer.echo(
            f"dqnlab: stopped by {result.interrupted} at step {result.steps} after saving a "
            f"checkpoint; resume with: dqnlab resume {run_dir}",
            err=True,
        )
        sys.exit(130 if result.interrupted == "SIGINT" else 143)
    typer.echo(
        f"dqnlab: {result.steps} steps, {result.frames} frames in {result.seconds:.0f} s "
        f"({result.frames_per_second:.0f} frames/s overall, {result.learning_frames_per_second:.0f} "
        f"once learning); "
        + (
            f"best evaluation mean {result.best_eval_mean:.2f}"
            if result.evaluations
            else "no periodic evaluation ran"
        )
    )


@app.command()
def evaluate(
    run_dir: Annotated[Path, typer.Argument(help="A run directory written by `dqnlab train`")],
    checkpoint: Annotated[
        str, typer.Option(help="best, last, or the path of a checkpoint file")
    ] = "best",
    episodes: Annotated[
        int | None, typer.Option(help="Games to play (default: final_eval_episodes, 30)")
    ] = None,
    json_path: Annotated[
        Path | None, typer.Option("--json", help="Write the result as JSON to this file")
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of the evaluation's random streams")] = 12345,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda")] = "auto",
) -> None:
    """The Nature final protocol: games of at most 18,000 frames, epsilon 0.05, no-op starts.

    Evaluating the run's best network (the default) also saves the result as
    RUN_DIR/final_evaluation.json, which `dqnlab report` reads."""
    from dqnlab.agent import resolve_device
    from dqnlab.evaluate import final_evaluation, final_evaluation_record, save_final_evaluation

    result, config, checkpoint_path = final_evaluation(
        run_dir, checkpoint, episodes, seed, resolve_device(device)
    )
    typer.echo(
        f"{config.env}: {result.mean:.2f} ± {result.std:.2f} over {len(result.scores)} games "
        f"({checkpoint_path}, {result.frames} frames at {result.frames_per_second:.0f} frames/s)"
    )
    record = final_evaluation_record(result, config, checkpoint_path, seed)
    if checkpoint == "best":
        save_final_evaluation(run_dir, record)
    if json_path:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(record, indent=2) + "\n")


@app.command()
def bench(
    env: Annotated[str, typer.Option(help="Atari game to measure")] = "breakout",
    steps: Annotated[
        int, typer.Option(help="Agent steps timed for training and for evaluation")
    ] = 2000,
    replay_capacity: Annotated[
        int, typer.Option(help="Transitions in the replay measured")
    ] = 1_000_000,
    json_path: Annotated[
        Path | None, typer.Option("--json", help="Write the figures as JSON to this file")
    ] = None,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda")] = "auto",
    peers: Annotated[
        bool, typer.Option(help="Also run Stable-Baselines3's DQN (dqnlab[bench]), alternating")
    ] = False,
    compile_update: Annotated[
        bool, typer.Option("--compile", help="Measure with the update compiled (compile_update)")
    ] = False,
) -> None:
    """Measure training and evaluation throughput, the update, and replay memory use."""
    from dqnlab.agent import resolve_device
    from dqnlab.bench import run_benchmark

    figures = run_benchmark(
        env,
        steps,
        replay_capacity,
        resolve_device(device),
        peers=peers,
        compile_update=compile_update,
    )
    for name, value in figures.items():
        typer.echo(f"{name:40s} {value:.4g}" if isinstance(value, float) else f"{name:40s} {value}")
    if json_path:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(figures, indent=2) + "\n")


@app.command()
def games() -> None:
    """List the Atari games ale-py ships (names accepted by --env)."""
    from dqnlab.envs.atari import game_names

    typer.echo(" ".join(game_names()))


@app.command()
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
    typer.echo(resources.files("dqnlab").joinpath("presets", f"{name}.toml").read_text(), nl=False)


def _keep_freed_memory() -> None:
    """Ask glibc to keep freed memory instead of returning it to the system: PyTorch's
    per-update temporaries were otherwise faulted in again every update (500-3,000 page
    faults, 1.5-5 ms of a ~22 ms update on 2 CPU cores). Best effort: glibc only."""
    if sys.platform != "linux":
        return
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 64 << 20)  # M_MMAP_THRESHOLD: serve blocks up to 64 MiB from the heap
        libc.mallopt(-1, 256 << 20)  # M_TRIM_THRESHOLD: keep up to 256 MiB of free heap
    except (OSError, AttributeError):
        pass


def main() -> None:
    """Entry point: a DqnlabError ends the command with one line and exit status 2."""
    _keep_freed_memory()
    try:
        app()
    except DqnlabError as error:
        print(f"dqnlab: error: {error}", file=sys.stderr)
        sys.exit(2)
