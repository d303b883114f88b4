"""`dqnlab bench`: throughput, memory and the compressed replay on this machine, the
compressed frame size of every game, or what Ray adds to a sweep."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from dqnlab.cli.common import Device, resolve_device, write_json
from dqnlab.errors import DqnlabError

if TYPE_CHECKING:
    import torch


def bench(
    env: Annotated[str, typer.Option(help="Atari game to measure")] = "breakout",
    steps: Annotated[
        int, typer.Option(help="Agent steps timed for training and for evaluation")
    ] = 2000,
    replay_capacity: Annotated[
        int | None,
        typer.Option(
            help="Transitions in the replay measured (default 1,000,000; 100,000 per variant "
            "with --variants)"
        ),
    ] = None,
    json_path: Annotated[
        Path | None, typer.Option("--json", help="Write the figures as JSON to this file")
    ] = None,
    device: Device = "auto",
    peers: Annotated[
        bool, typer.Option(help="Also run Stable-Baselines3's DQN (dqnlab[bench]), alternating")
    ] = False,
    cleanrl: Annotated[
        Path | None,
        typer.Option(
            help="Also run CleanRL's dqn_atari.py from the CleanRL checkout in this folder, "
            "alternating (with or without --peers), in a venv with CleanRL's pinned versions"
        ),
    ] = None,
    cleanrl_venv: Annotated[
        Path | None,
        typer.Option(
            help="The venv to run --cleanrl's script in (default: one made once under "
            "~/.cache/dqnlab from the checkout's requirements/requirements-atari.txt)"
        ),
    ] = None,
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
    variants: Annotated[
        str | None,
        typer.Option(
            help="Instead of the rest: each listed preset's minibatch draw, update and "
            "training frames/s side by side (all: nature, double, dueling, prioritized, c51, "
            "rainbow), and the prioritized draw on a full 1M-slot replay",
        ),
    ] = None,
    checkpoint: Annotated[
        bool,
        typer.Option(
            "--checkpoint",
            help="Instead of the rest (or with --num-envs, beside it): the seconds and bytes "
            "of the nature preset's stop checkpoint after 25,000 steps of random play, raw "
            "and lz4",
        ),
    ] = False,
    gpu: Annotated[
        bool,
        typer.Option(
            "--gpu",
            help="Instead of the rest: the GPU path's figures (update ms with and without "
            "update_graph, frames/s, the CPU's update matched), to --json (default "
            "bench-gpu.json); --quick for a tiny budget",
        ),
    ] = False,
    quick: Annotated[bool, typer.Option("--quick", help="--gpu with a tiny budget")] = False,
    num_envs: Annotated[
        str | None,
        typer.Option(
            help="Instead of the rest: training frames/s of the nature preset with each "
            "listed number of environments (num_envs), e.g. 1,2,4,8, and the update against "
            "the matrix multiply; --peers, --cleanrl and --checkpoint join it, and a table "
            "of all of it closes the output",
        ),
    ] = None,
    concurrency: Annotated[
        str,
        typer.Option(
            help="With --num-envs: each count measured with each listed concurrency, e.g. "
            "none,actor-learner"
        ),
    ] = "none",
    emulators: Annotated[
        int | None,
        typer.Option(
            help="Instead of the rest: agent steps/s of this many emulators stepped by "
            "dqnlab in one process against ale-py's threaded vector environment (1 and 2 "
            "threads), the same preprocessing each way",
        ),
    ] = None,
    sweep_runs: Annotated[
        int, typer.Option(help="Tiny CartPole runs trained each way in each --sweep repeat")
    ] = 4,
    sweep_repeats: Annotated[
        int, typer.Option(help="Times --sweep trains the runs by hand and by the sweep, in turn")
    ] = 2,
) -> None:
    """Measure training and evaluation throughput, the update, and replay memory use (with
    --variants: the same for each member of the DQN family; with --sweep: what Ray adds to
    a sweep's runs, and how soon a lost node's run trains again)."""
    from dqnlab.bench.throughput import run_benchmark

    if gpu:
        from dqnlab.bench.gpu import write_gpu_benchmark

        write_gpu_benchmark(
            json_path or Path("bench-gpu.json"), str(resolve_device(device)), quick, env
        )
        return
    if emulators is not None:
        from dqnlab.bench.emulators import measure_emulators

        if emulators < 1:
            raise DqnlabError(f"--emulators {emulators}: give at least 1")
        figures = measure_emulators(emulators, steps=max(1, steps // emulators), game=env)
        for name, value in figures.items():
            typer.echo(
                f"{name:45s} {value:.4g}" if isinstance(value, float) else f"{name:45s} {value}"
            )
        if json_path:
            write_json(json_path, figures)
        return
    if compression_scan is not None:
        from dqnlab.bench.compression import write_scan

        write_scan(compression_scan, scan_steps, echo=typer.echo)
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
    elif num_envs is not None:
        figures = _table(
            num_envs, concurrency, env, steps, replay_capacity, resolve_device(device),
            peers, cleanrl, cleanrl_venv, checkpoint,
        )  # fmt: skip
    elif checkpoint:
        from dqnlab.bench.checkpoint import measure_stop_checkpoint

        figures = measure_stop_checkpoint(env, device=resolve_device(device))
    elif variants is not None:
        from dqnlab.bench.variants import measure_variants, parse_variants

        figures = measure_variants(
            parse_variants(variants),
            env,
            steps,
            replay_capacity or 100_000,
            resolve_device(device),
        )
    else:
        figures = run_benchmark(
            env,
            steps,
            replay_capacity or 1_000_000,
            resolve_device(device),
            peers=peers,
            compile_update=compile_update,
            compression_fill_steps=compression_fill_steps,
            compression_checkpoint_capacity=compression_checkpoint_capacity,
            cleanrl_dir=cleanrl,
            cleanrl_venv=cleanrl_venv,
        )
    for name, value in figures.items():
        typer.echo(f"{name:40s} {value:.4g}" if isinstance(value, float) else f"{name:40s} {value}")
    if num_envs is not None:
        from dqnlab.bench.table import format_table

        typer.echo("\n" + format_table(figures))
    if json_path:
        write_json(json_path, figures)


def _table(
    num_envs: str,
    concurrency: str,
    env: str,
    steps: int,
    replay_capacity: int | None,
    device: torch.device,
    peers: bool,
    cleanrl: Path | None,
    cleanrl_venv: Path | None,
    checkpoint: bool,
) -> dict[str, Any]:
    """`--num-envs`: each count and concurrency, with the peers in the same rounds and the
    stop checkpoint when asked: issue 22's table from one command."""
    from dqnlab.bench.peers import prepare_peers
    from dqnlab.bench.vector import measure_num_envs, parse_concurrency, parse_counts

    counts, modes = parse_counts(num_envs), tuple(parse_concurrency(concurrency))
    peer = prepare_peers(peers, cleanrl, cleanrl_venv)
    figures = measure_num_envs(
        counts, env, steps, replay_capacity or 100_000, device,
        concurrency=modes, peers=peers, cleanrl=peer,
    )  # fmt: skip
    if checkpoint:
        from dqnlab.bench.checkpoint import measure_stop_checkpoint

        figures.update(
            {
                k: v
                for k, v in measure_stop_checkpoint(env, device=device).items()
                if k.startswith("checkpoint")
            }
        )
    return figures
