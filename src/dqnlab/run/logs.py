"""What a run writes while it trains: CSV files of episodes and evaluations, TensorBoard."""

from __future__ import annotations

import csv
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dqnlab.run import rundir

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter

    from dqnlab.run.wandb_log import MirroredWriter, WandbLog

# `env`: which of the run's `num_envs` environments played the game (0 with one).
EPISODE_FIELDS = (
    "step", "frames", "episode", "score", "steps", "epsilon", "wall_seconds", "env",
)  # fmt: skip
# Logged rows reach the file (the OS's page cache, not an fsync) at most this long after
# they were logged, so that `tail -f`, a plotting script or a report reads a live run.
FRESH_SECONDS = 30.0
EVALUATION_FIELDS = (
    "step", "frames", "mean", "std", "episodes", "steps", "best_mean", "frames_per_second",
    "wall_seconds", "heldout_max_q", "heldout_td_error",
)  # fmt: skip


class RunLogger:
    """Appends rows to `episodes.csv` and `evaluations.csv` and scalars to TensorBoard,
    and with `wandb_log` the same scalars to W&B.

    `resume_step`: the step of the checkpoint a run resumes from (0: none, start over).
    Rows and events logged after it (by the run that was killed) are dropped, since the
    resumed run logs them again: no duplicates, no gaps. W&B cannot drop steps:
    `wandb_log` sends only those W&B does not hold yet (`wandb_log.WandbLog`).
    `evaluations_resume_step`, where given, is evaluations.csv's instead: the rows of the
    evaluations the checkpoint left playing in the background (`background_eval`) are
    dropped too, since they come back again. (TensorBoard purges by step for all tags at
    once, so the events of such an evaluation recorded after the checkpoint by the killed
    run stay beside the resumed run's: the same step and values, twice.)
    """

    def __init__(
        self,
        run_dir: Path,
        tensorboard: bool = True,
        resume_step: int | None = None,
        wandb_log: WandbLog | None = None,
        evaluations_resume_step: int | None = None,
    ) -> None:
        self.run_dir = run_dir
        self._files = {}
        self._writers = {}
        if evaluations_resume_step is None:
            evaluations_resume_step = resume_step
        files = (
            ("episodes", rundir.episodes_path(run_dir), EPISODE_FIELDS, resume_step),
            (
                "evaluations",
                rundir.evaluations_path(run_dir),
                EVALUATION_FIELDS,
                evaluations_resume_step,
            ),
        )
        for name, path, fields, kept_up_to in files:
            if kept_up_to is not None and path.exists():
                truncate_after(path, kept_up_to)
            if path.exists():
                _extend_header(path, fields)
            new = not path.exists()
            handle = path.open("a", newline="")
            writer = csv.DictWriter(handle, fieldnames=fields)
            if new:
                writer.writeheader()
                handle.flush()
            self._files[name] = handle
            self._writers[name] = writer
        self.tensorboard: SummaryWriter | MirroredWriter | None = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.tensorboard = SummaryWriter(
                log_dir=str(rundir.tensorboard_dir(run_dir)),
                purge_step=None if resume_step is None else resume_step + 1,
            )
        self.wandb_log = wandb_log
        if wandb_log is not None:  # every scalar below also goes to W&B, at the same step
            self.tensorboard = wandb_log.mirroring(self.tensorboard)
        self._pushed_at = time.monotonic()

    def episode(self, row: dict[str, Any]) -> None:
        self._writers["episodes"].writerow(row)
        if self.tensorboard:
            self.tensorboard.add_scalar("train/episode_score", row["score"], row["step"])

    def evaluation(self, row: dict[str, Any]) -> None:
        self._writers["evaluations"].writerow(row)
        self._files["evaluations"].flush()
        if self.tensorboard:
            self.tensorboard.add_scalar("eval/mean_score", row["mean"], row["step"])
            self.tensorboard.add_scalar("eval/episodes", row["episodes"], row["step"])
            if row.get("heldout_max_q") is not None:  # Nature Fig. 2 (algorithm/heldout.py)
                self.tensorboard.add_scalar("eval/heldout_max_q", row["heldout_max_q"], row["step"])
                self.tensorboard.add_scalar(
                    "eval/heldout_td_error", row["heldout_td_error"], row["step"]
                )

    def scalars(self, step: int, values: dict[str, float]) -> None:
        if self.tensorboard:
            for name, value in values.items():
                self.tensorboard.add_scalar(name, value, step)

    def keep_fresh(self, at_once: bool = False) -> None:
        """Push what was logged to the files once FRESH_SECONDS have passed since the last
        push (the training loop calls this every step: it costs a clock read), or
        `at_once` (before an evaluation, which takes minutes)."""
        if at_once or time.monotonic() - self._pushed_at >= FRESH_SECONDS:
            for handle in self._files.values():
                handle.flush()
            if self.tensorboard:
                self.tensorboard.flush()
            self._pushed_at = time.monotonic()

    def flush(self) -> None:
        """Everything logged so far reaches the disk (called before every checkpoint)."""
        for handle in self._files.values():
            handle.flush()
            os.fsync(handle.fileno())
        if self.tensorboard:
            self.tensorboard.flush()
        if self.wandb_log is not None:
            self.wandb_log.commit()

    def close(self) -> None:
        self.flush()
        for handle in self._files.values():
            handle.close()
        if self.tensorboard:
            self.tensorboard.close()
        if self.wandb_log is not None:
            self.wandb_log.close()


def truncate_after(path: Path, step: int) -> None:
    """Keep the header and the rows whose step is at most `step`; drop a torn last line."""
    lines = path.read_text().splitlines(keepends=True)
    kept = lines[:1]
    for line in lines[1:]:
        if not line.endswith("\n"):
            break  # half-written by a killed process
        if int(line.split(",", 1)[0]) <= step:
            kept.append(line)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text("".join(kept))
    os.replace(temporary, path)


def _extend_header(path: Path, fields: tuple[str, ...]) -> None:
    """A file written by an older dqnlab, whose columns are the first of `fields`, gets
    the new columns in its header (its rows leave them empty), so appended rows line up."""
    with path.open(newline="") as handle:
        header = handle.readline().rstrip("\r\n").split(",")
    if tuple(header) == fields or tuple(header) != fields[: len(header)]:
        return
    lines = path.read_text().splitlines(keepends=True)
    lines[0] = ",".join(fields) + "\n"
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text("".join(lines))
    os.replace(temporary, path)


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))
