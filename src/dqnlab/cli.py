"""The `dqnlab` command: train, evaluate, benchmark, ablate, sweep, status, report, inspect, list games and presets."""

from __future__ import annotations

import ctypes
import json
import sys
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from dqnlab.config import DEFAULT_EVALUATION_SEED
from dqnlab.errors import DqnlabError

if TYPE_CHECKING:
    from dqnlab.analysis.report.aggregate import AggregateSettings

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="markdown",
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
    from dqnlab.config import parse_overrides, resolve_config
    from dqnlab.envs import check_env_name, is_atari
    from dqnlab.run.rundir import default_run_dir, prepare_run_dir

    check_env_name(env)
    preset = preset or ("nature" if is_atari(env) else "classic")
    config = resolve_config(
        preset, parse_overrides(set_ or []), env=env, total_steps=steps, seed=seed
    )
    torch_device = resolve_device(device)
    run_dir = run_dir or default_run_dir(env, preset, config.seed)
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
    seed: Annotated[
        int, typer.Option(help="Seed of the evaluation's random streams")
    ] = DEFAULT_EVALUATION_SEED,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda")] = "auto",
    video: Annotated[
        Path | None,
        typer.Option(help="Film every game into this directory, the score in each file name"),
    ] = None,
    video_format: Annotated[
        str, typer.Option(help="auto (MP4, GIF where no encoder), mp4 or gif")
    ] = "auto",
) -> None:
    """The Nature final protocol: games of at most 18,000 frames, epsilon 0.05, no-op starts.

    Evaluating the run's best network (the default) also saves the result as
    RUN_DIR/final_evaluation.json, which `dqnlab report` reads, unless that file holds
    more games of the same network. With --video the games
    are played one after another on one emulator and filmed from the raw screens (every
    emulator frame, 60 frames/s); without it they are spread over every core (other
    games, the same protocol). A run trained with logger = tensorboard+wandb also gets
    the saved final evaluation and the videos in its W&B run's summary."""
    from dqnlab.run.evaluate import final_evaluation, final_evaluation_record
    from dqnlab.run.rundir import load_final_evaluation, record_final_evaluation
    from dqnlab.run.wandb_log import add_to_summary, final_evaluation_values, video_media

    videos: list[Path] = []
    if video is None:
        result, network = final_evaluation(
            run_dir, checkpoint, episodes, seed, resolve_device(device)
        )
    else:
        from dqnlab.analysis.video import filmed_final_evaluation

        recording, network = filmed_final_evaluation(
            run_dir, checkpoint, episodes, seed, resolve_device(device), video, video_format
        )
        videos = recording.paths
        for file in videos:
            typer.echo(f"dqnlab: wrote {file}")
        if recording.note:
            typer.echo(f"dqnlab: {recording.video_format.upper()}: {recording.note}")
        result = recording.result
    config = network.config
    typer.echo(
        f"{config.env}: {result.mean:.2f} ± {result.std:.2f} over {len(result.scores)} games "
        f"({network.path}, {result.frames} frames at {result.frames_per_second:.0f} frames/s)"
    )
    record = final_evaluation_record(result, config, network.path, network.step, seed)
    written = False
    if checkpoint == "best":
        path, written = record_final_evaluation(run_dir, record)
        if written:
            typer.echo(f"dqnlab: saved as {path}")
        else:
            saved = load_final_evaluation(run_dir) or {}
            typer.echo(
                f"dqnlab: kept {path}: it holds {saved.get('episodes')} games of this network"
            )
    if checkpoint in ("best", "last"):  # the run's own network: to its W&B run, if it has one
        values = final_evaluation_values(record) if written else {}
        if add_to_summary(run_dir, values, video_media(checkpoint, videos)):
            typer.echo("dqnlab: sent to the run's W&B summary")
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
    compression_fill_steps: Annotated[
        int,
        typer.Option(
            help="Transitions of random play in which to measure replay_compression = lz4 "
            "against none (0: skip)"
        ),
    ] = 100_000,
    compression_checkpoint_capacity: Annotated[
        int,
        typer.Option(
            help="Time the compressed and raw checkpoints on replays of this many slots, "
            "repeating the filled transitions (0: the filled replays themselves)"
        ),
    ] = 0,
    compression_scan: Annotated[
        Path | None,
        typer.Option(
            help="Instead of the rest: write each Atari-57 game's compressed frame size to "
            "this CSV (the table of data/replay_compression.csv)"
        ),
    ] = None,
    scan_steps: Annotated[
        int, typer.Option(help="Frames of random play per game for --compression-scan")
    ] = 16_384,
    sweep: Annotated[
        bool,
        typer.Option(
            "--sweep",
            help="Instead of the rest: what Ray adds to a sweep (its start-up, and per run "
            "against the same runs trained by hand), and the time from a lost node to its "
            "run training again, on loopback clusters of this machine",
        ),
    ] = False,
    sweep_runs: Annotated[
        int, typer.Option(help="Tiny CartPole runs trained each way in each --sweep repeat")
    ] = 4,
    sweep_repeats: Annotated[
        int, typer.Option(help="Times --sweep trains the runs by hand and by the sweep, in turn")
    ] = 2,
) -> None:
    """Measure training and evaluation throughput, the update, and replay memory use (with
    --sweep: what Ray adds to a sweep's runs, and how soon a lost node's run trains again)."""
    from dqnlab.bench.throughput import run_benchmark

    if compression_scan is not None:
        _compression_scan(compression_scan, scan_steps)
        return
    if sweep:
        import tempfile

        from dqnlab.bench.sweep import run_sweep_benchmark

        with tempfile.TemporaryDirectory(prefix="dqnlab-sweep-bench-") as directory:
            figures = run_sweep_benchmark(
                Path(directory),
                sweep_runs,
                sweep_repeats,
                echo=lambda line: typer.echo(line, err=True),
            )
    else:
        figures = run_benchmark(
            env,
            steps,
            replay_capacity,
            resolve_device(device),
            peers=peers,
            compile_update=compile_update,
            compression_fill_steps=compression_fill_steps,
            compression_checkpoint_capacity=compression_checkpoint_capacity,
        )
    for name, value in figures.items():
        typer.echo(f"{name:40s} {value:.4g}" if isinstance(value, float) else f"{name:40s} {value}")
    if json_path:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(figures, indent=2) + "\n")


def _compression_scan(path: Path, steps: int) -> None:
    import csv

    from dqnlab.analysis.report.scores import load_reference_scores
    from dqnlab.bench.compression import scan

    games = sorted(load_reference_scores())
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as handle:
        handle.write(f"# dqnlab bench --compression-scan {path} --scan-steps {steps}\n")
        writer = None
        for row in (scan([game], steps)[0] for game in games):
            if writer is None:
                writer = csv.DictWriter(handle, fieldnames=list(row))
                writer.writeheader()
            writer.writerow(row)
            handle.flush()
            typer.echo(
                f"{row['game']:24s} {row['lz4_bytes_per_frame']:8.1f} B/frame  x{row['ratio']}"
            )


@app.command()
def ablate(
    env: Annotated[
        str, typer.Option(help="Atari game (breakout), Gymnasium id or module:EnvClass")
    ],
    vary: Annotated[
        list[str],
        typer.Option(
            help="KEY=V1,V2 (values as in --set), or linked settings KEY1+KEY2=A1+A2,B1+B2; repeat for a grid"
        ),
    ],
    seeds: Annotated[int, typer.Option(help="Seeds per setting: SEED, SEED+1, ...")] = 1,
    seed: Annotated[int, typer.Option(help="The first seed")] = 0,
    steps: Annotated[
        int | None, typer.Option(help="Training budget of each run in agent steps")
    ] = None,
    preset: Annotated[
        str | None, typer.Option(help="Base preset (nature for Atari, classic otherwise)")
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="A setting shared by every run: KEY=VALUE (repeatable)"),
    ] = None,
    sweep_dir: Annotated[
        Path | None, typer.Option(help="Where the runs go (default sweeps/ENV-KEYS)")
    ] = None,
    jobs: Annotated[
        int | None,
        typer.Option(help="Runs trained side by side (default: what cores and memory allow)"),
    ] = None,
    episodes: Annotated[
        int | None,
        typer.Option(
            help="Games of each run's final evaluation (default: final_eval_episodes, 30)"
        ),
    ] = None,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda")] = "auto",
) -> None:
    """Train a grid of runs that differ in the --vary settings, then report them together.

    The seed paper's two ablations:

    * `dqnlab ablate --env breakout --vary life_loss_terminal=true,false`
    * `dqnlab ablate --env breakout --vary optimizer+learning_rate=deepmind_rmsprop+0.00025,rmsprop+0.00005`

    Running the same command again skips finished runs and resumes interrupted ones."""
    from dqnlab.config import parse_overrides
    from dqnlab.envs import check_env_name, is_atari
    from dqnlab.run.rundir import default_sweep_dir
    from dqnlab.sweeps.ablate import (
        check_sweep_dir,
        default_jobs,
        parse_variation,
        plan_sweep,
        run_sweep,
    )

    check_env_name(env)
    variations = [parse_variation(text) for text in vary]
    keys = [key for variation in variations for key in variation.keys]
    sweep_dir = sweep_dir or default_sweep_dir(env, keys)
    sweep = plan_sweep(
        env,
        variations,
        preset=preset or ("nature" if is_atari(env) else "classic"),
        overrides=parse_overrides(set_ or []),
        seeds=seeds,
        first_seed=seed,
        steps=steps,
        sweep_dir=sweep_dir,
    )
    check_sweep_dir(sweep)
    torch_device = resolve_device(device)  # a bad --device fails here, not in every run
    if jobs is not None and jobs <= 0:
        raise DqnlabError(f"--jobs {jobs} must be positive")
    jobs = jobs or default_jobs(sweep)
    typer.echo(f"dqnlab: {len(sweep.runs)} runs into {sweep_dir}, {jobs} at a time")
    with _ray_connection("local"):
        _run_or_stop(
            lambda: run_sweep(
                sweep,
                jobs=jobs,
                device=str(torch_device),
                echo=typer.echo,
                live=sys.stdout.isatty(),
            )  # fmt: skip
        )
    _report_sweep(sweep, episodes, device, report=True)


def _report_sweep(sweep, episodes: int | None, device: str, report: bool) -> None:  # noqa: ANN001
    """A sweep's end: its report (unless not asked for), then a failed run named."""
    finished = [run.run_dir for run in sweep.runs if run.status in ("ok", "done")]
    if finished and report:
        _report(finished, sweep.directory / "report", episodes, device)
    if sweep.failed:
        raise DqnlabError(
            f"{len(sweep.failed)} of {len(sweep.runs)} runs failed: "
            + ", ".join(run.name for run in sweep.failed)
            + "; run the same command again to retry them"
        )


def _ray_connection(address: str):  # noqa: ANN202 - ray is imported only when needed
    """Connected to Ray for the block; a local cluster started here ends with it."""
    import contextlib

    from dqnlab.sweeps.cluster import connect

    @contextlib.contextmanager
    def connected():  # noqa: ANN202
        connection = connect(address)
        try:
            yield connection
        finally:
            connection.close()

    return connected()


def _run_or_stop(run) -> None:  # noqa: ANN001
    """Run the sweep; Ctrl-C has stopped its runs after their checkpoints: say how to go on."""
    try:
        run()
    except KeyboardInterrupt:
        typer.echo(
            "dqnlab: stopped; every run wrote a checkpoint. Run the same command again to "
            "carry on (finished runs are skipped, the others resume)",
            err=True,
        )
        sys.exit(130)


@app.command()
def sweep(
    env: Annotated[
        str | None, typer.Option(help="Environments, comma-separated: pong,breakout or CartPole-v1")
    ] = None,
    games: Annotated[
        str | None,
        typer.Option(
            help="A game set instead of --env: nature49, atari57, or a file of games (one a line)"
        ),
    ] = None,
    preset: Annotated[
        str | None, typer.Option(help="Base preset (nature for Atari, classic otherwise)")
    ] = None,
    seeds: Annotated[int, typer.Option(help="Seeds per game and setting: SEED, SEED+1, ...")] = 1,
    seed: Annotated[int, typer.Option(help="The first seed")] = 0,
    vary: Annotated[
        list[str] | None,
        typer.Option(
            help="KEY=V1,V2 (values as in --set), or linked settings KEY1+KEY2=A1+A2,B1+B2; repeat for a grid"
        ),
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="A setting shared by every run: KEY=VALUE (repeatable)"),
    ] = None,
    steps: Annotated[
        int | None, typer.Option(help="Training budget of each run in agent steps")
    ] = None,
    sweep_dir: Annotated[
        Path | None, typer.Option(help="Where the runs go (default sweeps/GAMES-KEYS)")
    ] = None,
    address: Annotated[
        str, typer.Option(help="local (a Ray on this machine), auto, HOST:PORT or ray://HOST:PORT")
    ] = "local",
    cpus_per_run: Annotated[
        float, typer.Option(help="CPUs of each run, also its PyTorch threads")
    ] = 2.0,
    gpus_per_run: Annotated[
        float, typer.Option(help="GPUs of each run; 0.25 puts four runs on a GPU")
    ] = 0.0,
    memory_per_run: Annotated[
        float | None,
        typer.Option(
            help="Host memory of each run in GB (default: its replay plus the process's measured overhead)"
        ),
    ] = None,
    max_retries: Annotated[
        int, typer.Option(help="Restarts of a run whose process or node died (it resumes)")
    ] = 3,
    report: Annotated[bool, typer.Option(help="Report into SWEEP/report at the end")] = True,
    episodes: Annotated[
        int | None, typer.Option(help="Games of a missing final evaluation in the report")
    ] = None,
) -> None:
    """Train a grid of games × --vary settings × seeds on Ray (this machine or a cluster),
    then report them together.

    * `dqnlab sweep --games nature49 --seeds 5 --gpus-per-run 0.25 --address auto`
    * `dqnlab sweep --env pong,breakout --vary learning_rate=0.00025,0.0001`

    A run whose process or node dies is retried on any node and resumes from its newest
    checkpoint. Running the same command again skips finished runs and resumes the others;
    Ctrl-C stops every run after a checkpoint. `dqnlab status SWEEP_DIR` shows where it stands."""
    sweep_plan, resources, device = _plan_sweep_command(
        env, games, preset, seeds, seed, vary or [], set_ or [], steps, sweep_dir,
        cpus_per_run, gpus_per_run, memory_per_run, max_retries,
    )  # fmt: skip
    from dqnlab.sweeps.cluster import node_resources
    from dqnlab.sweeps.driver import run_sweep_on_ray
    from dqnlab.sweeps.resources import check_resources

    with _ray_connection(address):
        check_resources(resources, node_resources())
        typer.echo(
            f"dqnlab: {len(sweep_plan.runs)} runs into {sweep_plan.directory}; each asks for "
            f"{resources.cpus:g} CPUs, {resources.gpus:g} GPUs, "
            f"{resources.memory_bytes / 1e9:.1f} GB"
        )
        _run_or_stop(
            lambda: run_sweep_on_ray(
                sweep_plan,
                resources,
                device=device,
                max_retries=max_retries,
                echo=typer.echo,
                live=sys.stdout.isatty(),
            )
        )
    _report_sweep(sweep_plan, episodes, "cpu", report)


def _plan_sweep_command(
    env: str | None,
    games: str | None,
    preset: str | None,
    seeds: int,
    seed: int,
    vary: list[str],
    set_: list[str],
    steps: int | None,
    sweep_dir: Path | None,
    cpus_per_run: float,
    gpus_per_run: float,
    memory_per_run: float | None,
    max_retries: int,
):  # noqa: ANN202 - the sweep, its resources and the runs' device
    """Every input of `dqnlab sweep` checked (one line and exit 2 on the first bad one)
    before Ray is started or any run touched."""
    from dqnlab.config import parse_overrides
    from dqnlab.envs import check_env_name
    from dqnlab.run.rundir import default_sweep_dir
    from dqnlab.sweeps.grid import check_sweep_dir, game_set, parse_variation, plan_grid
    from dqnlab.sweeps.resources import sweep_resources

    if (env is None) == (games is None):
        raise DqnlabError(
            "dqnlab sweep needs one of --env ENV[,ENV...] or --games nature49|atari57|FILE"
        )
    if max_retries < 0:
        raise DqnlabError(f"--max-retries {max_retries} must be 0 or more")
    envs = game_set(games) if games else [name.strip() for name in (env or "").split(",")]
    envs = [name for name in envs if name]
    for name in envs:
        check_env_name(name)
    variations = [parse_variation(text) for text in vary]
    keys = [key for variation in variations for key in variation.keys]
    label = Path(games).stem if games else "+".join(envs)
    sweep_dir = sweep_dir or default_sweep_dir(label, keys or [f"{seeds}seeds"])
    sweep_plan = plan_grid(
        envs, variations, preset=preset, overrides=parse_overrides(set_), seeds=seeds,
        first_seed=seed, steps=steps, sweep_dir=sweep_dir,
    )  # fmt: skip
    check_sweep_dir(sweep_plan)
    memory = int(memory_per_run * 1e9) if memory_per_run is not None else None
    if memory is not None and memory <= 0:
        raise DqnlabError(f"--memory-per-run {memory_per_run} must be positive")
    resources = sweep_resources(sweep_plan, cpus_per_run, gpus_per_run, memory)
    return sweep_plan, resources, ("cuda" if gpus_per_run > 0 else "cpu")


@app.command()
def status(
    path: Annotated[Path, typer.Argument(help="A sweep directory or a run directory")],
    json_path: Annotated[
        Path | None, typer.Option("--json", help="Also write the runs' states as JSON to this file")
    ] = None,
) -> None:
    """Where a sweep's runs (or one run) stand, from the run directories alone: no Ray
    needed, from any machine that sees the storage."""
    from dqnlab.analysis.status import collect_status, format_status_table, status_json

    statuses = collect_status(path)
    for line in format_status_table(statuses):
        typer.echo(line)
    if json_path:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(status_json(statuses), indent=2) + "\n")


@app.command()
def report(
    run_dirs: Annotated[
        list[Path], typer.Argument(help="Run directories, or sweep directories of runs")
    ],
    out: Annotated[
        Path | None,
        typer.Option(help="Output directory (default: SWEEP/report for one sweep, else report)"),
    ] = None,
    episodes: Annotated[
        int | None,
        typer.Option(help="Games of a missing final evaluation (default: final_eval_episodes)"),
    ] = None,
    frames: Annotated[int, typer.Option(help="Frames of each run's Q-value figures (0: none)")] = 4,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda")] = "auto",
    reference: Annotated[
        str,
        typer.Option(
            help="Published curves behind Atari games' and the on-track table: dopamine or none"
        ),
    ] = "dopamine",
    baseline: Annotated[
        str,
        typer.Option(
            help="Human score of the aggregates across games: human (dqn_zoo's) or human_nature (the Nature paper's tester)"
        ),
    ] = "human",
    # The defaults of aggregate.AggregateSettings, not imported here (the report package
    # imports torch); tests/analysis/report/test_aggregate.py checks that they agree.
    bootstrap_reps: Annotated[
        int, typer.Option(help="Repetitions of the aggregates' stratified bootstrap")
    ] = 10_000,
    bootstrap_seed: Annotated[
        int, typer.Option(help="Seed of the aggregates' stratified bootstrap")
    ] = 0,
) -> None:
    """The results table, the learning curves and the Q-values of the best and worst networks.

    Per game: each configuration's final-evaluation mean ± s.d. (over seeds where there
    are several), Nature DQN's and the seed paper's scores, human-normalised scores with
    both human baselines; runs are grouped by the settings in which they differ. A run
    without a final evaluation is evaluated first with its best network (saved, so once).
    Behind each Atari game's curves, Dopamine's published DQN curves (another protocol,
    labelled), and an "on track?" table: each run's latest 1M-frame window of training
    games against them; unfinished runs are accepted (with a note). Under the curves,
    Nature Fig. 2's held-out mean max-Q and |TD error| where the runs logged them.
    With two games or more, the aggregates across games with 95% stratified bootstrap
    confidence intervals (Agarwal et al. 2021, with rliable): IQM, median, mean and
    optimality gap of the human-normalised scores, performance profiles, and the
    probability of improvement between configurations.
    Writes results.md, results.csv, summary.csv, curves-GAME.png/.svg, aggregates.csv,
    aggregates.png/.svg, performance-profiles.png/.svg, probability-of-improvement.csv and
    q-values/RUN/ (a figure per frame, overview.png, q_values.csv)."""
    from dqnlab.analysis.report.aggregate import AggregateSettings

    aggregate = AggregateSettings(baseline, bootstrap_reps, bootstrap_seed)  # checked first
    if frames < 0:
        raise DqnlabError(f"--frames {frames} must be 0 or more")
    if episodes is not None and episodes <= 0:
        raise DqnlabError(f"--episodes {episodes} must be positive")
    if out is None:
        from dqnlab.run.rundir import is_run_dir

        one_sweep = len(run_dirs) == 1 and not is_run_dir(run_dirs[0])
        out = run_dirs[0] / "report" if one_sweep else Path("report")
    _report(run_dirs, out, episodes, device, frames, reference, aggregate)


def _report(
    run_dirs: list[Path],
    out: Path,
    episodes: int | None,
    device: str,
    frames: int = 4,
    reference: str = "dopamine",
    aggregate: AggregateSettings | None = None,
) -> None:
    from dqnlab.analysis.report import best_network_evaluator, format_table, write_report

    torch_device = resolve_device(device)
    written = write_report(
        run_dirs,
        out,
        evaluate_missing=best_network_evaluator(torch_device, episodes=episodes),
        echo=typer.echo,
        inspect_frames=frames,
        device=torch_device,
        reference=reference,
        aggregate=aggregate,
    )
    typer.echo(format_table(written))
    for note in written.notes:
        typer.echo(f"note: {note}")
    figures = [path for curve in written.curves for path in curve.files if path.suffix == ".png"]
    for path in figures:
        typer.echo(f"learning curves: {path}")
    for path in written.aggregates.files if written.aggregates is not None else []:
        if path.suffix == ".png":
            typer.echo(f"aggregates across games: {path}")
    for item in written.inspections:
        picture = item.inspection.overview_path or item.out_dir
        typer.echo(f"Q-values of {item.run_dir}: {picture}")
    typer.echo(f"dqnlab: report in {out / 'results.md'}")


@app.command()
def inspect(
    run_dir: Annotated[Path, typer.Argument(help="A run directory written by `dqnlab train`")],
    frames: Annotated[int, typer.Option(help="Frames picked from one evaluation game")] = 8,
    checkpoints: Annotated[
        str,
        typer.Option(
            help="Networks compared: best, worst and/or evaluation steps, comma-separated"
        ),
    ] = "best,worst",
    observations: Annotated[
        Path | None,
        typer.Option(help="A .npy of stacked network inputs to use instead of picked frames"),
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="Output directory (default RUN_DIR/inspect)")
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of the game the frames are picked from")] = 0,
    device: Annotated[str, typer.Option(help="auto, cpu or cuda")] = "auto",
) -> None:
    """Q-values per action of several networks of a run on the same frames (the seed paper's
    best-against-worst figure).

    Frames are spread over the best network's first evaluation game (or read from
    --observations, e.g. an earlier inspection's observations.npy). Writes a figure per
    frame (the screen and a bar per action and network, greedy actions hatched),
    overview.png, q_values.csv and the inputs. worst is the network of the lowest
    periodic evaluation after the first quarter of training; steps need
    eval_networks_kept = "all"."""
    from dqnlab.analysis.inspection.qvalues import parse_checkpoints
    from dqnlab.analysis.inspection.write import inspect_run
    from dqnlab.run.rundir import inspect_dir

    if frames <= 0:
        raise DqnlabError(f"--frames {frames} must be positive")
    out = out or inspect_dir(run_dir)
    inspection = inspect_run(
        run_dir,
        out,
        frames=frames,
        checkpoints=parse_checkpoints(checkpoints),
        observations=observations,
        seed=seed,
        device=resolve_device(device),
    )
    typer.echo(f"{inspection.env}: {inspection.note}")
    for line in inspection.summary():
        typer.echo(f"  {line}")
    typer.echo(f"dqnlab: {len(inspection.figure_paths)} figures and q_values.csv in {out}")


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
    typer.echo((resources.files("dqnlab") / "presets" / f"{name}.toml").read_text(), nl=False)


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


def _keep_freed_memory() -> None:
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


def _format_warning(message, category, filename, lineno, line=None) -> str:  # noqa: ANN001
    """dqnlab's own warnings as one line; others as Python shows them."""
    if "dqnlab" in Path(filename).parts:
        return f"dqnlab: warning: {message}\n"
    return _python_format_warning(message, category, filename, lineno, line)


_python_format_warning = warnings.formatwarning


def main() -> None:
    """Entry point: a DqnlabError ends the command with one line and exit status 2 (75
    for a run directory another process trains: `lease.LeaseHeld`)."""
    warnings.formatwarning = _format_warning
    _keep_freed_memory()
    try:
        app()
    except DqnlabError as error:
        print(f"dqnlab: error: {error}", file=sys.stderr)
        sys.exit(getattr(error, "exit_status", 2))  # 2, or a status a caller acts on
