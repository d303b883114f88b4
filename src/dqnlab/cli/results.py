"""`dqnlab evaluate`, `dqnlab report` and `dqnlab inspect`: what trained runs do, as
scores, tables, curves and Q-values."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from dqnlab.cli.common import Device, RunDir, resolve_device, write_json
from dqnlab.config import DEFAULT_EVALUATION_SEED
from dqnlab.errors import DqnlabError

if TYPE_CHECKING:
    from dqnlab.analysis.report.aggregate import AggregateSettings
    from dqnlab.run.evaluate import EvaluatedNetwork
    from dqnlab.run.play import EvaluationResult

REFERENCE_HELP = (
    "dopamine: Dopamine's published curves behind Atari games' and the on-track table; "
    "der-paper: the Atari 100k table against Data-Efficient Rainbow's published scores, which "
    "join the aggregates; none"
)
BASELINE_HELP = (
    "Human score of the aggregates across games: human (dqn_zoo's) or human_nature (the "
    "Nature paper's tester)"
)


EvaluationSettings = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        help="Play under another protocol: KEY=VALUE for eval_epsilon, eval_noise, "
        "noop_max_frames, sticky_action_probability or final_eval_max_episode_frames "
        "(repeatable; the result is then not saved as final_evaluation.json)",
    ),
]


def evaluate(
    run_dir: RunDir,
    checkpoint: Annotated[
        str | None,
        typer.Option(
            help="best, last, or the path of a checkpoint file (default: the run's "
            "final_eval_network, best unless its protocol says last, as Atari 100k's)"
        ),
    ] = None,
    episodes: Annotated[
        int | None, typer.Option(help="Games to play (default: final_eval_episodes, 30)")
    ] = None,
    json_path: Annotated[
        Path | None, typer.Option("--json", help="Write the result as JSON to this file")
    ] = None,
    seed: Annotated[
        int, typer.Option(help="Seed of the evaluation's random streams")
    ] = DEFAULT_EVALUATION_SEED,
    device: Device = "auto",
    video: Annotated[
        Path | None,
        typer.Option(help="Film every game into this directory, the score in each file name"),
    ] = None,
    video_format: Annotated[
        str, typer.Option(help="auto (MP4, GIF where no encoder), mp4 or gif")
    ] = "auto",
    set_: EvaluationSettings = None,
) -> None:
    """The Nature final protocol: games of at most 18,000 frames, epsilon 0.05, no-op starts.

    Evaluating the run's final_eval_network (the default: its best network, or its last
    under Atari 100k's protocol) also saves the result as
    RUN_DIR/final_evaluation.json, which `dqnlab report` reads, unless that file holds
    more games of the same network. With --video the games
    are played one after another on one emulator and filmed from the raw screens (every
    emulator frame, 60 frames/s); without it they are spread over every core (other
    games, the same protocol). A run trained with logger = tensorboard+wandb also gets
    the saved final evaluation and the videos in its W&B run's summary. With --set the
    same network plays under another protocol (for example eval_noise=sampled, or
    noop_max_frames=0), recorded in the result's "settings"."""
    from dqnlab.config import parse_overrides
    from dqnlab.run.evaluate import final_evaluation_record, final_network

    settings = parse_overrides(set_ or [])
    protocol_network = final_network(run_dir)
    checkpoint = checkpoint or protocol_network
    result, network, videos = _play_final_evaluation(
        run_dir, checkpoint, episodes, seed, device, video=video, video_format=video_format,
        settings=settings,
    )  # fmt: skip
    config = network.config
    typer.echo(
        f"{config.env}: {result.mean:.2f} ± {result.std:.2f} over {len(result.scores)} games "
        f"({network.path}, {result.frames} frames at {result.frames_per_second:.0f} frames/s)"
    )
    record = final_evaluation_record(result, config, network.path, network.step, seed, settings)
    _keep_record(run_dir, record, checkpoint, protocol_network, videos)
    if json_path:
        write_json(json_path, record)


def _keep_record(
    run_dir: Path,
    record: dict[str, Any],
    checkpoint: str,
    protocol_network: str,
    videos: list[Path],
) -> None:
    """Save a final evaluation of the run's protocol network as its final_evaluation.json
    (not one played under other settings), and send it and the videos to the run's W&B
    summary where the network is the run's own."""
    from dqnlab.run.wandb_log import add_to_summary, final_evaluation_values, video_media

    written = False
    if "settings" in record:
        typer.echo("dqnlab: not saved as the run's final evaluation: --set changed its protocol")
    elif checkpoint == protocol_network:
        written = _save_final_evaluation(run_dir, record)
    if checkpoint in ("best", "last"):  # the run's own network: to its W&B run, if it has one
        values = final_evaluation_values(record) if written else {}
        if add_to_summary(run_dir, values, video_media(checkpoint, videos)):
            typer.echo("dqnlab: sent to the run's W&B summary")


def _play_final_evaluation(
    run_dir: Path,
    checkpoint: str,
    episodes: int | None,
    seed: int,
    device: str,
    *,
    video: Path | None,
    video_format: str,
    settings: dict[str, Any],
) -> tuple[EvaluationResult, EvaluatedNetwork, list[Path]]:
    """The final evaluation's games of `checkpoint` (played as `settings` say), filmed into
    the directory `video` unless it is None: the result, the network and the videos (each
    one's path printed)."""
    if video is None:
        from dqnlab.run.evaluate import final_evaluation

        result, network = final_evaluation(
            run_dir, checkpoint, episodes, seed, resolve_device(device), settings=settings
        )
        return result, network, []
    from dqnlab.analysis.video import filmed_final_evaluation

    recording, network = filmed_final_evaluation(
        run_dir, checkpoint, episodes, seed, resolve_device(device), video, video_format,
        settings,
    )  # fmt: skip
    for file in recording.paths:
        typer.echo(f"dqnlab: wrote {file}")
    if recording.note:
        typer.echo(f"dqnlab: {recording.video_format.upper()}: {recording.note}")
    return recording.result, network, recording.paths


def _save_final_evaluation(run_dir: Path, record: dict[str, Any]) -> bool:
    """Save `record` as the run's final evaluation unless the saved one holds more games of
    the same network; whether it was saved."""
    from dqnlab.run.rundir import load_final_evaluation, record_final_evaluation

    path, written = record_final_evaluation(run_dir, record)
    if written:
        typer.echo(f"dqnlab: saved as {path}")
    else:
        saved = load_final_evaluation(run_dir) or {}
        typer.echo(f"dqnlab: kept {path}: it holds {saved.get('episodes')} games of this network")
    return written


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
    device: Device = "auto",
    reference: Annotated[str, typer.Option(help=REFERENCE_HELP)] = "dopamine",
    baseline: Annotated[str, typer.Option(help=BASELINE_HELP)] = "human",
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
    Behind each Atari game's curves, Dopamine's published curve of each agent whose parts
    a configuration has (DQN, C51, its compact Rainbow; another protocol, labelled), and an
    "on track?" table: each run's latest 1M-frame window of training games against its
    agent's curve; unfinished runs are accepted (with a note). Under the curves,
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
        out = _report_dir(run_dirs)
    report_runs(run_dirs, out, episodes, device, frames, reference, aggregate)


def _report_dir(run_dirs: list[Path]) -> Path:
    """SWEEP/report for one sweep directory, else ./report."""
    from dqnlab.run.rundir import is_run_dir

    one_sweep = len(run_dirs) == 1 and not is_run_dir(run_dirs[0])
    return run_dirs[0] / "report" if one_sweep else Path("report")


def report_runs(
    run_dirs: list[Path],
    out: Path,
    episodes: int | None,
    device: str,
    frames: int = 4,
    reference: str = "dopamine",
    aggregate: AggregateSettings | None = None,
) -> None:
    """Write the report of `run_dirs` into `out` and print its table and where its files are."""
    from dqnlab.analysis.report import final_network_evaluator, format_table, write_report

    torch_device = resolve_device(device)
    written = write_report(
        run_dirs,
        out,
        evaluate_missing=final_network_evaluator(torch_device, episodes=episodes),
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


def inspect(
    run_dir: RunDir,
    frames: Annotated[int, typer.Option(help="Frames picked from one evaluation game")] = 8,
    checkpoints: Annotated[
        str | None,
        typer.Option(
            help="Networks compared: best, worst and/or evaluation steps, comma-separated "
            "(default best,worst; an exported folder has only best)"
        ),
    ] = None,
    observations: Annotated[
        Path | None,
        typer.Option(help="A .npy of stacked network inputs to use instead of picked frames"),
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="Output directory (default RUN_DIR/inspect)")
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of the game the frames are picked from")] = 0,
    device: Device = "auto",
) -> None:
    """Q-values per action of several networks of a run on the same frames (the seed paper's
    best-against-worst figure).

    Frames are spread over the best network's first evaluation game (or read from
    --observations, e.g. an earlier inspection's observations.npy). Writes a figure per
    frame (the screen and a bar per action and network, greedy actions hatched),
    overview.png, q_values.csv and the inputs. worst is the network of the lowest
    periodic evaluation after the first quarter of training; steps need
    eval_networks_kept = "all". An exported or pulled folder has one network (best)."""
    from dqnlab.analysis.inspection.qvalues import parse_checkpoints
    from dqnlab.analysis.inspection.write import inspect_run
    from dqnlab.run.exported import is_exported_dir
    from dqnlab.run.rundir import inspect_dir

    if checkpoints is None:
        checkpoints = "best" if is_exported_dir(run_dir) else "best,worst"

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
