"""What a run writes while it trains: CSV files of episodes and evaluations, TensorBoard."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

EPISODE_FIELDS = ("step", "frames", "episode", "score", "steps", "epsilon", "wall_seconds")
EVALUATION_FIELDS = (
    "step", "frames", "mean", "std", "episodes", "steps", "best_mean", "frames_per_second",
    "wall_seconds",
)  # fmt: skip


class RunLogger:
    """Appends rows to `episodes.csv` and `evaluations.csv` and scalars to TensorBoard."""

    def __init__(self, run_dir: Path, tensorboard: bool = True) -> None:
        self.run_dir = run_dir
        self._files = {}
        self._writers = {}
        for name, fields in (("episodes", EPISODE_FIELDS), ("evaluations", EVALUATION_FIELDS)):
            path = run_dir / f"{name}.csv"
            new = not path.exists()
            handle = path.open("a", newline="")
            writer = csv.DictWriter(handle, fieldnames=fields)
            if new:
                writer.writeheader()
            self._files[name] = handle
            self._writers[name] = writer
        self.tensorboard = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.tensorboard = SummaryWriter(log_dir=str(run_dir / "tensorboard"))

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

    def scalars(self, step: int, values: dict[str, float]) -> None:
        if self.tensorboard:
            for name, value in values.items():
                self.tensorboard.add_scalar(name, value, step)

    def flush(self) -> None:
        for handle in self._files.values():
            handle.flush()
        if self.tensorboard:
            self.tensorboard.flush()

    def close(self) -> None:
        self.flush()
        for handle in self._files.values():
            handle.close()
        if self.tensorboard:
            self.tensorboard.close()


def read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))
