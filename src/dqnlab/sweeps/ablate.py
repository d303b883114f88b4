"""Ablations: a small grid of runs on one environment that differ in named settings, the
short form of a sweep (`sweeps.driver`), on the same engine.

`dqnlab ablate --env breakout --vary life_loss_terminal=true,false --seeds 2` trains
breakout-{life_loss_terminal=true,false}-s{0,1}, each with `dqnlab train` in its own
process and run directory, as Ray tasks on this machine (side by side where the machine has
room), then reports them together. Settings that must change together are linked with `+`:
`--vary optimizer+learning_rate=deepmind_rmsprop+0.00025,rmsprop+0.00005` is the seed
paper's optimizer comparison (two runs, not four).

Running the same command again carries on: finished runs are skipped and interrupted ones
resume from their newest checkpoint (`dqnlab train` on an existing run directory).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import psutil

from dqnlab.errors import ConfigError
from dqnlab.sweeps.driver import run_sweep_on_ray
from dqnlab.sweeps.grid import (
    PlannedRun,
    Sweep,
    Variation,
    check_sweep_dir,
    parse_variation,
    plan_grid,
)
from dqnlab.sweeps.resources import RunResources, run_memory_bytes

__all__ = [
    "PlannedRun", "Sweep", "Variation", "check_sweep_dir", "default_jobs", "parse_variation",
    "plan_sweep", "run_sweep",
]  # fmt: skip


def plan_sweep(
    env: str,
    variations: Sequence[Variation],
    *,
    preset: str,
    overrides: dict[str, Any],
    seeds: int,
    first_seed: int,
    steps: int | None,
    sweep_dir: Path,
    env_kwargs: dict[str, Any] | None = None,
    env_wrappers: Sequence[str] = (),
) -> Sweep:
    """Every run of the grid (the product of the variations, times the seeds) on `env`,
    named SETTINGS-sSEED, each config resolved and validated before anything starts
    (`grid.plan_grid`, which adds `env_kwargs` and `env_wrappers`)."""
    if not variations:
        raise ConfigError("ablate needs at least one --vary KEY=V1,V2")
    return plan_grid(
        [env], variations, preset=preset, overrides=overrides, seeds=seeds,
        first_seed=first_seed, steps=steps, sweep_dir=sweep_dir, env_in_names=False,
        env_kwargs=env_kwargs, env_wrappers=env_wrappers,
    )  # fmt: skip


def default_jobs(sweep: Sweep) -> int:
    """Runs side by side where the machine has room: two cores per run (the update keeps
    both cores of a 2-core machine busy), and each run's memory must fit in 80% of the
    available memory."""
    by_cores = max(1, (psutil.cpu_count() or 1) // 2)
    per_run = max(run_memory_bytes(run.config) for run in sweep.runs)
    by_memory = max(1, int(psutil.virtual_memory().available * 0.8 // per_run))
    return max(1, min(len(sweep.runs), by_cores, by_memory))


def run_sweep(
    sweep: Sweep,
    *,
    jobs: int,
    device: str,
    echo: Callable[[str], Any] = print,
    poll_seconds: float = 0.5,
    live: bool = False,
) -> Sweep:
    """Train every run not yet finished, `jobs` at a time, on the Ray this process is
    connected to: each run asks for the machine's cores over `jobs` (its PyTorch threads)
    and, on a GPU, that share of it. A failed run does not stop the others. `live`: the
    table redrawn in place (a terminal), as `run_sweep_on_ray`."""
    cores = psutil.cpu_count() or 1
    gpus = 1.0 / jobs if device.startswith("cuda") else 0.0
    # Memory is not asked for: `jobs` (default_jobs) already counts it on this machine.
    resources = RunResources(cpus=max(1, cores // jobs), gpus=gpus, memory_bytes=0)
    return run_sweep_on_ray(
        sweep, resources, device=device, echo=echo, poll_seconds=poll_seconds, live=live
    )
