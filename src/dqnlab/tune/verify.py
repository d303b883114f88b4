"""A study's settings checked on seeds it never saw (`dqnlab tune --verify N`).

A study's value is a mean over a few seeds, and its best trial is the highest of many such
means, so it flatters the settings it picks. The check trains the best trial's settings
(best.toml) and the preset the study started from, each on N seeds no trial used, at the
study's budget, and plays each run's best and last networks as its final evaluation plays
them (`final_eval_episodes` games, the evaluation's default seed). The tuned settings are
worth shipping where they beat the start on these runs, with the network the run keeps
(`final_eval_network`); docs/tune.md shows each tuned task's check.

    STUDY_DIR/verify/tuned-sSEED/   the runs of best.toml's settings (dqnlab run directories)
    STUDY_DIR/verify/start-sSEED/   the runs of the starting preset's
        best.json, last.json        each network's games, as `dqnlab evaluate --json` writes
    STUDY_DIR/verify.csv            one row per run and network

Each run resumes from its newest checkpoint and an evaluation already recorded is not
played again, so the same command carries a stopped check on. With `jobs` > 1 the runs are
dealt out in turn among that many worker processes (`workers.py`), one PyTorch thread each
unless `threads` is fixed, as the study's trials are.
"""

from __future__ import annotations

import csv
import dataclasses
import statistics
import sys
from multiprocessing.queues import SimpleQueue
from pathlib import Path

import torch

from dqnlab.config import DEFAULT_EVALUATION_SEED, Config, resolve_config
from dqnlab.errors import DqnlabError
from dqnlab.run.evaluate import final_evaluation, final_evaluation_record
from dqnlab.run.rundir import prepare_run_dir, read_json_file, write_json_file
from dqnlab.run.train import train
from dqnlab.tune.study import BEST_FILE, TunePlan, study_path
from dqnlab.tune.trials import trial_config
from dqnlab.tune.workers import STOPPED, run_workers

VERIFY_DIR = "verify"
VERIFY_TABLE = "verify.csv"
# The first seed of the check, after the preset's: trials use the preset's seed and the next
# `seeds` - 1 (seeds 10 to 14 for a study of seed 0 and up to 10 seeds per trial).
FIRST_SEED_OFFSET = 10
SETTINGS = ("tuned", "start")
NETWORKS = ("best", "last")


@dataclasses.dataclass(frozen=True)
class Checked:
    """One network of one run of the check, and its games."""

    settings: str  # "tuned" (best.toml) or "start" (the study's preset)
    seed: int
    network: str  # "best" or "last"
    scores: tuple[float, ...]

    @property
    def mean(self) -> float:
        return statistics.fmean(self.scores)


class VerifyStopped(DqnlabError):
    """SIGINT or SIGTERM stopped a run of the check after its checkpoint (with `jobs`, one
    run in each job)."""

    def __init__(self, signal_name: str, *run_dirs: Path) -> None:
        where = " and ".join(map(str, run_dirs))
        each = " each" if len(run_dirs) > 1 else ""
        super().__init__(
            f"stopped by {signal_name} in {where}{each} after saving a checkpoint; the same "
            "command carries the check on"
        )
        self.exit_status = 130 if signal_name == "SIGINT" else 143
        self.signal_name, self.run_dirs = signal_name, run_dirs


def verification_seeds(plan: TunePlan, base_seed: int, count: int) -> list[int]:
    """`count` seeds that no trial of the study used."""
    first = base_seed + max(FIRST_SEED_OFFSET, plan.seeds)
    return [first + k for k in range(count)]


def verify(
    study_dir: Path,
    plan: TunePlan,
    count: int,
    device: torch.device,
    threads: int | None = None,
    jobs: int = 1,
) -> list[Checked]:
    """Train and play the check's runs (those done are kept), `jobs` at a time; write
    verify.csv, and return every network's games, tuned settings first."""
    best = study_path(study_dir, BEST_FILE)
    if not best.exists():
        raise DqnlabError(f"--verify: {best} does not exist (no trial of the study completed)")
    if jobs < 1:
        raise DqnlabError(f"--jobs {jobs}: at least one")
    start = trial_config(plan, {}, 1 if threads is None and jobs > 1 else threads)
    # best.toml holds the machine settings at their defaults: the check runs as the trials ran
    machine = {"threads": start.threads, **plan.fixed}
    tuned = resolve_config(str(best), machine, env=plan.env, total_steps=plan.steps)
    runs = [
        (
            settings,
            dataclasses.replace(config, seed=seed),
            study_dir / VERIFY_DIR / f"{settings}-s{seed}",
        )
        for settings, config in zip(SETTINGS, (tuned, start), strict=True)
        for seed in verification_seeds(plan, start.seed, count)
    ]
    if jobs > 1:  # each job trains and plays its runs; this process reads their records
        _run_jobs([runs[k::jobs] for k in range(min(jobs, len(runs)))], device)
    checked = []
    for settings, config, run_dir in runs:
        checked += _checked_run(settings, config, run_dir, device)
    write_table(study_path(study_dir, VERIFY_TABLE), checked)
    return checked


def _run_jobs(shares: list[list[tuple[str, Config, Path]]], device: torch.device) -> None:
    """Each share of the runs in its own process; stopped by a signal, the check stops in
    one line naming each job's run."""
    stopped = run_workers(_job, [(share, str(device)) for share in shares], carried_on="check")
    if stopped:
        raise VerifyStopped(stopped[0][0], *(run_dir for _, run_dir in stopped))


def _job(runs: list[tuple[str, Config, Path]], device: str, stops: SimpleQueue) -> None:
    """A worker of the check: its runs trained and played one after the other."""
    try:
        for settings, config, run_dir in runs:
            _checked_run(settings, config, run_dir, torch.device(device))
    except VerifyStopped as stop:
        stops.put((stop.signal_name, stop.run_dirs[0]))
        sys.exit(STOPPED)


def _checked_run(
    settings: str, config: Config, run_dir: Path, device: torch.device
) -> list[Checked]:
    """One run of the check trained to its budget (or carried on), then its networks played."""
    records = {network: run_dir / f"{network}.json" for network in NETWORKS}
    resume = _prepare(config, run_dir)
    if not all(path.exists() for path in records.values()):
        _train(config, run_dir, device, resume)
    checked = []
    for network, path in records.items():
        record = read_json_file(path)
        if record is None:
            result, played = final_evaluation(run_dir, network, None, DEFAULT_EVALUATION_SEED,
                                              device)  # fmt: skip
            record = final_evaluation_record(result, played.config, played.path, played.step,
                                             DEFAULT_EVALUATION_SEED)  # fmt: skip
            write_json_file(path, record)
        scores = record["scores"]
        checked.append(Checked(settings, config.seed, network, tuple(map(float, scores))))
    return checked


def _prepare(config: Config, run_dir: Path) -> bool:
    """The run directory made ready (True: it holds the run, to be carried on). One that
    holds a run of other settings, left by a check of an earlier best trial, is refused."""
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    try:
        return prepare_run_dir(run_dir, force=False, config=config)
    except DqnlabError as error:
        raise DqnlabError(
            f"--verify: {error}; it was checked with other settings (a best trial since "
            f"replaced?): delete {run_dir.parent} to check these"
        ) from None


def _train(config: Config, run_dir: Path, device: torch.device, resume: bool) -> None:
    """Train a run of the check from its start or its newest checkpoint to its budget."""
    result = train(config, run_dir, device, progress=False, tensorboard=False, resume=resume)
    if result.interrupted is not None:
        raise VerifyStopped(result.interrupted, run_dir)


def write_table(path: Path, checked: list[Checked]) -> None:
    """verify.csv: settings, seed, network, games, mean, std (over games), min, max."""
    partial = path.with_suffix(".csv.partial")
    with partial.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["settings", "seed", "network", "episodes", "mean", "std", "min", "max"])
        for row in checked:
            writer.writerow(
                [row.settings, row.seed, row.network, len(row.scores), f"{row.mean:.6g}",
                 f"{statistics.pstdev(row.scores):.6g}", f"{min(row.scores):g}",
                 f"{max(row.scores):g}"]
            )  # fmt: skip
    partial.replace(path)


def summary(checked: list[Checked], start_preset: str) -> list[str]:
    """A line per settings: each network's mean over the runs, and each run's."""
    lines = []
    for settings in SETTINGS:
        name = "tuned (best.toml)" if settings == "tuned" else f"start ({start_preset})"
        parts = []
        for network in NETWORKS:
            rows = [row for row in checked if (row.settings, row.network) == (settings, network)]
            if rows:
                runs = ", ".join(f"{row.mean:.1f}" for row in rows)
                parts.append(
                    f"{network} network {statistics.fmean(r.mean for r in rows):.2f} ({runs})"
                )
        lines.append(f"{name}: " + "; ".join(parts))
    return lines
