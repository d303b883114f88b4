"""The inputs of `dqnlab sweep` and `dqnlab ablate`, as given on the command line, checked
and planned into the grid of runs (and, for a sweep, what each run asks Ray for), before
Ray is started or any run touched: a bad input is one DqnlabError, naming its option."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from dqnlab.config import atari100k_departures, parse_overrides, parse_pairs
from dqnlab.envs import check_env, default_preset
from dqnlab.errors import DqnlabError
from dqnlab.run.rundir import default_sweep_dir
from dqnlab.sweeps.ablate import default_jobs, plan_sweep
from dqnlab.sweeps.grid import Sweep, check_sweep_dir, game_set, parse_variation, plan_grid
from dqnlab.sweeps.resources import RunResources, sweep_resources


@dataclass(frozen=True)
class SweepPlan:
    """A sweep ready to run: its grid, what each run asks for, and the runs' device."""

    sweep: Sweep
    resources: RunResources
    device: str  # "cuda" where the runs ask for GPUs, else "cpu"
    warnings: tuple[str, ...] = ()  # to print before the runs start


def plan_sweep_options(
    *,
    env: str | None,
    games: str | None,
    preset: str | None,
    seeds: int,
    first_seed: int,
    vary: Sequence[str],
    settings: list[str],
    steps: int | None,
    sweep_dir: Path | None,
    cpus_per_run: float,
    gpus_per_run: float,
    memory_per_run_gb: float | None,
    max_retries: int,
    env_kwargs: Sequence[str] = (),
    wrappers: Sequence[str] = (),
) -> SweepPlan:
    """`dqnlab sweep`'s options checked in the order a user reads them: --env (comma-
        separated) or --games (`grid.game_set`), --vary and --set texts, the default sweep
        directory (sweeps/GAMES-KEYS), the grid and the directory it goes into, then each run's
        resources (memory in GB). `env_kwargs` (--env-kwarg KEY=VALUE texts) and `wrappers` are
    added to every run's env_kwargs and env_wrappers."""
    if (env is None) == (games is None):
        raise DqnlabError(
            "dqnlab sweep needs one of --env ENV[,ENV...] or --games "
            "nature49|atari57|atari100k|FILE"
        )
    if max_retries < 0:
        raise DqnlabError(f"--max-retries {max_retries} must be 0 or more")
    envs = game_set(games) if games else [name.strip() for name in (env or "").split(",")]
    envs = [name for name in envs if name]
    variations = [parse_variation(text) for text in vary]
    keys = [key for variation in variations for key in variation.keys]
    label = Path(games).stem if games else "+".join(envs)
    sweep_dir = sweep_dir or default_sweep_dir(label, keys or [f"{seeds}seeds"])
    sweep = plan_grid(
        envs, variations, preset=preset, overrides=parse_overrides(settings), seeds=seeds,
        first_seed=first_seed, steps=steps, sweep_dir=sweep_dir,
        env_kwargs=parse_pairs(list(env_kwargs), "--env-kwarg"), env_wrappers=wrappers,
    )  # fmt: skip
    check_envs(sweep)
    check_sweep_dir(sweep)
    memory = int(memory_per_run_gb * 1e9) if memory_per_run_gb is not None else None
    if memory is not None and memory <= 0:
        raise DqnlabError(f"--memory-per-run {memory_per_run_gb} must be positive")
    resources = sweep_resources(sweep, cpus_per_run, gpus_per_run, memory)
    warnings = protocol_warnings(sweep) if games == "atari100k" else ()
    return SweepPlan(sweep, resources, "cuda" if gpus_per_run > 0 else "cpu", warnings)


def protocol_warnings(sweep: Sweep) -> tuple[str, ...]:
    """One line per setting in which the sweep's runs depart from the Atari 100k protocol
    (`config.atari100k_departures`): their table is not comparable with the published one,
    which `dqnlab report` repeats."""
    departures = sorted({d for run in sweep.runs for d in atari100k_departures(run.config)})
    return tuple(
        f"--games atari100k with {departure}: this sweep does not follow the Atari 100k "
        "protocol and its scores are not comparable with the published ones"
        for departure in departures
    )


def plan_ablation_options(
    *,
    env: str,
    vary: Sequence[str],
    preset: str | None,
    settings: list[str],
    seeds: int,
    first_seed: int,
    steps: int | None,
    sweep_dir: Path | None,
    env_kwargs: Sequence[str] = (),
    wrappers: Sequence[str] = (),
) -> Sweep:
    """`dqnlab ablate`'s options checked: the environment, the --vary and --set texts, the
    default preset (`envs.default_preset`) and sweep directory
    (sweeps/ENV-KEYS), the grid (`ablate.plan_sweep`), the environment of each run (with
    --env-kwarg and --wrapper added) and the directory it goes into."""
    variations = [parse_variation(text) for text in vary]
    keys = [key for variation in variations for key in variation.keys]
    sweep_dir = sweep_dir or default_sweep_dir(env, keys)
    sweep = plan_sweep(
        env,
        variations,
        preset=preset or default_preset(env),
        overrides=parse_overrides(settings),
        seeds=seeds,
        first_seed=first_seed,
        steps=steps,
        sweep_dir=sweep_dir,
        env_kwargs=parse_pairs(list(env_kwargs), "--env-kwarg"),
        env_wrappers=wrappers,
    )
    check_envs(sweep)
    check_sweep_dir(sweep)
    return sweep


def check_envs(sweep: Sweep) -> None:
    """Each environment the sweep's runs build (name, env_kwargs, env_wrappers) made once
    and checked, before any run starts: --vary may give env_kwargs several values."""
    checked: list[tuple[str, dict, tuple[str, ...]]] = []
    for run in sweep.runs:
        config = run.config
        key = (config.env, config.env_kwargs, config.env_wrappers)
        if key not in checked:
            checked.append(key)
            check_env(config)


def ablation_jobs(sweep: Sweep, jobs: int | None) -> int:
    """`dqnlab ablate --jobs`, checked, or as many runs as the machine has room for
    (`ablate.default_jobs`)."""
    if jobs is not None and jobs <= 0:
        raise DqnlabError(f"--jobs {jobs} must be positive")
    return jobs or default_jobs(sweep)
