"""`dqnlab sweep`, `dqnlab ablate` and `dqnlab status`: grids of runs trained on Ray, and
where their runs stand."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from dqnlab.cli.common import ENV_HELP, Device, EnvKwargs, Wrappers, resolve_device, write_json
from dqnlab.cli.results import report_runs
from dqnlab.errors import DqnlabError

if TYPE_CHECKING:
    from dqnlab.sweeps.plan import SweepPlan

# Options `dqnlab sweep` and `dqnlab ablate` share.
VARY_HELP = (
    "KEY=V1,V2 (values as in --set), or linked settings KEY1+KEY2=A1+A2,B1+B2; repeat for a grid"
)
SharedSettings = Annotated[
    list[str] | None,
    typer.Option("--set", help="A setting shared by every run: KEY=VALUE (repeatable)"),
]
BasePreset = Annotated[
    str | None, typer.Option(help="Base preset (nature for Atari, classic otherwise)")
]
FirstSeed = Annotated[int, typer.Option(help="The first seed")]
RunSteps = Annotated[int | None, typer.Option(help="Training budget of each run in agent steps")]
GAMES_HELP = (
    "A game set instead of --env: nature49, atari57, atari100k (the Atari 100k benchmark's 26), "
    "or a file of games (one a line)"
)


def sweep(
    env: Annotated[
        str | None, typer.Option(help="Environments, comma-separated: pong,breakout or CartPole-v1")
    ] = None,
    games: Annotated[str | None, typer.Option(help=GAMES_HELP)] = None,
    preset: BasePreset = None,
    seeds: Annotated[int, typer.Option(help="Seeds per game and setting: SEED, SEED+1, ...")] = 1,
    seed: FirstSeed = 0,
    vary: Annotated[list[str] | None, typer.Option(help=VARY_HELP)] = None,
    set_: SharedSettings = None,
    env_kwarg: EnvKwargs = None,
    wrapper: Wrappers = None,
    steps: RunSteps = None,
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
    from dqnlab.sweeps.plan import plan_sweep_options

    plan = plan_sweep_options(
        env=env, games=games, preset=preset, seeds=seeds, first_seed=seed, vary=vary or [],
        settings=set_ or [], steps=steps, sweep_dir=sweep_dir, cpus_per_run=cpus_per_run,
        gpus_per_run=gpus_per_run, memory_per_run_gb=memory_per_run, max_retries=max_retries,
        env_kwargs=env_kwarg or [], wrappers=wrapper or [],
    )  # fmt: skip
    for warning in plan.warnings:
        typer.echo(f"dqnlab: warning: {warning}", err=True)
    _train_on_ray(plan, address, max_retries)
    _report_sweep(plan.sweep, episodes, "cpu", report)


def _train_on_ray(plan: SweepPlan, address: str, max_retries: int) -> None:
    """Train the planned runs on the Ray cluster at `address`, once `check_resources` finds
    room for a run on it."""
    from dqnlab.sweeps.cluster import connected, node_resources
    from dqnlab.sweeps.driver import run_sweep_on_ray
    from dqnlab.sweeps.resources import check_resources

    resources = plan.resources
    with connected(address):
        check_resources(resources, node_resources())
        typer.echo(
            f"dqnlab: {len(plan.sweep.runs)} runs into {plan.sweep.directory}; each asks for "
            f"{resources.cpus:g} CPUs, {resources.gpus:g} GPUs, "
            f"{resources.memory_bytes / 1e9:.1f} GB"
        )
        _run_or_stop(
            lambda: run_sweep_on_ray(
                plan.sweep,
                resources,
                device=plan.device,
                max_retries=max_retries,
                echo=typer.echo,
                live=sys.stdout.isatty(),
            )
        )


def ablate(
    env: Annotated[str, typer.Option(help=ENV_HELP)],
    vary: Annotated[list[str], typer.Option(help=VARY_HELP)],
    seeds: Annotated[int, typer.Option(help="Seeds per setting: SEED, SEED+1, ...")] = 1,
    seed: FirstSeed = 0,
    steps: RunSteps = None,
    preset: BasePreset = None,
    set_: SharedSettings = None,
    env_kwarg: EnvKwargs = None,
    wrapper: Wrappers = None,
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
    device: Device = "auto",
) -> None:
    """Train a grid of runs that differ in the --vary settings, then report them together.

    The seed paper's two ablations:

    * `dqnlab ablate --env breakout --vary life_loss_terminal=true,false`
    * `dqnlab ablate --env breakout --vary optimizer+learning_rate=deepmind_rmsprop+0.00025,rmsprop+0.00005`

    Running the same command again skips finished runs and resumes interrupted ones."""
    from dqnlab.sweeps.ablate import run_sweep
    from dqnlab.sweeps.cluster import connected
    from dqnlab.sweeps.plan import ablation_jobs, plan_ablation_options

    sweep = plan_ablation_options(
        env=env, vary=vary, preset=preset, settings=set_ or [], seeds=seeds, first_seed=seed,
        steps=steps, sweep_dir=sweep_dir, env_kwargs=env_kwarg or [], wrappers=wrapper or [],
    )  # fmt: skip
    torch_device = resolve_device(device)  # a bad --device fails here, not in every run
    jobs = ablation_jobs(sweep, jobs)
    typer.echo(f"dqnlab: {len(sweep.runs)} runs into {sweep.directory}, {jobs} at a time")
    with connected("local"):
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
        write_json(json_path, status_json(statuses))


def _report_sweep(sweep, episodes: int | None, device: str, report: bool) -> None:  # noqa: ANN001
    """A sweep's end: its report (unless not asked for), then a failed run named."""
    finished = [run.run_dir for run in sweep.runs if run.status in ("ok", "done")]
    if finished and report:
        report_runs(finished, sweep.directory / "report", episodes, device)
    if sweep.failed:
        raise DqnlabError(
            f"{len(sweep.failed)} of {len(sweep.runs)} runs failed: "
            + ", ".join(run.name for run in sweep.failed)
            + "; run the same command again to retry them"
        )


def _run_or_stop(run: Callable[[], Any]) -> None:
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
