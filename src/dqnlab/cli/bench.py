"""`dqnlab bench`: how fast dqnlab runs on this machine, one subcommand per question:
throughput, envs, variants, small, checkpoint, gpu. Each prints its figures, one a line, and
writes them as JSON with --json (`report`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from dqnlab.cli.common import Device, resolve_device, write_json

app = typer.Typer(
    name="bench",
    no_args_is_help=True,
    help="Measure dqnlab on this machine: throughput, environments, the DQN family, small "
    "networks, the stop checkpoint, the GPU path.",
)


@app.callback()
def _arithmetic() -> None:
    """dqnlab's runs flush denormals to zero (`flush_denormals`, on by default): so do its
    measurements; peers run in-process keep IEEE's gradual underflow (`denormals_kept`)."""
    from dqnlab.run.denormals import set_flush_denormals

    set_flush_denormals(True)


# Options the subcommands share; each gives its own default.
Env = Annotated[str, typer.Option(help="Atari game to measure")]
Steps = Annotated[
    int,
    typer.Option(
        help="Agent steps timed in each round of training (and of evaluation, where timed)"
    ),
]
ReplayCapacity = Annotated[int, typer.Option(help="Transitions in the replay measured")]
JsonPath = Annotated[
    Path | None, typer.Option("--json", help="Write the figures as JSON to this file")
]
Peers = Annotated[
    bool, typer.Option(help="Also run Stable-Baselines3's DQN (dqnlab[bench]), alternating")
]
CleanRL = Annotated[
    Path | None,
    typer.Option(
        "--cleanrl",
        help="Also run CleanRL's dqn_atari.py from the CleanRL checkout in this folder, "
        "alternating (with or without --peers), in a venv with CleanRL's pinned versions",
    ),
]
CleanRLVenv = Annotated[
    Path | None,
    typer.Option(
        "--cleanrl-venv",
        help="The venv to run --cleanrl's script in (default: one made once under "
        "~/.cache/dqnlab from the checkout's requirements/requirements-atari.txt)",
    ),
]


def report(figures: dict[str, Any], json_path: Path | None, table: str = "") -> None:
    """Each figure on a line (floats to 4 significant digits), then `table` if given;
    the figures as JSON to `json_path` if given."""
    width = max((len(name) for name in figures), default=0)
    for name, value in figures.items():
        shown = f"{value:.4g}" if isinstance(value, float) else str(value)
        typer.echo(f"{name:{width}s} {shown}")
    if table:
        typer.echo("\n" + table)
    if json_path:
        write_json(json_path, figures)


@app.command()
def throughput(
    env: Env = "breakout",
    steps: Steps = 2000,
    replay_capacity: ReplayCapacity = 1_000_000,
    device: Device = "auto",
    peers: Peers = False,
    cleanrl: CleanRL = None,
    cleanrl_venv: CleanRLVenv = None,
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
    json_path: JsonPath = None,
) -> None:
    """Training and evaluation frames/s of the nature preset, the update against a matrix
    multiply, sampling, and the replay's memory, raw and compressed (lz4)."""
    from dqnlab.bench.throughput import run_benchmark

    figures = run_benchmark(
        env, steps, replay_capacity, resolve_device(device), peers=peers,
        compile_update=compile_update, compression_fill_steps=compression_fill_steps,
        compression_checkpoint_capacity=compression_checkpoint_capacity,
        cleanrl_dir=cleanrl, cleanrl_venv=cleanrl_venv,
    )  # fmt: skip
    report(figures, json_path)


@app.command()
def envs(
    num_envs: Annotated[
        str, typer.Option(help="The numbers of environments (num_envs) to measure, e.g. 1,2,4,8")
    ] = "1,2,4,8",
    concurrency: Annotated[
        str,
        typer.Option(help="Each count measured with each listed concurrency: none,actor-learner"),
    ] = "none",
    peers: Peers = False,
    cleanrl: CleanRL = None,
    cleanrl_venv: CleanRLVenv = None,
    checkpoint: Annotated[
        bool,
        typer.Option(
            "--checkpoint",
            help="Also the stop checkpoint's seconds and bytes, as `dqnlab bench checkpoint` "
            "measures them, in the figures and the table",
        ),
    ] = False,
    env: Env = "breakout",
    steps: Steps = 2000,
    replay_capacity: ReplayCapacity = 100_000,
    device: Device = "auto",
    json_path: JsonPath = None,
) -> None:
    """Training frames/s of the nature preset with each number of environments, the peers
    in the same rounds, and the update against a matrix multiply; a Markdown table of it
    all closes the output (issue 22's table)."""
    from dqnlab.bench.peers import prepare_peers
    from dqnlab.bench.table import format_table
    from dqnlab.bench.vector import measure_num_envs, parse_concurrency, parse_counts

    counts, modes = parse_counts(num_envs), tuple(parse_concurrency(concurrency))
    torch_device = resolve_device(device)
    peer = prepare_peers(peers, cleanrl, cleanrl_venv)
    figures = measure_num_envs(
        counts, env, steps, replay_capacity, torch_device,
        concurrency=modes, peers=peers, cleanrl=peer,
    )  # fmt: skip
    if checkpoint:
        from dqnlab.bench.checkpoint import measure_stop_checkpoint

        stop = measure_stop_checkpoint(env, device=torch_device)
        figures.update({k: v for k, v in stop.items() if k.startswith("checkpoint")})
    report(figures, json_path, table=format_table(figures))


@app.command()
def variants(
    names: Annotated[
        str,
        typer.Argument(
            help="Shipped presets, comma-separated, or all (nature, double, dueling, "
            "prioritized, c51, rainbow, qrdqn, iqn)"
        ),
    ] = "all",
    env: Env = "breakout",
    steps: Steps = 2000,
    replay_capacity: ReplayCapacity = 100_000,
    device: Device = "auto",
    json_path: JsonPath = None,
) -> None:
    """Each preset's minibatch draw, update and training frames/s side by side, and the
    prioritized draw on a full 1M-slot replay."""
    from dqnlab.bench.variants import measure_variants, parse_variants

    presets = parse_variants(names)
    figures = measure_variants(presets, env, steps, replay_capacity, resolve_device(device))
    report(figures, json_path)


@app.command()
def small(
    steps: Steps = 5000,
    rounds: Annotated[
        int, typer.Option(min=1, help="Rounds of training, dqnlab's and SB3's alternating")
    ] = 2,
    peers: Peers = False,
    device: Device = "cpu",
    json_path: JsonPath = None,
) -> None:
    """Updates per second of the small networks (CartPole's MLP, MinAtar's small CNN, DER's
    network), each against its dense operations alone, and the classic preset's training
    steps/s on CartPole-v1 (with --peers, against Stable-Baselines3's DQN with the same
    settings, alternating)."""
    from dqnlab.bench.peers import prepare_peers
    from dqnlab.bench.small import measure_small_networks

    prepare_peers(peers, None, None)
    figures = measure_small_networks(steps, rounds, resolve_device(device), peers=peers)
    report(figures, json_path)


@app.command()
def checkpoint(env: Env = "breakout", device: Device = "auto", json_path: JsonPath = None) -> None:
    """The seconds and bytes of the nature preset's stop checkpoint after 25,000 steps of
    random play, raw and lz4, and whether it loads the same."""
    from dqnlab.bench.checkpoint import measure_stop_checkpoint

    report(measure_stop_checkpoint(env, device=resolve_device(device)), json_path)


@app.command()
def gpu(
    quick: Annotated[
        bool, typer.Option("--quick", help="A tiny budget (seconds on a CPU)")
    ] = False,
    env: Env = "breakout",
    device: Device = "auto",
    budget: Annotated[
        float | None,
        typer.Option(
            help="Seconds after which the sections not yet begun are skipped (default: 7 "
            "minutes, for the 8-minute target)"
        ),
    ] = None,
    only: Annotated[
        str | None,
        typer.Option(
            help="The sections to run, comma-separated (default all; a wrong name lists them)"
        ),
    ] = None,
    json_path: Annotated[
        Path, typer.Option("--json", help="Write the figures as JSON to this file")
    ] = Path("bench-gpu.json"),
) -> None:
    """The GPU path's figures: the update with and without update_graph, frames/s with 1,
    8, 16 and 32 environments and with an actor thread, and a CPU update matched on the
    GPU (under 8 minutes on one H100/H200; the CUDA-only sections are skipped without
    CUDA)."""
    from dqnlab.bench.gpu import BUDGET_SECONDS, run_gpu_benchmark

    sections = frozenset(filter(None, (only or "").split(","))) or None
    figures = run_gpu_benchmark(
        resolve_device(device), quick=quick, env=env,
        echo=lambda line: typer.echo(line, err=True),
        budget_seconds=BUDGET_SECONDS if budget is None else budget, only=sections,
    )  # fmt: skip
    report(figures, json_path)
